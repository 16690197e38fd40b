/* Linearise and integrate along the motion path (the pipeline of clblur/reference.py).
 *
 * Conventions
 * - Build options: -DSTORE_HALF (linear intermediate as half, else float), -DHAVE_FP64
 *   when the device has doubles, -DGPU_VARIANT for GPU work shapes, and the shared constants
 *   (clblur/opencl/constants.py).  This file is appended to response.cl.
 * - The kernels see a window (h x w) that lies inside the full image (a tile with its halo).
 * - The linear intermediate holds one group of up to 4 channels, RGBA-interleaved, padded to
 *   (h + 1) x (w + 1) pixels by repeating the last column and row: both horizontal
 *   neighbours of a bilinear sample come from one 8-value load, clamped or not.
 * - Clamp-to-edge is a clamp to the window: the window lies inside the image, so clamping
 *   to the image and then to the window (the reference's guard) is the same; a tile with a
 *   sufficient halo therefore computes exactly what the untiled image does.
 * - Work-items handle LANES consecutive pixels of a row (the box kernel: LANES neighbouring
 *   lines).  Per-pixel results never depend on the grouping: a lane whose taps are done adds
 *   fma(0, v, acc), which leaves acc unchanged bit for bit (v is finite, acc never -0), and
 *   box sums are exact integers, so tiles reproduce the untiled output bit for bit.
 * - Floating-point contraction is off: every a*b+c is rounded as written (or is an explicit
 *   fma), so results do not depend on how the compiler vectorises.
 */
#pragma OPENCL FP_CONTRACT OFF

#if GROUP != 4
#error "the kernels hold a channel group in a float4"
#endif

#ifdef HAVE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#ifdef STORE_HALF
#define STORE_T half
#define LOAD4(i) vload_half4((i), lin)
#define LOAD8(i) vload_half8(0, lin + 4 * (size_t)(i))     /* pixels i and i + 1 */
#define LOAD16(i) vload_half16(0, lin + 4 * (size_t)(i))   /* pixels i .. i + 3 */
#define STORE4(v, i) vstore_half4_rte((v), (i), lin)
#else
#define STORE_T float
#define LOAD4(i) vload4((i), lin)
#define LOAD8(i) vload8(0, lin + 4 * (size_t)(i))
#define LOAD16(i) vload16(0, lin + 4 * (size_t)(i))
#define STORE4(v, i) vstore4((v), (i), lin)
#endif

/* Linearise one channel group into the padded intermediate (global size (w + 1, h + 1)):
 * integer codes through per-channel tables (lut[k * lut_len + code]); float32 input is
 * already linear (linearise_float below, or the host in float64 for float64 images). */
static float linear_channel(__global const uchar *image, int in_kind, size_t index, int k,
                            __global const float *lut, int lut_len)
{
    if (in_kind == IN_U8)
        return lut[k * lut_len + image[index]];
    if (in_kind == IN_U16)
        return lut[k * lut_len + ((__global const ushort *)image)[index]];
    return ((__global const float *)image)[index];  /* IN_F32 */
}

__kernel void linearise(__global const uchar *image, int in_kind, int channels, int cbase,
                        int cg, __global const float *lut, int lut_len, __global STORE_T *lin,
                        int w, int h)
{
    int col = get_global_id(0), row = get_global_id(1);
    if (col > w || row > h) return;
    size_t base = ((size_t)min(row, h - 1) * w + min(col, w - 1)) * channels + cbase;
    float4 e = (float4)(0.0f);
    e.x = linear_channel(image, in_kind, base, 0, lut, lut_len);
    if (cg > 1) e.y = linear_channel(image, in_kind, base + 1, 1, lut, lut_len);
    if (cg > 2) e.z = linear_channel(image, in_kind, base + 2, 2, lut, lut_len);
    if (cg > 3) e.w = linear_channel(image, in_kind, base + 3, 3, lut, lut_len);
    STORE4(e, (size_t)row * (w + 1) + col);
}

/* A float32 image (pixels x channels, interleaved) -> float32 exposures of the same layout:
 * clblur.pixels.linearise in float32, eight pixels of one channel per work-item (global size
 * (ceil((stop - start) / 8), channels)), pixels [start, stop) (a band of rows).  limits[c]:
 * (top: the largest value inverted, rounded down to float32; the exposure of top itself and
 * of a full-scale value, from the host in float64; gamma exponent; 1 for a bounded response).
 * Under a bounded response values >= 1 are full scale (saturation * E_fs), values in
 * (top, 1) get top's exposure (under exp the inverse's slope 1 / (k (1 - v)) near top would
 * turn top's float32 rounding into a 1e-3 error) and the rest are clipped at 0 and
 * inverted; the unbounded linear response passes scene-linear values through, negative
 * ones included. */
#if LANES != 8
#error "linearise_float holds LANES pixels in a float8"
#endif
__kernel void linearise_float(__global const float *image, int channels, long start, long stop,
                              __constant const float *resp, __global const float *tables,
                              __constant const float8 *limits, __global float *lin)
{
    int c = get_global_id(1);
    long p0 = start + (long)get_global_id(0) * LANES;
    if (p0 >= stop || c >= channels) return;
    float a[LANES];
    for (int j = 0; j < LANES; j++)  /* past the band's end: repeat its last pixel */
        a[j] = image[min(p0 + j, stop - 1) * channels + c];
    float8 v = vload8(0, a);
    float8 lim = limits[c];
    float8 e = v;
    if (lim.s4 != 0.0f) {
        e = inverse_response8(clamp(v, 0.0f, lim.s0), resp + c * RESP_STRIDE, tables, lim.s3);
        e = select(e, (float8)(lim.s1), v > lim.s0);
        e = select(e, (float8)(lim.s2), v >= 1.0f);
    }
    vstore8(e, 0, a);
    for (int j = 0; j < LANES && p0 + j < stop; j++)
        lin[(p0 + j) * channels + c] = a[j];
}

/* linearise() into channel planes for the CPU field kernel: plane c (c < cg) of the padded
 * (h + 1) x (w + 1) intermediate starts at c * (h + 1) * (w + 1); the same values. */
__kernel void linearise_planes(__global const uchar *image, int in_kind, int channels,
                               int cbase, int cg, __global const float *lut, int lut_len,
                               __global STORE_T *lin, int w, int h)
{
    int col = get_global_id(0), row = get_global_id(1);
    if (col > w || row > h) return;
    size_t base = ((size_t)min(row, h - 1) * w + min(col, w - 1)) * channels + cbase;
    size_t at = (size_t)row * (w + 1) + col, plane_size = (size_t)(w + 1) * (size_t)(h + 1);
#ifdef STORE_HALF
#define PSTORE(c) vstore_half_rte(linear_channel(image, in_kind, base + (c), (c), lut, lut_len), \
                                  at + (c) * plane_size, lin)
