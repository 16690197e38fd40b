/* Linearise and integrate along the motion path (the pipeline of clblur/reference.py).
 *
 * Conventions
 * - Build options: -DSTORE_HALF (linear intermediate as half, else float) and -DHAVE_FP64
 *   when the device has doubles.  This file is appended to response.cl.
 * - The window (h x w) starts at full-image (r0, c0) of an fh x fw image and lies inside it.
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

#define IN_U8 0
#define IN_U16 1
#define IN_F32 2
#define LANES 8

/* Linearise one channel group into the padded intermediate (global size (w + 1, h + 1)):
 * integer codes through per-channel tables (lut[k * lut_len + code]); float32 input is
 * already linear (the host applied the inverse response in float64). */
static float linear_channel(__global const uchar *image, int in_kind, size_t index, int k,
                            __global const float *lut, int lut_len)
{
    if (in_kind == IN_U8)
        return lut[k * lut_len + image[index]];
    if (in_kind == IN_U16)
        return lut[k * lut_len + ((__global const ushort *)image)[index]];
    return ((__global const float *)image)[index];
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

#ifdef HAVE_FP64
/* clblur.motion.sample_counts for LANES vectors: exact ceil(|v|) + 1 from float64 squares of
 * the float32 vector, corrected with exact integer-square comparisons (contraction is off;
 * true vector compares are -1, hence the subtractions). */
static int8 sample_counts8(float8 vx, float8 vy)
{
    double8 x = convert_double8(vx), y = convert_double8(vy);
    double8 l2 = x * x + y * y;
    double8 m = ceil(sqrt(l2));
    m = select(m, m + 1.0, m * m < l2);
    m = select(m, m - 1.0, m > 0.0 && (m - 1.0) * (m - 1.0) >= l2);
    return convert_int8(m) + 1;
}
#endif

/* floor() of offsets without the library call (slow on some CPU drivers): truncate, then
 * step down where truncation went up (negative non-integers; true compares are -1). */
static int8 floor_int8(float8 v)
{
    int8 t = convert_int8(v);
    return t + (convert_float8(t) > v);
}

/* Store LANES consecutive pixels of a row (the first `valid` of them), starting at `pixel`;
 * integer outputs are quantised 4 pixels x 4 channels at a time. */
static void store_row8(float4 a0, float4 a1, float4 a2, float4 a3, float4 a4, float4 a5,
                       float4 a6, float4 a7, __global uchar *restrict out, int out_kind,
                       size_t pixel, int valid, int channels, int cbase, int cg,
                       __constant const float *resp, __global const float *tables,
                       __global const float *thresholds, __global const int *buckets)
{
    if (out_kind != OUT_F32 && valid >= LANES) {
        int16 lo = quantise16((float16)(a0, a1, a2, a3), thresholds, buckets);
        int16 hi = quantise16((float16)(a4, a5, a6, a7), thresholds, buckets);
        store_codes(lo.s0123, out, out_kind, pixel, channels, cbase, cg);
        store_codes(lo.s4567, out, out_kind, pixel + 1, channels, cbase, cg);
        store_codes(lo.s89ab, out, out_kind, pixel + 2, channels, cbase, cg);
        store_codes(lo.scdef, out, out_kind, pixel + 3, channels, cbase, cg);
        store_codes(hi.s0123, out, out_kind, pixel + 4, channels, cbase, cg);
        store_codes(hi.s4567, out, out_kind, pixel + 5, channels, cbase, cg);
        store_codes(hi.s89ab, out, out_kind, pixel + 6, channels, cbase, cg);
        store_codes(hi.scdef, out, out_kind, pixel + 7, channels, cbase, cg);
        return;
    }
    float4 a[LANES] = {a0, a1, a2, a3, a4, a5, a6, a7};
    for (int l = 0; l < LANES && l < valid; ++l)
        store_pixel(a[l], out, out_kind, pixel + l, channels, cbase, cg, resp, tables,
                    thresholds, buckets);
}

/* One lane of the field kernel: the two horizontal neighbours of the upper and the lower row
 * (one 8-value load each) times their bilinear weights, which already hold the tap weight
 * (0 once the lane's N taps are done: adding fma(0, v, acc) leaves acc exactly as it is).
 * wt/wb select (w00 x4, w01 x4) and (w10 x4, w11 x4) for the lane from the weight vectors. */
#define FIELD_LANE(L)                                                                  \
    {                                                                                  \
        acc##L = fma(LOAD8(base.s##L), shuffle(w_top, (uint8)(L, L, L, L, L + 8, L + 8, \
                     L + 8, L + 8)), acc##L);                                          \
        acc##L = fma(LOAD8(base.s##L + ws), shuffle(w_bottom, (uint8)(L, L, L, L,       \
                     L + 8, L + 8, L + 8, L + 8)), acc##L);                            \
    }

#define FIELD_MEAN(L) (weighted ? acc##L.lo + acc##L.hi : (acc##L.lo + acc##L.hi) / (float)n.s##L)

