/* Linearise and integrate along the motion path (the pipeline of clblur/reference.py).
 *
 * Conventions
 * - Build options: -DSTORE_HALF (linear intermediate as half4, else float4), -DPPW=<pixels
 *   per work-item>, -DHAVE_FP64 when the device has doubles.  Appended after response.cl.
 * - The linear intermediate holds one group of up to 4 channels, RGBA-interleaved, for the
 *   window (h x w) that starts at full-image (r0, c0) of an fh x fw image.
 * - Positions are computed in full-image coordinates and clamped to the full image
 *   (clamp-to-edge), then shifted into the window and clamped again as a guard, so a tile
 *   with a sufficient halo computes exactly what the untiled image does.
 * - Floating-point contraction is off: every a*b+c is rounded as written, so results do not
 *   depend on how the compiler vectorises, and integer steps stay exact.
 */
#pragma OPENCL FP_CONTRACT OFF

#ifdef HAVE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#ifdef STORE_HALF
#define STORE_T half
#define LOAD4(i) vload_half4((i), lin)
#define STORE4(v, i) vstore_half4_rte((v), (i), lin)
#else
#define STORE_T float
#define LOAD4(i) vload4((i), lin)
#define STORE4(v, i) vstore4((v), (i), lin)
#endif

#define IN_U8 0
#define IN_U16 1
#define IN_F32 2

/* Linearise one channel group: integer codes through per-channel tables (lut[k * lut_len +
 * code]); float32 input is already linear (the host applied the inverse response in float64). */
__kernel void linearise(__global const uchar *image, int in_kind, int channels, int cbase,
                        int cg, __global const float *lut, int lut_len, __global STORE_T *lin,
                        int npix)
{
    int i = get_global_id(0);
    if (i >= npix) return;
    float e[4] = {0.0f, 0.0f, 0.0f, 0.0f};
    size_t base = (size_t)i * (size_t)channels + (size_t)cbase;
    for (int k = 0; k < cg; ++k) {
        if (in_kind == IN_U8)
            e[k] = lut[k * lut_len + image[base + k]];
        else if (in_kind == IN_U16)
            e[k] = lut[k * lut_len + ((__global const ushort *)image)[base + k]];
        else
            e[k] = ((__global const float *)image)[base + k];
    }
    STORE4((float4)(e[0], e[1], e[2], e[3]), i);
}

#ifdef HAVE_FP64
/* clblur.motion.sample_counts: exact ceil(|v|) + 1 from float64 squares of the float32
 * vector, corrected with exact integer-square comparisons (contraction is off). */
static int sample_count(float vx, float vy)
{
    double x = (double)vx, y = (double)vy;
    double l2 = x * x + y * y;
    double m = ceil(sqrt(l2));
    if (m * m < l2) m += 1.0;
    if (m > 0.0 && (m - 1.0) * (m - 1.0) >= l2) m -= 1.0;
    return (int)m + 1;
}
#endif

/* floor() for the offsets (calls a slow library routine on some CPUs): truncate, then step
 * down where truncation went up (negative non-integers). */
static int floor_int(float v)
{
    int t = convert_int(v);
    return (float)t > v ? t - 1 : t;
}

/* Bilinear sample of the window at full-image position (x + fx, y + fy), x and y integers,
 * 0 <= fx, fy < 1.  Clamping the two integer neighbours to the image equals clamping the
 * position first (clamp-to-edge): beyond an edge both neighbours are the edge pixel. */
static float4 bilinear(__global const STORE_T *lin, int x, float fx, int y, float fy, int w,
                       int h, int r0, int c0, int fw, int fh)
{
    int ix0 = clamp(clamp(x, 0, fw - 1) - c0, 0, w - 1);
    int ix1 = clamp(clamp(x + 1, 0, fw - 1) - c0, 0, w - 1);
    int iy0 = clamp(clamp(y, 0, fh - 1) - r0, 0, h - 1);
    int iy1 = clamp(clamp(y + 1, 0, fh - 1) - r0, 0, h - 1);
    float4 a = LOAD4(iy0 * w + ix0), b = LOAD4(iy0 * w + ix1);
    float4 c = LOAD4(iy1 * w + ix0), d = LOAD4(iy1 * w + ix1);
    float4 top = a * (1.0f - fx) + b * fx;
    float4 bottom = c * (1.0f - fx) + d * fx;
    return top * (1.0f - fy) + bottom * fy;
}

/* Per-pixel motion field.  Sample j of pixel p lies at p - v * (j - a (N-1)) / (N-1), taken
 * as p + o with o = -(v / (N-1)) * (j - a (N-1)): exact whenever the step v / (N-1) is an
 * integer.  o is split into integer and fraction before it meets p, so the fraction keeps
 * the precision of |o| rather than of the pixel coordinate.
 * N is `fixed_n` when > 0, else counts[i] when `host_counts`, else computed here. */