#else
#define PSTORE(c) lin[at + (c) * plane_size] = linear_channel(image, in_kind, base + (c), (c), \
                                                              lut, lut_len)
#endif
    PSTORE(0);
    if (cg > 1) PSTORE(1);
    if (cg > 2) PSTORE(2);
    if (cg > 3) PSTORE(3);
#undef PSTORE
}

/* Flow vector of pixel i (float32 or half pairs).  A component that is not finite or lies
 * beyond +-FLOW_LIMIT px is counted (bad[0], bad[1]; only when `count`: a lane that repeats
 * the last pixel does not count twice) and read as 0, so a bad flow can never make the tap
 * loop unbounded; the host refuses the whole request when a count is not zero. */
static float2 read_flow(__global const uchar *flow, int flow_half, size_t i,
                        __global int *bad_flow, bool count)
{
    float2 v = flow_half ? vload_half2(i, (__global const half *)flow)
                         : vload2(i, (__global const float *)flow);
    int nonfinite = !isfinite(v.x) + !isfinite(v.y);
    int beyond = (isfinite(v.x) && fabs(v.x) > FLOW_LIMIT) +
                 (isfinite(v.y) && fabs(v.y) > FLOW_LIMIT);
    if (nonfinite + beyond) {
        if (count) {
            if (nonfinite) atomic_add(bad_flow, nonfinite);
            if (beyond) atomic_add(bad_flow + 1, beyond);
        }
        return (float2)(0.0f);
    }
    return v;
}

/* sample_count (clblur.motion.sample_counts, exact, where the device has fp64): counts.cl,
 * which precedes this file in the program (clblur.opencl.program.KERNEL_FILES). */

#ifdef HAVE_FP64
/* sample_count for LANES vectors, exact: a float32 candidate m = ceil(sqrt(l2)) is accepted
 * when (m - 1)^2 and m^2 (exact integers below 2^24) clear the float32 l2 by a relative
 * margin of 1e-6, far more than its rounding error (< 2e-7 relative), so the float64 l2 of
 * the reference lies strictly between them too; other lanes (near-integer lengths, tiny or
 * huge vectors) take the float64 route.  Zero vectors are exact either way. */
static int8 sample_counts8(float8 vx, float8 vy)
{
    float8 l2 = vx * vx + vy * vy;
    float8 root = sqrt(l2);
    float8 m = convert_float8(convert_int8(root));  /* ceil (root >= 0) without the call */
    m = select(m, m + 1.0f, m < root);
    float8 below = (m - 1.0f) * (m - 1.0f), above = m * m;
    int8 zero = vx == 0.0f && vy == 0.0f;
    int8 clear = l2 > 1e-20f && m < 4096.0f && above > l2 * (1.0f + 1e-6f) &&
                 (m == 1.0f || below < l2 * (1.0f - 1e-6f));
    int8 fast = convert_int8(m) + 1;
    fast = select(fast, (int8)(1), zero);
    if (all(clear | zero))
        return fast;
    int c[LANES], f[LANES];
    float xs[LANES], ys[LANES];
    vstore8(clear | zero, 0, c);
    vstore8(fast, 0, f);
    vstore8(vx, 0, xs);
    vstore8(vy, 0, ys);
    for (int l = 0; l < LANES; ++l)
        if (!c[l]) f[l] = sample_count(xs[l], ys[l]);
    return vload8(0, f);
}
#endif

/* The flow parameters of a kernel that integrates a per-pixel field. */
#define FIELD_PARAMS                                                                      \
    __global const uchar *flow, int flow_half, __global int *bad_flow,                     \
    __global const int *counts, int host_counts, int fixed_n, __global const float *time_w, \
    int weighted, int ends, float anchor

/* N of pixel i: host counts (devices without fp64), the fixed N, or computed here. */
static int pixel_count(float2 v, size_t i, __global const int *counts, int host_counts,
                       int fixed_n)
{
    if (host_counts) return counts[i];
#ifdef HAVE_FP64
    if (fixed_n <= 0) {
        /* the float32 candidate of sample_counts8, float64 only when it is not clear
         * (float64 is slow on many GPUs) */
        float l2 = v.x * v.x + v.y * v.y;
        float m = ceil(sqrt(l2));
        if (v.x == 0.0f && v.y == 0.0f) return 1;
        if (l2 > 1e-20f && m < 4096.0f && m * m > l2 * (1.0f + 1e-6f) &&
            (m == 1.0f || (m - 1.0f) * (m - 1.0f) < l2 * (1.0f - 1e-6f)))
            return (int)m + 1;
        return sample_count(v.x, v.y);
    }
#endif
    return fixed_n;
}

/* floor() of offsets without the library call (slow on some CPU drivers): truncate, then
 * step down where truncation went up (negative non-integers). */
static int floor_int(float v)
{
    int t = convert_int(v);
    return convert_float(t) > v ? t - 1 : t;
}

/* Store LANES consecutive pixels of a row (the first `valid` of them), starting at `pixel`,
 * from two vectors of four pixels x four channels; integer outputs are quantised 16 values
 * at a time. */
static void store_row8(float16 lo, float16 hi, size_t pixel, int valid, STORE_PARAMS)
{
    if (out_kind != OUT_F32 && valid >= LANES) {
        int16 q_lo = quantise16(lo, thresholds, buckets);
        int16 q_hi = quantise16(hi, thresholds, buckets);
        store_codes(q_lo.s0123, out, out_kind, pixel, channels, cbase, cg);
        store_codes(q_lo.s4567, out, out_kind, pixel + 1, channels, cbase, cg);
        store_codes(q_lo.s89ab, out, out_kind, pixel + 2, channels, cbase, cg);
        store_codes(q_lo.scdef, out, out_kind, pixel + 3, channels, cbase, cg);
        store_codes(q_hi.s0123, out, out_kind, pixel + 4, channels, cbase, cg);
        store_codes(q_hi.s4567, out, out_kind, pixel + 5, channels, cbase, cg);
        store_codes(q_hi.s89ab, out, out_kind, pixel + 6, channels, cbase, cg);
        store_codes(q_hi.scdef, out, out_kind, pixel + 7, channels, cbase, cg);
        return;
    }
    float4 a[LANES] = {lo.s0123, lo.s4567, lo.s89ab, lo.scdef,
                       hi.s0123, hi.s4567, hi.s89ab, hi.scdef};
    for (int l = 0; l < LANES && l < valid; ++l)
        store_pixel(a[l], pixel + l, STORE_ARGS);
}

/* Per-pixel motion field.  Sample j of pixel p lies at p + o, o = -(v / (N-1)) (j - a (N-1))
 * (the reference's p - v (j - a (N-1)) / (N-1), exact whenever the step v / (N-1) is an
 * integer).  o is split into integer and fraction before it meets p, so the fraction keeps
 * the precision of |o| rather than that of the pixel coordinate.  Every pixel sums, per tap,
 * left += fma(top-left, w_tl), left += fma(bottom-left, w_bl), right likewise with the right
 * neighbours, and ends with (left + right) / N (or without the division for time weights):
 * both variants below do exactly this, so they agree bit for bit. */
