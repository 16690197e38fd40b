/* Harmonic (membrane) fill on the device: clblur/layer_planes.py harmonic_fill is the
 * specification (a cascadic multigrid over a pull-push pyramid); clblur/opencl/fill.py drives
 * these kernels.
 *
 * Conventions
 * - Build option -DCHANNELS=C (the value channels, 1..15); CP = C + 1.
 * - A pyramid level is lh x lw x CP floats, row-major: the values premultiplied by the
 *   weight, then the weight (as the reference's arrays).  All levels live in one buffer at
 *   element offsets (off).  Once its coarse-to-fine step has run (fill_up), a level holds
 *   (held, free) instead: trust * (value / max(weight, 1e-30)) per channel, then 1 - trust,
 *   what every Jacobi sweep of the level reads.
 * - An estimate is lh x lw x C floats (two ping-pong buffers sized for the finest level).
 * - One work-item per output pixel, (x, y) = (get_global_id(0), get_global_id(1)); the
 *   global size may be rounded up past the image, so every kernel checks its bounds.
 * - The arithmetic is the reference's, operation for operation, in float32 (contraction
 *   off: every a * b + c is rounded twice, as numpy and OpenCV's scalar code do):
 *   pyrUp and the 4-neighbour mean of cv2.filter2D are matched bit for bit.  cv2.pyrDown's
 *   vectorised loops sum the five taps in an order of their own (and its scalar border and
 *   tail code in another): fill_down takes the order of the vectorised loops (measured on
 *   OpenCV 5.0), so it differs from cv2 only at border and tail pixels, by an ulp.
 */
#pragma OPENCL FP_CONTRACT OFF

#ifndef CHANNELS
#define CHANNELS 3
#endif
#define CP (CHANNELS + 1)
#define TINY 1e-30f /* the reference's floor of a weight it divides by */

/* Index i of an axis of n pixels with OpenCV's BORDER_REFLECT_101 (gfedcb|abcdefgh|gfedcba);
 * an axis of one pixel maps everything to 0.  |i| < 2 n here, so one reflection suffices
 * except on the shortest axes, hence the loop. */
static int reflect101(int i, int n)
{
    if (n == 1)
        return 0;
    while (i < 0 || i >= n)
        i = i < 0 ? -i : 2 * (n - 1) - i;
    return i;
}

/* The level-0 array: values premultiplied by the weight (known: 1, else 0), then the weight.
 * values: h x w x C; known: h x w bytes (0 or 1). */
__kernel void fill_pack(__global const float *values, __global const uchar *known,
                        __global float *level, int h, int w)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h)
        return;
    size_t p = (size_t)y * w + x;
    float wt = known[p] ? 1.0f : 0.0f;
    for (int k = 0; k < CHANNELS; ++k)
        level[p * CP + k] = values[p * CHANNELS + k] * wt;  /* NaN * 0 stays NaN, as numpy */
    level[p * CP + CHANNELS] = wt;
}

/* cv2.pyrDown of the sh x sw level at src + soff into the dh x dw one at dst + doff
 * (dh = (sh + 1) / 2, dw = (sw + 1) / 2): the 5 x 5 kernel [1 4 6 4 1]^T [1 4 6 4 1] / 256,
 * reflect-101 border, at the even source pixels; first along rows, then down the columns. */