__kernel void integrate_field(__global const STORE_T *lin, __global const float *flow,
                              __global const int *counts, int host_counts, int fixed_n,
                              __global const float *time_w, int weighted, float anchor,
                              int w, int h, int r0, int c0, int fw, int fh,
                              __constant const float *resp, __global const float *tables,
                              __global uchar *out, int out_kind, int channels, int cbase, int cg)
{
    int row = get_global_id(1);
    int col0 = get_global_id(0) * PPW;
    if (row >= h) return;
    int py = row + r0;
    int col_end = min(col0 + PPW, w);
    for (int col = col0; col < col_end; ++col) {
        int i = row * w + col;
        float vx = flow[2 * i], vy = flow[2 * i + 1];
        int n = fixed_n;
        if (n <= 0) {
#ifdef HAVE_FP64
            n = host_counts ? counts[i] : sample_count(vx, vy);
#else
            n = counts[i];
#endif
        }
        float den = (float)max(n - 1, 1);
        float sx = vx / den, sy = vy / den;
        float a_n1 = anchor * (float)(n - 1);
        int px = col + c0;
        float4 acc = (float4)(0.0f);
        for (int j = 0; j < n; ++j) {
            float t = (float)j - a_n1;
            float ox = -(sx * t), oy = -(sy * t);
            int ix = floor_int(ox), iy = floor_int(oy);
            float4 s = bilinear(lin, px + ix, ox - (float)ix, py + iy, oy - (float)iy, w, h,
                                r0, c0, fw, fh);
            acc += weighted ? time_w[j] * s : s;
        }
        if (!weighted) acc = acc / (float)n;
        store_pixel(acc, out, out_kind, (size_t)i, channels, cbase, cg, resp, tables);
    }
}

/* Space-invariant integer taps: g(p) = sum_t w_t L(clamp(p + d_t)).  Serves PSFs and uniform
 * motion, whose bilinear samples share their fractional parts and so rasterise exactly. */
__kernel void integrate_taps(__global const STORE_T *lin, __global const int *tap_dx,
                             __global const int *tap_dy, __global const float *tap_w, int ntaps,
                             int dx_min, int dx_max, int dy_min, int dy_max,
                             int w, int h, int r0, int c0, int fw, int fh,
                             __constant const float *resp, __global const float *tables,
                             __global uchar *out, int out_kind, int channels, int cbase, int cg)
{
    int row = get_global_id(1);
    int col0 = get_global_id(0) * PPW;
    if (row >= h) return;
    int y = row + r0;
    int col_end = min(col0 + PPW, w);
    /* Rows whose taps all stay inside the window and the image need no clamping. */
    bool rows_inside = y + dy_min >= max(r0, 0) && y + dy_max <= min(r0 + h, fh) - 1;
    int x_lo = max(c0, 0), x_hi = min(c0 + w, fw) - 1;
    for (int col = col0; col < col_end; ++col) {
        int x = col + c0;
        float4 acc = (float4)(0.0f);
        if (rows_inside && x + dx_min >= x_lo && x + dx_max <= x_hi) {
            int i = row * w + col;
            for (int t = 0; t < ntaps; ++t)
                acc += tap_w[t] * LOAD4(i + tap_dy[t] * w + tap_dx[t]);
        } else {
            for (int t = 0; t < ntaps; ++t) {
                int sx = clamp(clamp(x + tap_dx[t], 0, fw - 1) - c0, 0, w - 1);
                int sy = clamp(clamp(y + tap_dy[t], 0, fh - 1) - r0, 0, h - 1);
                acc += tap_w[t] * LOAD4(sy * w + sx);
            }
        }
        store_pixel(acc, out, out_kind, (size_t)(row * w + col), channels, cbase, cg, resp,
                    tables);
    }
}

/* Fixed-point image of a linear value: exact integers, so running sums do not drift and do
 * not depend on where a row (or a tile) starts. */
static long4 fixed_point(float4 v, float scale)
{
    return convert_long4_rte(v * scale);
}

/* Box of taps d = lo..hi along one axis, equal weights, as a running sum: cost per pixel does
 * not grow with the box length.  `axis` 0 slides along rows (one work-item per row), 1 along
 * columns (one work-item per column). */
__kernel void integrate_box(__global const STORE_T *lin, int axis, int lo, int hi, float scale,
                            int w, int h, int r0, int c0, int fw, int fh,
                            __constant const float *resp, __global const float *tables,
                            __global uchar *out, int out_kind, int channels, int cbase, int cg)
{
    int line = get_global_id(0);
    int len = axis == 0 ? w : h;            /* pixels along the line in the window */
    if (line >= (axis == 0 ? h : w)) return;
    int stride = axis == 0 ? 1 : w;          /* window index step along the line */
    int first = axis == 0 ? line * w : line; /* window index of the line's first pixel */
    int org = axis == 0 ? c0 : r0;           /* full-image coordinate of that pixel */
    int full = axis == 0 ? fw : fh;
    int count = hi - lo + 1;
    float norm = 1.0f / ((float)count * scale);
#define SRC(p) (first + clamp(clamp((p), 0, full - 1) - org, 0, len - 1) * stride)
    long4 sum = (long4)(0);
    for (int d = lo; d <= hi; ++d)
        sum += fixed_point(LOAD4(SRC(org + d)), scale);
    for (int k = 0; k < len; ++k) {
        int p = org + k;
        float4 mean = convert_float4(sum) * norm;
        store_pixel(mean, out, out_kind, (size_t)(first + k * stride), channels, cbase, cg,
                    resp, tables);
        sum += fixed_point(LOAD4(SRC(p + hi + 1)), scale) - fixed_point(LOAD4(SRC(p + lo)), scale);
    }
#undef SRC
}