#ifndef GPU_VARIANT

/* The CPU variant: FIELD_LANES (16) consecutive pixels of a row per work-item, as vector
 * lanes, reading the intermediate as channel planes (linearise_planes): plane c of
 * (h + 1) x (w + 1) values starts at c * plane_size.  Sixteen neighbouring pixels of one
 * channel are one float16, so a tap's four bilinear weights apply lane for lane: no
 * channel-spreading shuffles, no idle fourth channel for three-channel groups, and the
 * positions and weights of 16 pixels cost what those of one vector cost. */
#ifdef STORE_HALF
/* Element by element: PoCL compiles vload_halfn at an arbitrary half offset into an aligned
 * load (a crash where it is not aligned).  Half planes are not this kernel's default (float
 * storage is faster here, run_plan), so they only have to be right. */
#define PLOAD1(p, i) vload_half((size_t)(i), (p))
#define PLOAD8_(p, i)                                                                     \
    (float8)(PLOAD1(p, (i)), PLOAD1(p, (i) + 1), PLOAD1(p, (i) + 2), PLOAD1(p, (i) + 3),      \
             PLOAD1(p, (i) + 4), PLOAD1(p, (i) + 5), PLOAD1(p, (i) + 6), PLOAD1(p, (i) + 7))
#define PLOAD16(p, i) (float16)(PLOAD8_(p, (i)), PLOAD8_(p, (i) + 8))
#else
#define PLOAD16(p, i) vload16(0, (p) + (size_t)(i))
#define PLOAD1(p, i) ((p)[(size_t)(i)])
#endif

/* Whether every lane of v is 0: an OR tree (all() and any() scalarise into chains of
 * branches on PoCL). */
static bool zero16(int16 v)
{
    int8 o8 = v.lo | v.hi;
    int4 o4 = o8.lo | o8.hi;
    int2 o2 = o4.lo | o4.hi;
    return (o2.x | o2.y) == 0;
}

/* floor() of offsets without the library call (slow on some CPU drivers), 16 lanes:
 * truncate, then step down where truncation went up (true vector compares are -1). */
static int16 floor_int16(float16 v)
{
    int16 t = convert_int16(v);
    return t + (convert_float16(t) > v);
}

/* Sixteen lanes' values of plane p at the indices in `at` (one load each). */
#define PGATHER16(p, at)                                                                  \
    (float16)(PLOAD1(p, (at).s0), PLOAD1(p, (at).s1), PLOAD1(p, (at).s2),                   \
              PLOAD1(p, (at).s3), PLOAD1(p, (at).s4), PLOAD1(p, (at).s5),                   \
              PLOAD1(p, (at).s6), PLOAD1(p, (at).s7), PLOAD1(p, (at).s8),                   \
              PLOAD1(p, (at).s9), PLOAD1(p, (at).sa), PLOAD1(p, (at).sb),                   \
              PLOAD1(p, (at).sc), PLOAD1(p, (at).sd), PLOAD1(p, (at).se),                   \
              PLOAD1(p, (at).sf))

/* One tap of channel C: left += tl w_tl, left += bl w_bl, right += tr w_tr, right += br w_br
 * (the per-pixel order of every variant), from contiguous loads (CONTIG), two contiguous
 * loads and a select (TWO) or one load per lane (GATHER). */
#define PLANE_ACC(C)                                                                      \
    left##C = fma(tl, w_tl, left##C);                                                     \
    left##C = fma(bl, w_bl, left##C);                                                     \
    right##C = fma(tr, w_tr, right##C);                                                   \
    right##C = fma(br, w_br, right##C);

/* The four taps' loads of channel C for the lanes, LOAD(p, o) reading offset o (0, 1, ws,
 * ws + 1) from the channel's plane p, then PLANE_ACC. */
#define TAPS_FROM(C, LOAD)                                                                \
    {                                                                                     \
        __global const STORE_T *p = lin + (size_t)(C) * plane_size;                       \
        float16 tl = LOAD(p, 0), tr = LOAD(p, 1);                                         \
        float16 bl = LOAD(p, ws), br = LOAD(p, ws + 1);                                   \
        PLANE_ACC(C)                                                                      \
    }

#define LOAD_CONTIG(p, o) PLOAD16(p, b + (o))
/* Lanes at two offsets (d = base - lane is d.s0 in the lanes `first`, d.sf in the others: a
 * smooth flow whose integer offset steps once across the 16 pixels). */
#define LOAD_TWO(p, o) select(PLOAD16(p, bf + (o)), PLOAD16(p, b + (o)), first)
#define LOAD_GATHER(p, o) PGATHER16(p, base + (o))

#define CONTIG(C) TAPS_FROM(C, LOAD_CONTIG)
#define TWO(C) TAPS_FROM(C, LOAD_TWO)
#define GATHER(C) TAPS_FROM(C, LOAD_GATHER)

/* One tap of the CPU field kernel for its lanes and CG channels (a constant), given base,
 * fx, upper and lower. */
#define FIELD_TAP(CG)                                                                     \
    {                                                                                     \
        float16 w_tl = (1.0f - fx) * upper, w_tr = fx * upper;                            \
        float16 w_bl = (1.0f - fx) * lower, w_br = fx * lower;                            \
        int16 d = base - lane;                                                            \
        int16 first = d == (int16)(d.s0);                                                 \
        size_t b = (size_t)d.s0;                                                          \
        if (zero16(~first)) {                                                             \
            CONTIG(0)                                                                     \
            if (CG > 1) CONTIG(1)                                                         \
            if (CG > 2) CONTIG(2)                                                         \
            if (CG > 3) CONTIG(3)                                                         \
        } else if (zero16(~(first | (d == (int16)(d.sf)))) && d.sf >= 0 &&               \
                   d.s0 <= last15) {                                                      \
            /* both loads stay inside the plane: d.sf >= 0, d.s0 + 15 <= the last pixel */ \
            size_t bf = (size_t)d.sf;                                                     \
            TWO(0)                                                                        \
            if (CG > 1) TWO(1)                                                            \
            if (CG > 2) TWO(2)                                                            \
            if (CG > 3) TWO(3)                                                            \
        } else {                                                                          \
            GATHER(0)                                                                     \
            if (CG > 1) GATHER(1)                                                         \
            if (CG > 2) GATHER(2)                                                         \
            if (CG > 3) GATHER(3)                                                         \
        }                                                                                 \
    }

/* One tap j of the CPU field kernel with clamps, edge selects and per-lane weights: a lane
 * whose N is done gets weight 0; time weights, or the continuous exposure's half weight at a
 * lane's first and last sample (ends). */