/* Per-pixel motion field.  Sample j of pixel p lies at p + o, o = -(v / (N-1)) (j - a (N-1))
 * (the reference's p - v (j - a (N-1)) / (N-1), exact whenever the step v / (N-1) is an
 * integer).  o is split into integer and fraction before it meets p, so the fraction keeps
 * the precision of |o| rather than that of the pixel coordinate.  N is counts[i] when
 * `host_counts` (devices without fp64), else `fixed_n` when > 0, else computed here.
 * LANES pixels per work-item run as vector lanes; the tap loop runs to the largest N among
 * them. */
__kernel void integrate_field(__global const STORE_T *lin, __global const float *flow,
                              __global const int *counts, int host_counts, int fixed_n,
                              __global const float *time_w, int weighted, float anchor,
                              int w, int h, int r0, int c0, int fw, int fh,
                              __constant const float *resp, __global const float *tables,
                              __global const float *thresholds, __global const int *buckets,
                              __global uchar *restrict out, int out_kind, int channels, int cbase,
                              int cg)
{
    int row = get_global_id(1);
    int col0 = get_global_id(0) * LANES;
    if (row >= h || col0 >= w) return;
    int ws = w + 1;
    float vxs[LANES], vys[LANES];
    int ns[LANES];
    for (int l = 0; l < LANES; ++l) {
        int i = row * w + min(col0 + l, w - 1);
        vxs[l] = flow[2 * i];
        vys[l] = flow[2 * i + 1];
        ns[l] = host_counts ? counts[i] : fixed_n;
    }
    float8 vx = vload8(0, vxs), vy = vload8(0, vys);
    int8 n = vload8(0, ns);
#ifdef HAVE_FP64
    if (fixed_n <= 0 && !host_counts)
        n = sample_counts8(vx, vy);
#endif
    int nmax = max(max(max(n.s0, n.s1), max(n.s2, n.s3)), max(max(n.s4, n.s5), max(n.s6, n.s7)));
    float8 n1 = convert_float8(n - 1);
    float8 den = fmax(n1, 1.0f);
    float8 sx = vx / den, sy = vy / den;
    float8 a_n1 = anchor * n1;
    int8 px = (int8)(col0) + (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    float8 acc0 = 0.0f, acc1 = 0.0f, acc2 = 0.0f, acc3 = 0.0f;  /* (left, right) sums */
    float8 acc4 = 0.0f, acc5 = 0.0f, acc6 = 0.0f, acc7 = 0.0f;
    for (int j = 0; j < nmax; ++j) {
        float8 t = (float8)((float)j) - a_n1;
        float8 ox = -(sx * t), oy = -(sy * t);
        int8 ix = floor_int8(ox), iy = floor_int8(oy);
        float8 fx = ox - convert_float8(ix), fy = oy - convert_float8(iy);
        int8 xi = px + ix, yi = (int8)(row) + iy;
        /* Before the first pixel the sample is the first pixel; past the last, the padding
         * repeats the last, so the fraction does not matter there. */
        fx = select(fx, (float8)(0.0f), xi < 0);
        fy = select(fy, (float8)(0.0f), yi < 0);
        int8 base = clamp(yi, 0, h - 1) * ws + clamp(xi, 0, w - 1);
        float8 wj = select((float8)(0.0f), (float8)(weighted ? time_w[j] : 1.0f),
                           (int8)(j) < n);
        float8 upper = (1.0f - fy) * wj, lower = fy * wj;
        float16 w_top = (float16)((1.0f - fx) * upper, fx * upper);
        float16 w_bottom = (float16)((1.0f - fx) * lower, fx * lower);
        FIELD_LANE(0) FIELD_LANE(1) FIELD_LANE(2) FIELD_LANE(3)
        FIELD_LANE(4) FIELD_LANE(5) FIELD_LANE(6) FIELD_LANE(7)
    }
    store_row8(FIELD_MEAN(0), FIELD_MEAN(1), FIELD_MEAN(2), FIELD_MEAN(3), FIELD_MEAN(4),
               FIELD_MEAN(5), FIELD_MEAN(6), FIELD_MEAN(7), out, out_kind, (size_t)row * w + col0,
               w - col0, channels, cbase, cg, resp, tables, thresholds, buckets);
}

/* Space-invariant integer taps: g(p) = sum_t w_t L(clamp(p + d_t)), accumulated in tap order
 * with one fma each.  Serves PSFs and uniform motion (whose bilinear samples share their
 * fractional parts and so rasterise exactly).  Work-items whose LANES pixels read only
 * inside the window load them as contiguous vectors; others clamp per pixel.  Both paths
 * do the same arithmetic per pixel. */
__kernel void integrate_taps(__global const STORE_T *lin, __global const int *tap_dx,
                             __global const int *tap_dy, __global const float *tap_w, int ntaps,
                             int dx_min, int dx_max, int dy_min, int dy_max,
                             int w, int h, int r0, int c0, int fw, int fh,
                             __constant const float *resp, __global const float *tables,
                             __global const float *thresholds, __global const int *buckets,
                             __global uchar *restrict out, int out_kind, int channels, int cbase,
                             int cg)
{
    int row = get_global_id(1);
    int col0 = get_global_id(0) * LANES;
    if (row >= h || col0 >= w) return;
    int ws = w + 1;
    float4 acc[LANES];
    for (int l = 0; l < LANES; ++l) acc[l] = 0.0f;
    if (col0 + dx_min >= 0 && col0 + LANES - 1 + dx_max <= w - 1 && row + dy_min >= 0 &&
        row + dy_max <= h - 1) {
        float16 lo = 0.0f, hi = 0.0f;  /* pixels col0 .. col0 + 3 and col0 + 4 .. col0 + 7 */
        size_t origin = (size_t)row * ws + col0;
        for (int t = 0; t < ntaps; ++t) {
            size_t src = origin + tap_dy[t] * ws + tap_dx[t];
            float16 wt = (float16)(tap_w[t]);
            lo = fma(wt, LOAD16(src), lo);
            hi = fma(wt, LOAD16(src + 4), hi);
        }
        acc[0] = lo.s0123; acc[1] = lo.s4567; acc[2] = lo.s89ab; acc[3] = lo.scdef;
        acc[4] = hi.s0123; acc[5] = hi.s4567; acc[6] = hi.s89ab; acc[7] = hi.scdef;
    } else {
        for (int l = 0; l < LANES; ++l) {
            int col = min(col0 + l, w - 1);
            for (int t = 0; t < ntaps; ++t) {
                int x = clamp(col + tap_dx[t], 0, w - 1), y = clamp(row + tap_dy[t], 0, h - 1);
                acc[l] = fma((float4)(tap_w[t]), LOAD4((size_t)y * ws + x), acc[l]);
            }
        }
    }
    store_row8(acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6], acc[7], out, out_kind,
               (size_t)row * w + col0, w - col0, channels, cbase, cg, resp, tables, thresholds,
               buckets);
}

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
        store_pixel(S, out, out_kind,                                                      \
                    transposed ? (size_t)(x0 + L) * w + k : (size_t)k * w + x0 + L,         \
                    channels, cbase, cg, resp, tables, thresholds, buckets);