__kernel void fill_down(__global const float *src, ulong soff, int sh, int sw,
                        __global float *dst, ulong doff, int dh, int dw)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= dw || y >= dh)
        return;
    src += soff;
    dst += doff;
    size_t col[5], row[5];
    for (int t = 0; t < 5; ++t) {
        col[t] = (size_t)reflect101(2 * x + t - 2, sw) * CP;
        row[t] = (size_t)reflect101(2 * y + t - 2, sh) * sw * CP;
    }
    size_t o = ((size_t)y * dw + x) * CP;
    for (int k = 0; k < CP; ++k) {
        float r[5];
        for (int t = 0; t < 5; ++t) {
            __global const float *s = src + row[t] + k;
            float a = s[col[0]], b = s[col[1]], c = s[col[2]], d = s[col[3]], e = s[col[4]];
#if CP <= 4
            /* cv2's vectorised row pass for up to 4 interleaved channels */
            r[t] = ((a + e) + (b + d) * 4.0f) + c * 6.0f;
#else
            /* its scalar row pass (more channels than a vectorised one) */
            r[t] = ((c * 6.0f + (b + d) * 4.0f) + a) + e;
#endif
        }
        /* cv2's vectorised column pass: 4 (r1 + r3 + r2) + (r0 + r4 + 2 r2), then / 256
         * (4 x and the power-of-two scale are exact, so a fused multiply-add gives the
         * same bits) */
        float v = ((r[1] + r[3]) + r[2]) * 4.0f + ((r[0] + r[4]) + (r[2] + r[2]));
        dst[o + k] = v * (1.0f / 256.0f);
    }
}

/* The coarsest level's estimate: value / max(weight, 1e-30) (every pixel there has weight,
 * or the level is one pixel high or wide). */
__kernel void fill_coarsest(__global const float *level, ulong off, int h, int w,
                            __global float *est)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h)
        return;
    size_t p = (size_t)y * w + x;
    level += off;
    float wt = fmax(level[p * CP + CHANNELS], TINY);
    for (int k = 0; k < CHANNELS; ++k)
        est[p * CHANNELS + k] = level[p * CP + k] / wt;
}

/* Channel k of the horizontal pass of cv2.pyrUp at output column x (0 <= x < 2 sw): the
 * zero-interleaved row convolved with [1 4 6 4 1] (times 2), reflect-101 about the
 * interleaved row of 2 sw pixels, in OpenCV's scalar order and its special cases. */
static float up_row(__global const float *s, int sw, int x, int k)
{
    int j = x >> 1;
    if (sw == 1)
        return s[k] * 8.0f;
    if ((x & 1) == 0) {
        if (j == 0)
            return s[k] * 6.0f + s[CHANNELS + k] * 2.0f;
        if (j == sw - 1)
            return s[(j - 1) * CHANNELS + k] + s[j * CHANNELS + k] * 7.0f;
        return (s[(j - 1) * CHANNELS + k] + s[j * CHANNELS + k] * 6.0f)
               + s[(j + 1) * CHANNELS + k];
    }
    if (j == sw - 1)
        return s[j * CHANNELS + k] * 8.0f;
    return (s[j * CHANNELS + k] + s[(j + 1) * CHANNELS + k]) * 4.0f;
}

/* One coarse-to-fine step at a level of lh x lw (level + off, premultiplied values and
 * weight): its (held, free) written over it in place, and the estimate
 * held + free * cv2.pyrUp(coarse, dstsize=(lw, lh)) into est.  coarse: the ch x cw estimate
 * of the next coarser level (lh is 2 ch or 2 ch - 1, lw likewise).  finest != 0: the finest
 * level, whose trust is its weight itself, else min(1, 4 weight). */
__kernel void fill_up(__global float *level, ulong off, int lh, int lw,
                      __global const float *coarse, int ch, int cw,
                      __global float *est, int finest)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= lw || y >= lh)
        return;
    level += off;
    size_t p = (size_t)y * lw + x;
    float wt = level[p * CP + CHANNELS];
    float trust = finest ? wt : fmin(4.0f * wt, 1.0f);
    float free = 1.0f - trust;
    float floor_wt = fmax(wt, TINY);
    /* cv2.pyrUp's source rows about output row y: borderInterpolate(2 j, 2 ch) / 2 */
    int i = y >> 1;
    __global const float *r1 = coarse + (size_t)i * cw * CHANNELS;
    __global const float *r2 =
        coarse + (size_t)(reflect101(2 * i + 2, 2 * ch) >> 1) * cw * CHANNELS;
    __global const float *r0 =
        coarse + (size_t)(reflect101(2 * i - 2, 2 * ch) >> 1) * cw * CHANNELS;
    for (int k = 0; k < CHANNELS; ++k) {
        float b = up_row(r1, cw, x, k), c = up_row(r2, cw, x, k);
        float up;
        if (y & 1) {
            up = ((b + c) * 4.0f) * (1.0f / 64.0f);
        } else {
            float a = up_row(r0, cw, x, k);
            up = ((a + b * 6.0f) + c) * (1.0f / 64.0f);
        }
        float held = trust * (level[p * CP + k] / floor_wt);
        level[p * CP + k] = held;
        est[p * CHANNELS + k] = held + free * up;
    }
    level[p * CP + CHANNELS] = free;
}