#define FIELD_GENERAL(CG, J)                                                              \
    {                                                                                     \
        float16 t = (float16)((float)(J)) - a_n1;                                         \
        float16 ox = -(sx * t), oy = -(sy * t);                                           \
        int16 ix = floor_int16(ox), iy = floor_int16(oy);                                 \
        float16 fx = ox - convert_float16(ix), fy = oy - convert_float16(iy);             \
        int16 xi = px + ix, yi = (int16)(row) + iy;                                       \
        /* Before the first pixel the sample is the first pixel; past the last, the       \
         * padding repeats the last, so the fraction does not matter there. */            \
        fx = select(fx, (float16)(0.0f), xi < 0);                                         \
        fy = select(fy, (float16)(0.0f), yi < 0);                                         \
        int16 base = clamp(yi, 0, h - 1) * ws + clamp(xi, 0, w - 1);                      \
        float16 unit = ends ? select((float16)(1.0f), (float16)(0.5f),                    \
                                     (((int16)(J) == 0) | ((int16)(J) == n - 1)) & (n > 1)) \
                            : (float16)(1.0f);                                            \
        float16 wj = select((float16)(0.0f), weighted ? (float16)(time_w[J]) : unit,      \
                            (int16)(J) < n);                                              \
        float16 upper = (1.0f - fy) * wj, lower = fy * wj;                                \
        FIELD_TAP(CG)                                                                     \
    }

/* The tap loops of the CPU field kernel for CG channels: the taps every lane takes inside
 * the window with weight 1 (jf <= j < j0), the others general (j < jf: the continuous
 * exposure's first sample; j >= j0). */
#define FIELD_LOOPS(CG)                                                                   \
    {                                                                                     \
        for (int j = 0; j < jf; ++j)                                                      \
            FIELD_GENERAL(CG, j)                                                          \
        for (int j = jf; j < j0; ++j) {                                                   \
            float16 t = (float16)((float)j) - a_n1;                                       \
            float16 ox = -(sx * t), oy = -(sy * t);                                       \
            int16 ix = floor_int16(ox), iy = floor_int16(oy);                             \
            float16 fx = ox - convert_float16(ix), fy = oy - convert_float16(iy);         \
            int16 base = ((int16)(row) + iy) * ws + px + ix;                              \
            float16 upper = 1.0f - fy, lower = fy;  /* (1 - fy) * 1 and fy * 1, exactly */\
            FIELD_TAP(CG)                                                                 \
        }                                                                                 \
        for (int j = max(j0, jf); j < nmax; ++j)                                          \
            FIELD_GENERAL(CG, j)                                                          \
    }

/* store_row8 for the CPU field kernel: whole rows of 8 RGB pixels of uint8 codes (24
 * bytes) go out as two vector stores instead of 24 byte stores.  Same codes, same places.
 * (The box kernels' code grid measured no faster here: the field's exposures are not
 * coherent enough for its 512 KiB table.) */
static void store_row8_field(float16 lo, float16 hi, size_t pixel, int valid, STORE_PARAMS)
{
    if (out_kind != OUT_U8 || valid < LANES || channels != 3 || cg != 3) {
        store_row8(lo, hi, pixel, valid, STORE_ARGS);
        return;
    }
    int16 q_lo = quantise16(lo, thresholds, buckets), q_hi = quantise16(hi, thresholds, buckets);
    uchar16 a = convert_uchar16(q_lo), b = convert_uchar16(q_hi);
    __global uchar *o = out + pixel * 3;
    vstore16((uchar16)(a.s012, a.s456, a.s89a, a.scde, b.s012, b.s4), 0, o);
    vstore8((uchar8)(b.s56, b.s89a, b.scde), 0, o + 16);
}

/* 4 pixels x 4 channels (pixels K .. K + 3 of the channel sums s0 .. s3) for store_row8. */
#define PIXELS4(K0, K1, K2, K3)                                                           \
    (float16)(s0.K0, s1.K0, s2.K0, s3.K0, s0.K1, s1.K1, s2.K1, s3.K1,                     \
              s0.K2, s1.K2, s2.K2, s3.K2, s0.K3, s1.K3, s2.K3, s3.K3)

/* The tap loop runs to the largest N among the lanes (a lane whose taps are done gets
 * weight 0, and fma(0, v, acc) leaves acc unchanged bit for bit: v is finite, acc never
 * -0).  Lanes past the window's last column repeat its last pixel and are not stored. */