#define BOX_CODES(L, Q)                                                                   \
    if (x0 + L < across)                                                                   \
        store_codes(Q, out, out_kind,                                                      \
                    transposed ? (size_t)(x0 + L) * w + k : (size_t)k * w + x0 + L,         \
                    channels, cbase, cg);

/* Box of taps d = lo..hi along plane index k with equal weights, as running sums: the cost
 * per pixel does not grow with the box length.  LANES neighbouring lines run as vector lanes.
 * Taps clamp to the window (which lies inside the image: the same as clamping to the image
 * and then to the window).  mean = sum / (count * scale). */
__kernel void integrate_box(__global const float *plane, int ps, int across, int len,
                            int transposed, int lo, int hi, float scale, int w,
                            __constant const float *resp, __global const float *tables,
                            __global const float *thresholds, __global const int *buckets,
                            __global uchar *restrict out, int out_kind, int channels, int cbase,
                            int cg)
{
    int x0 = get_global_id(0) * LANES;
    if (x0 >= across) return;
    float norm = 1.0f / ((float)(hi - lo + 1) * scale);
    bool codes = out_kind != OUT_F32;
    long16 sum_lo = (long16)(0), sum_hi = (long16)(0);
    for (int d = lo; d <= hi; ++d) {
        size_t at = (size_t)clamp(d, 0, len - 1) * ps + x0;
        sum_lo += fixed_lo(plane, at, scale);
        sum_hi += fixed_hi(plane, at, scale);
    }
    for (int k = 0; k < len; ++k) {
        float16 m_lo = convert_float16(sum_lo) * norm, m_hi = convert_float16(sum_hi) * norm;
        if (codes) {
            int16 q_lo = quantise16(m_lo, thresholds, buckets);
            int16 q_hi = quantise16(m_hi, thresholds, buckets);
            BOX_CODES(0, q_lo.s0123) BOX_CODES(1, q_lo.s4567)
            BOX_CODES(2, q_lo.s89ab) BOX_CODES(3, q_lo.scdef)
            BOX_CODES(4, q_hi.s0123) BOX_CODES(5, q_hi.s4567)
            BOX_CODES(6, q_hi.s89ab) BOX_CODES(7, q_hi.scdef)
        } else {
            BOX_STORE(0, m_lo.s0123) BOX_STORE(1, m_lo.s4567)
            BOX_STORE(2, m_lo.s89ab) BOX_STORE(3, m_lo.scdef)
            BOX_STORE(4, m_hi.s0123) BOX_STORE(5, m_hi.s4567)
            BOX_STORE(6, m_hi.s89ab) BOX_STORE(7, m_hi.scdef)
        }
        size_t enter = (size_t)clamp(k + hi + 1, 0, len - 1) * ps + x0;
        size_t leave = (size_t)clamp(k + lo, 0, len - 1) * ps + x0;
        sum_lo += fixed_lo(plane, enter, scale) - fixed_lo(plane, leave, scale);
        sum_hi += fixed_hi(plane, enter, scale) - fixed_hi(plane, leave, scale);
    }
}