/* One Jacobi sweep at a level of lh x lw whose (held, free) are at level + off:
 * dst = held + free * mean of src's 4 neighbours (replicate border), the mean summed as
 * cv2.filter2D sums the nonzero taps of its kernel (up, left, right, down; a quarter each). */
__kernel void fill_sweep(__global const float *level, ulong off, int lh, int lw,
                         __global const float *src, __global float *dst)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= lw || y >= lh)
        return;
    level += off;
    size_t p = (size_t)y * lw + x;
    size_t up = (size_t)max(y - 1, 0) * lw + x, down = (size_t)min(y + 1, lh - 1) * lw + x;
    size_t left = p - (x > 0), right = p + (x < lw - 1);
    float free = level[p * CP + CHANNELS];
    for (int k = 0; k < CHANNELS; ++k) {
        float m = ((src[up * CHANNELS + k] * 0.25f + src[left * CHANNELS + k] * 0.25f)
                   + src[right * CHANNELS + k] * 0.25f) + src[down * CHANNELS + k] * 0.25f;
        dst[p * CHANNELS + k] = level[p * CP + k] + free * m;
    }
}

/* sweeps Jacobi sweeps as fill_sweep at a small level by one work-group (any size): from a
 * to b, then back, ...; the result is in a if sweeps is even, else in b.  The barrier
 * between sweeps (global fence: the estimates stay in global memory, so any level size and
 * channel count fit) replaces a launch per sweep, which costs far more than a sweep of a
 * level of a few thousand pixels. */
__kernel void fill_sweeps_group(__global const float *level, ulong off, int lh, int lw,
                                __global float *a, __global float *b, int sweeps)
{
    level += off;
    int n = lh * lw, step = get_local_size(0) * get_local_size(1);
    int first = get_local_id(1) * get_local_size(0) + get_local_id(0);
    for (int s = 0; s < sweeps; ++s) {
        __global const float *src = (s & 1) ? b : a;
        __global float *dst = (s & 1) ? a : b;
        for (int q = first; q < n; q += step) {
            int y = q / lw, x = q - y * lw;
            size_t p = q;
            size_t up = (size_t)max(y - 1, 0) * lw + x;
            size_t down = (size_t)min(y + 1, lh - 1) * lw + x;
            size_t left = p - (x > 0), right = p + (x < lw - 1);
            float free = level[p * CP + CHANNELS];
            for (int k = 0; k < CHANNELS; ++k) {
                float m = ((src[up * CHANNELS + k] * 0.25f + src[left * CHANNELS + k] * 0.25f)
                           + src[right * CHANNELS + k] * 0.25f)
                          + src[down * CHANNELS + k] * 0.25f;
                dst[p * CHANNELS + k] = level[p * CP + k] + free * m;
            }
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
    }
}

/* The result: the input's value at known pixels (its bits), the estimate elsewhere. */
__kernel void fill_out(__global const float *values, __global const uchar *known,
                       __global const float *est, __global float *out, int h, int w)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h)
        return;
    size_t p = (size_t)y * w + x;
    __global const float *from = known[p] ? values : est;
    for (int k = 0; k < CHANNELS; ++k)
        out[p * CHANNELS + k] = from[p * CHANNELS + k];
}