__kernel void integrate_field(__global const STORE_T *lin, FIELD_PARAMS, int w, int h,
                              STORE_PARAMS)
{
    int row = get_global_id(1);
    int col0 = get_global_id(0) * FIELD_LANES;
    if (row >= h || col0 >= w) return;
    int ws = w + 1;
    size_t plane_size = (size_t)ws * (size_t)(h + 1);
    float16 vx, vy;
    int16 n = (int16)(fixed_n);
    size_t i0 = (size_t)row * w + col0;
    bool whole = col0 + FIELD_LANES <= w;
    if (whole) {  /* vector loads; bad values take the per-lane path below */
        float16 f0 = flow_half ? vload_half16(0, (__global const half *)flow + 2 * i0)
                               : vload16(0, (__global const float *)flow + 2 * i0);
        float16 f1 = flow_half ? vload_half16(0, (__global const half *)flow + 2 * i0 + 16)
                               : vload16(0, (__global const float *)flow + 2 * i0 + 16);
        vx = (float16)(f0.even, f1.even);
        vy = (float16)(f0.odd, f1.odd);
        int16 bad = !isfinite(vx) | !isfinite(vy) | (fabs(vx) > FLOW_LIMIT) |
                    (fabs(vy) > FLOW_LIMIT);
        whole = zero16(bad);
        if (host_counts) n = vload16(0, counts + i0);
    }
    if (!whole) {
        float vxs[FIELD_LANES], vys[FIELD_LANES];
        int ns[FIELD_LANES];
        for (int l = 0; l < FIELD_LANES; ++l) {
            size_t i = (size_t)row * w + min(col0 + l, w - 1);
            float2 v = read_flow(flow, flow_half, i, bad_flow, col0 + l < w);
            vxs[l] = v.x;
            vys[l] = v.y;
            ns[l] = host_counts ? counts[i] : fixed_n;
        }
        vx = vload16(0, vxs);
        vy = vload16(0, vys);
        n = vload16(0, ns);
    }
#ifdef HAVE_FP64
    if (!host_counts && fixed_n <= 0)
        n = (int16)(sample_counts8(vx.lo, vy.lo), sample_counts8(vx.hi, vy.hi));
#endif
    int8 n8 = max(n.lo, n.hi);
    int4 n4 = max(n8.lo, n8.hi);
    int2 n2 = max(n4.lo, n4.hi);
    int nmax = max(n2.x, n2.y);
    n8 = min(n.lo, n.hi);
    n4 = min(n8.lo, n8.hi);
    n2 = min(n4.lo, n4.hi);
    int nmin = min(n2.x, n2.y);
    float16 n1 = convert_float16(n - 1);
    float16 den = fmax(n1, 1.0f);
    float16 sx = vx / den, sy = vy / den;
    float16 a_n1 = anchor * n1;
    const int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    int16 px = (int16)(col0) + lane;
    float16 left0 = 0.0f, left1 = 0.0f, left2 = 0.0f, left3 = 0.0f;
    float16 right0 = 0.0f, right1 = 0.0f, right2 = 0.0f, right3 = 0.0f;
    /* Samples move monotonically with j, so the first and the last tap bound every lane's
     * positions.  When all of them (and their right/lower neighbours, which the padding
     * holds) lie inside the window and there are no time weights, the taps that every lane
     * takes (j < the smallest N) need no clamps, edge selects or per-lane weight: the same
     * values.  The remaining taps (and every tap elsewhere) take the general loop. */
    float16 t_end = (float16)((float)(nmax - 1)) - a_n1;
    int16 x_a = px + floor_int16(-(sx * -a_n1)), x_b = px + floor_int16(-(sx * t_end));
    int16 y_a = (int16)(row) + floor_int16(-(sy * -a_n1));
    int16 y_b = (int16)(row) + floor_int16(-(sy * t_end));
    int16 out_x = (min(x_a, x_b) < 0) | (max(x_a, x_b) > w - 1);
    int16 out_y = (min(y_a, y_b) < 0) | (max(y_a, y_b) > h - 1);
    bool inside = zero16(out_x | out_y);
    int last15 = (h - 1) * ws + w - 1 - 15;  /* the last pixel's index, less 15 */
    /* with ends, every lane's first sample and its last (j = n - 1 >= nmin - 1) take half
     * weight: the general loop, not the unit-weight one */
    int jf = ends ? 1 : 0;
    int j0 = inside && !weighted ? (ends ? nmin - 1 : nmin) : 0;
    if (cg == 3)  /* the loops specialised per group size: no channel tests per tap */
        FIELD_LOOPS(3)
    else if (cg == 4)
        FIELD_LOOPS(4)
    else if (cg == 2)
        FIELD_LOOPS(2)
    else
        FIELD_LOOPS(1)
    float16 s0 = left0 + right0, s1 = left1 + right1, s2 = left2 + right2, s3 = left3 + right3;
    if (!weighted) {  /* the sum of the weights: N, or N - 1 with ends (1 when N = 1) */
        float16 nf = convert_float16(ends ? max(n - 1, 1) : n);
        s0 = s0 / nf;
        s1 = s1 / nf;
        s2 = s2 / nf;
        s3 = s3 / nf;
    }
    /* back to 4 pixels x 4 channels per vector for the stores */
    size_t pixel = (size_t)row * w + col0;
    store_row8_field(PIXELS4(s0, s1, s2, s3), PIXELS4(s4, s5, s6, s7), pixel, w - col0,
                     STORE_ARGS);
    if (col0 + LANES < w)
        store_row8_field(PIXELS4(s8, s9, sa, sb), PIXELS4(sc, sd, se, sf), pixel + LANES,
                         w - col0 - LANES, STORE_ARGS);
}

#else

/* GPU variant: one pixel per work-item (no 8-lane unroll: GPUs vectorise across work-items),
 * launched in 2-D work-groups so that a group's samples stay in a compact patch. */
__kernel void integrate_field(__global const STORE_T *lin, FIELD_PARAMS, int w, int h,
                              STORE_PARAMS)
{
    int col = get_global_id(0), row = get_global_id(1);
    if (row >= h || col >= w) return;
    int ws = w + 1;
    size_t i = (size_t)row * w + col;
    float2 v = read_flow(flow, flow_half, i, bad_flow, true);
    int n = pixel_count(v, i, counts, host_counts, fixed_n);
    float n1 = (float)(n - 1);
    float den = fmax(n1, 1.0f);
    float sx = v.x / den, sy = v.y / den;
    float a_n1 = anchor * n1;
    float4 left = 0.0f, right = 0.0f;
    for (int j = 0; j < n; ++j) {
        float t = (float)j - a_n1;
        float ox = -(sx * t), oy = -(sy * t);
        int ix = floor_int(ox), iy = floor_int(oy);
        float fx = ox - (float)ix, fy = oy - (float)iy;
        int xi = col + ix, yi = row + iy;
        fx = xi < 0 ? 0.0f : fx;
        fy = yi < 0 ? 0.0f : fy;
        size_t base = (size_t)clamp(yi, 0, h - 1) * ws + clamp(xi, 0, w - 1);
        float wj = weighted ? time_w[j]
                            : (ends && n > 1 && (j == 0 || j == n - 1) ? 0.5f : 1.0f);
        float upper = (1.0f - fy) * wj, lower = fy * wj;
        float8 top = LOAD8(base), bottom = LOAD8(base + ws);
        left = fma(top.lo, (float4)((1.0f - fx) * upper), left);
        left = fma(bottom.lo, (float4)((1.0f - fx) * lower), left);
        right = fma(top.hi, (float4)(fx * upper), right);
        right = fma(bottom.hi, (float4)(fx * lower), right);
    }
    float4 sum = left + right;
    if (!weighted) sum = sum / (float)(ends ? max(n - 1, 1) : n);  /* the weights' sum */
    store_pixel(sum, i, STORE_ARGS);
}

#endif

/* Space-invariant integer taps: g(p) = sum_t w_t L(clamp(p + d_t)), accumulated in tap order
 * with one fma each.  Serves PSFs and uniform motion (whose bilinear samples share their
 * fractional parts and so rasterise exactly).  Per pixel the arithmetic is the same in every
 * path and variant, so they agree bit for bit. */
#ifndef GPU_VARIANT

/* CPU variant: LANES pixels of a row per work-item.  Work-items whose pixels read only inside
 * the window load them as contiguous vectors; others clamp per pixel. */
__kernel void integrate_taps(__global const STORE_T *lin, __global const int *tap_dx,
                             __global const int *tap_dy, __global const float *tap_w, int ntaps,
                             int dx_min, int dx_max, int dy_min, int dy_max, int w, int h,
                             STORE_PARAMS)
{
    int row = get_global_id(1);
    int col0 = get_global_id(0) * LANES;
    if (row >= h || col0 >= w) return;
    int ws = w + 1;
    float16 lo = 0.0f, hi = 0.0f;  /* pixels col0 .. col0 + 3 and col0 + 4 .. col0 + 7 */
    if (col0 + dx_min >= 0 && col0 + LANES - 1 + dx_max <= w - 1 && row + dy_min >= 0 &&
        row + dy_max <= h - 1) {
        size_t origin = (size_t)row * ws + col0;
        for (int t = 0; t < ntaps; ++t) {
            size_t src = origin + tap_dy[t] * ws + tap_dx[t];
            float16 wt = (float16)(tap_w[t]);
            lo = fma(wt, LOAD16(src), lo);
            hi = fma(wt, LOAD16(src + 4), hi);
        }
    } else {
        float4 acc[LANES];
        for (int l = 0; l < LANES; ++l) {
            int col = min(col0 + l, w - 1);
            acc[l] = 0.0f;
            for (int t = 0; t < ntaps; ++t) {
                int x = clamp(col + tap_dx[t], 0, w - 1), y = clamp(row + tap_dy[t], 0, h - 1);
                acc[l] = fma((float4)(tap_w[t]), LOAD4((size_t)y * ws + x), acc[l]);
            }
        }
        lo = (float16)(acc[0], acc[1], acc[2], acc[3]);
        hi = (float16)(acc[4], acc[5], acc[6], acc[7]);
    }
    store_row8(lo, hi, (size_t)row * w + col0, w - col0, STORE_ARGS);
}

#else

/* GPU variant: one pixel per work-item in 2-D work-groups; the group first copies the patch
 * its taps read (its own pixels plus the taps' extent, clamped) into local memory, when it
 * fits, so each input pixel is read from global memory once per group. */
#define TILE_LIMIT 2048  /* float4 entries of local memory per group (32 KiB) */

__kernel void integrate_taps(__global const STORE_T *lin, __global const int *tap_dx,
                             __global const int *tap_dy, __global const float *tap_w, int ntaps,
                             int dx_min, int dx_max, int dy_min, int dy_max, int w, int h,
                             STORE_PARAMS)
{
    __local float4 tile[TILE_LIMIT];
    int col = get_global_id(0), row = get_global_id(1);
    int gx = get_group_id(0) * get_local_size(0) + get_global_offset(0);
    int gy = get_group_id(1) * get_local_size(1) + get_global_offset(1);
    int tw = (int)get_local_size(0) + dx_max - dx_min, th = (int)get_local_size(1) + dy_max - dy_min;
    bool tiled = tw * th <= TILE_LIMIT;  /* the same for the whole group */
    int ws = w + 1;
    if (tiled) {
        int lid = get_local_id(1) * get_local_size(0) + get_local_id(0);
        int lsize = get_local_size(0) * get_local_size(1);
        for (int k = lid; k < tw * th; k += lsize) {
            int x = clamp(gx + dx_min + k % tw, 0, w - 1), y = clamp(gy + dy_min + k / tw, 0, h - 1);
            tile[k] = LOAD4((size_t)y * ws + x);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (row >= h || col >= w) return;
    float4 acc = 0.0f;
    for (int t = 0; t < ntaps; ++t) {
        float4 v;
        if (tiled) {
            v = tile[(row + tap_dy[t] - gy - dy_min) * tw + (col + tap_dx[t] - gx - dx_min)];
        } else {
            int x = clamp(col + tap_dx[t], 0, w - 1), y = clamp(row + tap_dy[t], 0, h - 1);
            v = LOAD4((size_t)y * ws + x);
        }
        acc = fma((float4)(tap_w[t]), v, acc);
    }
    store_pixel(acc, (size_t)row * w + col, STORE_ARGS);
}

#endif

/* Linearise one channel group into a float4 "plane" for the box kernel: plane row k,
 * column x holds window pixel (row k, col x), or (row x, col k) when `transposed`, so the box
 * always slides along plane rows' index k and its lanes are contiguous.  Columns from
 * `across` up to the stride `ps` repeat the last one (whole-vector loads stay in bounds). */
__kernel void linearise_plane(__global const uchar *image, int in_kind, int channels, int cbase,
                              int cg, __global const float *lut, int lut_len,
                              __global float *plane, int ps, int across, int len, int transposed,
                              int w)
{
    int x = get_global_id(0), k = get_global_id(1);
    if (x >= ps || k >= len) return;
    int a = min(x, across - 1);
    size_t pix = transposed ? (size_t)a * w + k : (size_t)k * w + a;
    size_t base = pix * channels + cbase;
    float4 e = (float4)(0.0f);
    e.x = linear_channel(image, in_kind, base, 0, lut, lut_len);
    if (cg > 1) e.y = linear_channel(image, in_kind, base + 1, 1, lut, lut_len);
    if (cg > 2) e.z = linear_channel(image, in_kind, base + 2, 2, lut, lut_len);
    if (cg > 3) e.w = linear_channel(image, in_kind, base + 3, 3, lut, lut_len);
    vstore4(e, (size_t)k * ps + x, plane);
}

/* Fixed-point image of LANES pixels (4 channels each): exact integers, so running sums
 * neither drift nor depend on where a line (or a tile) starts. */
static long16 fixed_lo(__global const float *plane, size_t at, float scale)
{
    return convert_long16_rte(vload16(0, plane + 4 * at) * scale);
}

static long16 fixed_hi(__global const float *plane, size_t at, float scale)
{
    return convert_long16_rte(vload16(0, plane + 4 * (at + 4)) * scale);
}

#define BOX_STORE(L, S)                                                                   \
    if (x0 + L < across)                                                                   \
        store_pixel(S, transposed ? (size_t)(x0 + L) * w + k : (size_t)k * w + x0 + L,     \
                    STORE_ARGS);

#define BOX_CODES(L, Q)                                                                   \
    if (x0 + L < across)                                                                   \
        store_codes(Q, out, out_kind,                                                      \
                    transposed ? (size_t)(x0 + L) * w + k : (size_t)k * w + x0 + L,         \
                    channels, cbase, cg);

/* Integer codes of 4 pixels' channel groups: through the grid where the host built one
 * (cells > 0), else by the search.  Both give the same codes. */
#define BOX_QUANTISE(m)                                                                   \
    (cells > 0 ? quantise16_grid((m), grid, cells, gstride, gscale, thresholds, buckets)     \
               : quantise16((m), thresholds, buckets))

/* uint8 RGB images whose work-item has all LANES lines: the codes go out as packed vector
 * stores instead of three byte stores per pixel (4K horizontal box on PoCL: 1.05x).
 * Along rows (not transposed) one step writes the 8 neighbouring pixels' 24 bytes; across
 * rows (transposed) each line's pixels are contiguous along k, so four steps' codes are held
 * (c0 newest .. c3 oldest, 4 pixels x 4 channels per vector) and each line's 4 pixels (12
 * bytes) written at once; steps from len4 = len rounded down to 4 on take the per-pixel
 * stores.  Same codes, same places. */
#define BOX_PACKED_STATE                                                                  \
    bool packed = out_kind == OUT_U8 && channels == 3 && cg == 3 && x0 + LANES <= across;  \
    int len4 = len & ~3;                                                                   \
    uchar16 a0 = (uchar16)(0), a1 = a0, a2 = a0, a3 = a0, b0 = a0, b1 = a0, b2 = a0, b3 = a0;

#define BOX_LINE4(L, A, S)                                                                \
    {                                                                                      \
        uchar16 v = (uchar16)((A##3).S, (A##2).S, (A##1).S, (A##0).S, (uchar4)(0));        \
        __global uchar *o = out + ((size_t)(x0 + (L)) * w + (k - 3)) * 3;                  \
        vstore8(v.lo, 0, o);                                                               \
        vstore4(v.s89ab, 0, o + 8);                                                        \
    }

#define BOX_PACKED(Q_LO, Q_HI)                                                            \
    {                                                                                      \
        uchar16 a = convert_uchar16(Q_LO), b = convert_uchar16(Q_HI);                      \
        if (!transposed) {                                                                 \
            __global uchar *o = out + ((size_t)k * w + x0) * 3;                            \
            vstore16((uchar16)(a.s012, a.s456, a.s89a, a.scde, b.s012, b.s4), 0, o);       \
            vstore8((uchar8)(b.s56, b.s89a, b.scde), 0, o + 16);                           \
        } else {                                                                           \
            a3 = a2; a2 = a1; a1 = a0; a0 = a;                                             \
            b3 = b2; b2 = b1; b1 = b0; b0 = b;                                             \
            if ((k & 3) == 3) {                                                            \
                BOX_LINE4(0, a, s012) BOX_LINE4(1, a, s456)                                \
                BOX_LINE4(2, a, s89a) BOX_LINE4(3, a, scde)                                \
                BOX_LINE4(4, b, s012) BOX_LINE4(5, b, s456)                                \
                BOX_LINE4(6, b, s89a) BOX_LINE4(7, b, scde)                                \
            }                                                                              \
        }                                                                                  \
    }

/* The box mean of step k (8 lines x 4 channels in the fixed-point sums S_LO/S_HI), stored as
 * codes (packed where the layout allows) or as floats: the same store for both box kernels. */
#define BOX_EMIT(S_LO, S_HI)                                                                    \
    {                                                                                           \
        float16 m_lo = convert_float16(S_LO) * norm, m_hi = convert_float16(S_HI) * norm;       \
        if (codes) {                                                                            \
            int16 q_lo = BOX_QUANTISE(m_lo), q_hi = BOX_QUANTISE(m_hi);                         \
            if (packed && (!transposed || k < len4)) {                                          \
                BOX_PACKED(q_lo, q_hi)                                                          \
            } else {                                                                            \
                BOX_CODES(0, q_lo.s0123) BOX_CODES(1, q_lo.s4567)                               \
                BOX_CODES(2, q_lo.s89ab) BOX_CODES(3, q_lo.scdef)                               \
                BOX_CODES(4, q_hi.s0123) BOX_CODES(5, q_hi.s4567)                               \
                BOX_CODES(6, q_hi.s89ab) BOX_CODES(7, q_hi.scdef)                               \
            }                                                                                   \
        } else {                                                                                \
            BOX_STORE(0, m_lo.s0123) BOX_STORE(1, m_lo.s4567)                                   \
            BOX_STORE(2, m_lo.s89ab) BOX_STORE(3, m_lo.scdef)                                   \
            BOX_STORE(4, m_hi.s0123) BOX_STORE(5, m_hi.s4567)                                   \
            BOX_STORE(6, m_hi.s89ab) BOX_STORE(7, m_hi.scdef)                                   \
        }                                                                                       \
    }

/* Box of taps d = lo..hi along plane index k with equal weights, as running sums: the cost
 * per pixel does not grow with the box length.  LANES neighbouring lines run as vector lanes.
 * Taps clamp to the window (which lies inside the image: the same as clamping to the image
 * and then to the window).  mean = sum / (count * scale).  With ends (the continuous
 * exposure's trapezoid rule, count >= 3): the two end taps weigh half, mean = (2 sum - first
 * - last) / (2 (count - 1) scale), still exact integers before the one division. */
__kernel void integrate_box(__global const float *plane, int ps, int across, int len,
                            int transposed, int lo, int hi, int ends, float scale, int w,
                            __global const int *grid, int cells, int gstride, float gscale,
                            STORE_PARAMS)
{
    int x0 = get_global_id(0) * LANES;
    if (x0 >= across) return;
    float norm = 1.0f / ((float)(ends ? 2 * (hi - lo) : hi - lo + 1) * scale);
    bool codes = out_kind != OUT_F32;
    BOX_PACKED_STATE
    long16 sum_lo = (long16)(0), sum_hi = (long16)(0);
    for (int d = lo; d <= hi; ++d) {
        size_t at = (size_t)clamp(d, 0, len - 1) * ps + x0;
        sum_lo += fixed_lo(plane, at, scale);
        sum_hi += fixed_hi(plane, at, scale);
    }
    for (int k = 0; k < len; ++k) {
        if (ends) {
            size_t first = (size_t)clamp(k + lo, 0, len - 1) * ps + x0;
            size_t last = (size_t)clamp(k + hi, 0, len - 1) * ps + x0;
            BOX_EMIT(2 * sum_lo - fixed_lo(plane, first, scale) - fixed_lo(plane, last, scale),
                     2 * sum_hi - fixed_hi(plane, first, scale) - fixed_hi(plane, last, scale))
        } else {
            BOX_EMIT(sum_lo, sum_hi)
        }
        size_t enter = (size_t)clamp(k + hi + 1, 0, len - 1) * ps + x0;
        size_t leave = (size_t)clamp(k + lo, 0, len - 1) * ps + x0;
        sum_lo += fixed_lo(plane, enter, scale) - fixed_lo(plane, leave, scale);
        sum_hi += fixed_hi(plane, enter, scale) - fixed_hi(plane, leave, scale);
    }
}

/* Fixed-point exposures of one pixel's channel group straight from its integer codes:
 * lutq[k * lut_len + code] is the host's rint(float32 table entry * scale), exactly the
 * integer fixed_lo/fixed_hi make of the same entry (scale is a power of two, so the product
 * is exact and both round half to even).  No intermediate plane is written or read. */
static long4 fixed_codes(__global const uchar *image, int in_kind, __global const long *lutq,
                         int lut_len, size_t pix, int channels, int cbase, int cg)
{
    size_t base = pix * channels + cbase;
    long4 v = (long4)(0);
    if (in_kind == IN_U8) {
        v.x = lutq[image[base]];
        if (cg > 1) v.y = lutq[lut_len + image[base + 1]];
        if (cg > 2) v.z = lutq[2 * lut_len + image[base + 2]];
        if (cg > 3) v.w = lutq[3 * lut_len + image[base + 3]];
    } else {  /* IN_U16 */
        __global const ushort *im = (__global const ushort *)image;
        v.x = lutq[im[base]];
        if (cg > 1) v.y = lutq[lut_len + im[base + 1]];
        if (cg > 2) v.z = lutq[2 * lut_len + im[base + 2]];
        if (cg > 3) v.w = lutq[3 * lut_len + im[base + 3]];
    }
    return v;
}

/* Window pixel of line x0 + L (clamped to the last line) at position k along the box. */
#define BOX_PIXEL(L, k)                                                                   \
    (transposed ? (size_t)min(x0 + (L), across - 1) * w + (k)                              \
                : (size_t)(k) * w + min(x0 + (L), across - 1))
#define CODES4(L0, k)                                                                     \
    (long16)(fixed_codes(image, in_kind, lutq, lut_len, BOX_PIXEL(L0, k), channels, cbase, cg), \
             fixed_codes(image, in_kind, lutq, lut_len, BOX_PIXEL(L0 + 1, k), channels,    \
                         cbase, cg),                                                       \
             fixed_codes(image, in_kind, lutq, lut_len, BOX_PIXEL(L0 + 2, k), channels,    \
                         cbase, cg),                                                       \
             fixed_codes(image, in_kind, lutq, lut_len, BOX_PIXEL(L0 + 3, k), channels,    \
                         cbase, cg))

/* BOX_RING (a build option: constants.BOX_RING_CPU / BOX_RING_GPU): the longest box whose
 * values a work-item of integrate_box_codes keeps in two private rings (a step touches one
 * entry of each, in order); longer boxes read each value twice. */

/* The body of integrate_box_codes for one work-item (x0: its first line), always inlined,
 * so that the common case below gets in_kind, cg, channels and transposed as constants and
 * the per-pixel tests of fixed_codes and the stores fold away (same code, same results). */
__attribute__((always_inline))
static void box_codes_body(__global const uchar *image, int in_kind,
                           __global const long *lutq, int lut_len, int across, int len,
                           int transposed, int lo, int hi, int ends, float scale, int w,
                           __global const int *grid, int cells, int gstride, float gscale,
                           STORE_PARAMS, int x0, long16 *ring_lo, long16 *ring_hi)
{
    float norm = 1.0f / ((float)(ends ? 2 * (hi - lo) : hi - lo + 1) * scale);
    bool codes = out_kind != OUT_F32;
    BOX_PACKED_STATE
    long16 sum_lo = (long16)(0), sum_hi = (long16)(0);
    /* Boxes of up to BOX_RING taps keep the values they add until they leave the box, so
     * each step reads one pixel per line instead of two (same integers, same sums). */
    int n = hi - lo + 1, j = 0;
    bool ring = n <= BOX_RING;
    for (int d = lo; d <= hi; ++d) {
        int at = clamp(d, 0, len - 1);
        long16 v_lo = CODES4(0, at), v_hi = CODES4(4, at);
        sum_lo += v_lo;
        sum_hi += v_hi;
        if (ring) {
            ring_lo[d - lo] = v_lo;
            ring_hi[d - lo] = v_hi;
        }
    }
    for (int k = 0; k < len; ++k) {
        if (ends) {  /* the values at k + lo and k + hi: the ring's oldest and newest */
            int first = clamp(k + lo, 0, len - 1), last = clamp(k + hi, 0, len - 1);
            int newest = j == 0 ? n - 1 : j - 1;
            long16 f_lo = ring ? ring_lo[j] : CODES4(0, first);
            long16 f_hi = ring ? ring_hi[j] : CODES4(4, first);
            long16 l_lo = ring ? ring_lo[newest] : CODES4(0, last);
            long16 l_hi = ring ? ring_hi[newest] : CODES4(4, last);
            BOX_EMIT(2 * sum_lo - f_lo - l_lo, 2 * sum_hi - f_hi - l_hi)
        } else {
            BOX_EMIT(sum_lo, sum_hi)
        }
        int enter = clamp(k + hi + 1, 0, len - 1), leave = clamp(k + lo, 0, len - 1);
        if (ring) {  /* ring[j] entered n steps ago: the value at k + lo */
            long16 v_lo = CODES4(0, enter), v_hi = CODES4(4, enter);
            sum_lo += v_lo - ring_lo[j];
            sum_hi += v_hi - ring_hi[j];
            ring_lo[j] = v_lo;
            ring_hi[j] = v_hi;
            j = j + 1 == n ? 0 : j + 1;
        } else {
            sum_lo += CODES4(0, enter) - CODES4(0, leave);
            sum_hi += CODES4(4, enter) - CODES4(4, leave);
        }
    }
}

/* integrate_box for integer images, read from the codes (same sums, same results). */
__kernel void integrate_box_codes(__global const uchar *image, int in_kind,
                                  __global const long *lutq, int lut_len, int across, int len,
                                  int transposed, int lo, int hi, int ends, float scale, int w,
                                  __global const int *grid, int cells, int gstride,
                                  float gscale, STORE_PARAMS)
{
    int x0 = get_global_id(0) * LANES;
    if (x0 >= across) return;
    long16 ring_lo[BOX_RING], ring_hi[BOX_RING];
    if (in_kind == IN_U8 && channels == 3 && cg == 3) {  /* uint8 RGB: constants */
        if (transposed)
            box_codes_body(image, IN_U8, lutq, lut_len, across, len, 1, lo, hi, ends, scale, w,
                           grid, cells, gstride, gscale, resp, tables, thresholds, buckets, out,
                           out_kind, 3, 0, 3, x0, ring_lo, ring_hi);
        else
            box_codes_body(image, IN_U8, lutq, lut_len, across, len, 0, lo, hi, ends, scale, w,
                           grid, cells, gstride, gscale, resp, tables, thresholds, buckets, out,
                           out_kind, 3, 0, 3, x0, ring_lo, ring_hi);
    } else {
        box_codes_body(image, in_kind, lutq, lut_len, across, len, transposed, lo, hi, ends,
                       scale, w, grid, cells, gstride, gscale, STORE_ARGS, x0, ring_lo,
                       ring_hi);
    }
}

/* clblur.video's bent path: the mean of its two halves' exposures (float32, n pixels x
 * `channels`, written by integrate_field with the identity response and left on the device),
 * finished (forward response, quantisation) as every blur is.  The reference averages the
 * float32 exposures in float64; here the sum is float32 (one rounding, 2^-24 relative). */
__kernel void finish_mean(__global const float *first, __global const float *second, int n,
                          STORE_PARAMS)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    size_t at = (size_t)i * channels + cbase;
    float4 e = (float4)(0.0f);
    e.x = 0.5f * (first[at] + second[at]);
    if (cg > 1) e.y = 0.5f * (first[at + 1] + second[at + 1]);
    if (cg > 2) e.z = 0.5f * (first[at + 2] + second[at + 2]);
    if (cg > 3) e.w = 0.5f * (first[at + 3] + second[at + 3]);
    store_pixel(e, i, STORE_ARGS);
}
