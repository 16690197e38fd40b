/* Layered exposure: front-to-back composite of every shutter sample (clblur/layered_exposure.py,
 * function composite, is the float64 specification).
 *
 * Conventions
 * - Arrays cover a crop (h x w) starting at full-image (r0, c0) of an fh x fw image; positions
 *   are full-image coordinates, clamped to the image (clamp-to-edge), then to the crop.
 * - Build option -DCHANNELS=C (the light channels).
 * - planes: K x h x w x CP floats, premultiplied (colour * coverage ..., coverage), CP = C + 1,
 *   K <= MAXK.
 * - vectors: K x h x w x 2 (dx, dy) per layer; flow: h x w x 2, the image's own vectors;
 *   linear: h x w x CP, the linear image padded with one zero channel (light no layer covers
 *   is read from it), so that with CP = 4 every read is one float4 per tap.
 * - present: K x h x w, 0 where layer k cannot reach the pixel at any sample (skipped).
 * - One work-item per listed pixel (pix: n x 2 (row, col) in the crop); counts: its sample
 *   count N (with own_counts != 0, on a device with fp64: counted in the kernel instead, with
 *   counts.cl's sample_count; composite_lanes then reads counts as 1 on the region, 0 off
 *   it); weights: N time weights when weighted != 0, else 1/N each,
 *   or with ends != 0
 *   (the continuous exposure, clblur/motion.py sample_weight) 1/(N-1) each but half of it
 *   at j = 0 and j = N - 1 (1 when N = 1).
 * - Sample j of a pixel p reads each layer k at q = p - D_k(q) t, t = (j - a (N-1)) /
 *   max(N-1, 1): q = p - D_k(p) t for a rigid layer (warped[k] = 0), and INVERSE_STEPS
 *   (a build option: Layers.inverse_steps) fixed-point steps from there for a warped one,
 *   D_k read bilinearly in the form
 *   a + f (b - a) (exact where the corners are equal; clblur/reference.py lerp_at),
 *   safeguarded as clblur/layered_exposure.py _inverse_motion: the last iterate where its
 *   step is the smallest so far, else the iterate of the smallest step.
 * - warped: K flags; vectors of a warped layer cover the whole crop, those of a rigid one
 *   the listed pixels only.
 * - Curved paths (build option -DCURVED=1): curvature is
 *   K x h x w x 2, C_k laid out as vectors; the path is D_k t + C_k t^2, read at
 *   q = p - D_k(q) t - C_k(q) t^2 (t^2 formed as (num * num) / (den * den)); C_k is read
 *   where D_k is, in the same way.  CURVED=0: curvature is a placeholder, never read, and
 *   the straight kernels carry no curvature registers or branches (a separate build).
 * - Floating-point contraction is off: every a*b+c is rounded as written; the float4 path
 *   does per component exactly what the scalar path does.
 * - Once the layers in front leave no transmittance (T = 0 exactly: an opaque layer), the
 *   layers behind and the uncovered light would add T * s = +-0 to the sample: they are
 *   skipped, which changes no bit (all values are finite).
 */
#pragma OPENCL FP_CONTRACT OFF

/* CHANNELS (light channels, C) is a build option: loops over channels unroll and the
 * per-sample accumulators stay in registers. */
#ifndef CHANNELS
#define CHANNELS 3
#endif
/* MAXK (layers a work-item holds) comes from clblur.opencl.constants as a -D option. */
#ifndef CURVED
#define CURVED 0
#endif
/* The curved term of a reading position, x - C_k t^2 (scalar or float8 alike; nothing in a
 * straight build).  cx, cy, tt: the kernel's curvature of the q-th used layer and t^2. */
#if CURVED
#define BEND(x, y, q) do { (x) = (x) - cx[q] * tt; (y) = (y) - cy[q] * tt; } while (0)
#else
#define BEND(x, y, q) do { } while (0)
#endif
#define CP (CHANNELS + 1)

/* Bilinear taps at full-image (x, y), clamped to the image, then to the crop.  One body for
 * the scalar kernel's taps (size_t indices) and the 8-lane kernel's (int8, locate8 below),
 * so that both clamp and round alike. */
#define DEFINE_LOCATE(NAME, TAPS, REAL, INT, CAST, WIDE)                                  \
static TAPS NAME(int h, int w, int r0, int c0, int fh, int fw, REAL x, REAL y)            \
{                                                                                         \
    TAPS t;                                                                               \
    x = clamp(x, 0.0f, (float)(fw - 1));                                                  \
    y = clamp(y, 0.0f, (float)(fh - 1));                                                  \
    REAL fx0 = floor(x), fy0 = floor(y);                                                  \
    INT x0 = CAST(fx0), y0 = CAST(fy0);                                                   \
    INT x1 = min(x0 + 1, fw - 1), y1 = min(y0 + 1, fh - 1);                               \
    t.fx = x - fx0;                                                                       \
    t.fy = y - fy0;                                                                       \
    x0 = clamp(x0 - c0, 0, w - 1);                                                        \
    x1 = clamp(x1 - c0, 0, w - 1);                                                        \
    y0 = clamp(y0 - r0, 0, h - 1);                                                        \
    y1 = clamp(y1 - r0, 0, h - 1);                                                        \
    t.a = WIDE(y0) * w + x0;                                                              \
    t.b = WIDE(y0) * w + x1;                                                              \
    t.c = WIDE(y1) * w + x0;                                                              \
    t.d = WIDE(y1) * w + x1;                                                              \
    return t;                                                                             \
}
#define CAST_INT(v) ((int)(v))
#define WIDE_SIZE(v) ((size_t)(v))
#define AS_IS(v) (v)

typedef struct {
    size_t a, b, c, d;
    float fx, fy;
} taps;

DEFINE_LOCATE(locate, taps, float, int, CAST_INT, WIDE_SIZE)

#if CP == 4
typedef float4 px_t;
static px_t sample(__global const float *img, taps t)
{
    float4 a = vload4(t.a, img), b = vload4(t.b, img), c = vload4(t.c, img),
           d = vload4(t.d, img);
    float4 top = a * (1.0f - t.fx) + b * t.fx;
    float4 bottom = c * (1.0f - t.fx) + d * t.fx;
    return top * (1.0f - t.fy) + bottom * t.fy;
}
#define CH(v, i) ((i) == 0 ? (v).x : (i) == 1 ? (v).y : (i) == 2 ? (v).z : (v).w)
#else
typedef struct { float v[CP]; } px_t;
static px_t sample(__global const float *img, taps t)
{
    px_t out;
    for (int i = 0; i < CP; ++i) {
        float top = img[t.a * CP + i] * (1.0f - t.fx) + img[t.b * CP + i] * t.fx;
        float bottom = img[t.c * CP + i] * (1.0f - t.fx) + img[t.d * CP + i] * t.fx;
        out.v[i] = top * (1.0f - t.fy) + bottom * t.fy;
    }
    return out;
}
#define CH(p, i) ((p).v[i])
#endif

/* A vector field (h x w x 2) at taps t, as lerp_at: a + f (b - a). */
static float2 sample_vector(__global const float *vec, taps t)
{
    float2 a = vload2(t.a, vec), b = vload2(t.b, vec), c = vload2(t.c, vec),
           d = vload2(t.d, vec);
    float2 top = a + t.fx * (b - a);
    float2 bottom = c + t.fx * (d - c);
    return top + t.fy * (bottom - top);
}

/* Where layer point at (px, py) at sample offset num / den was at the anchor time: the
 * fixed-point steps of the conventions, from the first guess (x, y); curv (CURVED builds) is
 * the layer's C_k and tt the sample's t^2. */
static float2 inverse_motion(__global const float *vec, __global const float *curv,
                             int h, int w, int r0, int c0, int fh, int fw, float px, float py,
                             float num, float den, float tt, float x, float y)
{
    float bx = x, by = y, br = INFINITY, r = INFINITY;
    for (int it = 0; it < INVERSE_STEPS; ++it) {
        taps at = locate(h, w, r0, c0, fh, fw, x, y);
        float2 d = sample_vector(vec, at);
        float nx = px - (d.x * num) / den;
        float ny = py - (d.y * num) / den;
#if CURVED
        float2 c = sample_vector(curv, at);
        nx = nx - c.x * tt;
        ny = ny - c.y * tt;
#endif
        r = fmax(fabs(nx - x), fabs(ny - y));  /* the residual of the iterate (x, y) */
        if (r < br) {
            bx = x;
            by = y;
            br = r;
        }
        x = nx;
        y = ny;
    }
    if (!(r <= br)) {  /* not contracting at the last step: the iterate of least residual */
        x = bx;
        y = by;
    }
    return (float2)(x, y);
}

/* Weight of sample j of N without time weights (see Conventions): 1/N, or with ends the
 * trapezoid rule over N - 1 steps. */
static float end_weight(int j, int N, int ends)
{
    if (!ends)
        return 1.0f / (float)N;
    if (N == 1)
        return 1.0f;
    float full = 1.0f / (float)(N - 1);
    return (j == 0 || j == N - 1) ? 0.5f * full : full;
}

__kernel void composite_layers(__global const float *planes, __global const float *vectors,
                               __global const float *flow, __global const float *linear,
                               __global const uchar *present, __global const uchar *warped,
                               __global const float *curvature,
                               __global const int *pix, __global const int *counts,
                               int own_counts,
                               __global const float *weights, int weighted, int ends,
                               int n, int layers, int h, int w, int r0, int c0,
                               int fh, int fw, float anchor, __global float *out)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    int row = pix[2 * i], col = pix[2 * i + 1];
    float px = (float)(c0 + col), py = (float)(r0 + row);
    const int channels = CHANNELS;
    size_t plane = (size_t)h * w * CP;
    size_t at = (size_t)row * w + col;
    /* the layers that can reach this pixel, front to back, with their vectors */
    int use[MAXK];
    float vx[MAXK], vy[MAXK];
#if CURVED
    float cx[MAXK], cy[MAXK];
#endif
    int m = 0;
    for (int k = 0; k < layers; ++k) {
        if (!present[(size_t)k * h * w + at])
            continue;  /* the layer cannot reach this pixel: it would add zeros */
        use[m] = k;
        vx[m] = vectors[((size_t)k * h * w + at) * 2];
        vy[m] = vectors[((size_t)k * h * w + at) * 2 + 1];
#if CURVED
        cx[m] = curvature[((size_t)k * h * w + at) * 2];
        cy[m] = curvature[((size_t)k * h * w + at) * 2 + 1];
#endif
        ++m;
    }
    float fx = flow[2 * at], fy = flow[2 * at + 1];
    /* N: the host's counts, or with own_counts (straight paths, per-pixel counts, a device
     * with fp64) counted here as clblur.layered_exposure.counts does: the largest over the
     * pixel's own vector and the vectors of the layers present at it */
    int N;
#ifdef HAVE_FP64
    if (own_counts) {
        N = sample_count(fx, fy);
        for (int q = 0; q < m; ++q)
            N = max(N, sample_count(vx[q], vy[q]));
    } else
#endif
        N = counts[i];
    float den = (float)max(N - 1, 1);
    float acc[CHANNELS], e[CHANNELS];
    for (int c = 0; c < channels; ++c)
        acc[c] = 0.0f;
    for (int j = 0; j < N; ++j) {
        float num = (float)j - anchor * (float)(N - 1);
#if CURVED
        float tt = (num * num) / (den * den);
#else
        float tt = 0.0f;  /* unread */
#endif
        float left = 1.0f;
        for (int c = 0; c < channels; ++c)
            e[c] = 0.0f;
        for (int q = 0; q < m && left != 0.0f; ++q) {
            float x = px - (vx[q] * num) / den;
            float y = py - (vy[q] * num) / den;
            BEND(x, y, q);
            if (warped[use[q]]) {
                size_t field = (size_t)use[q] * h * w * 2;
                float2 at_q = inverse_motion(vectors + field, curvature + (CURVED ? field : 0),
                                             h, w, r0, c0, fh, fw, px, py, num, den, tt, x, y);
                x = at_q.x;
                y = at_q.y;
            }
            px_t s = sample(planes + use[q] * plane, locate(h, w, r0, c0, fh, fw, x, y));
            for (int c = 0; c < channels; ++c)
                e[c] += left * CH(s, c);
            left = left * (1.0f - CH(s, channels));
        }
        float wj = weighted ? weights[j] : end_weight(j, N, ends);
        if (left != 0.0f) {
            float x = px - (fx * num) / den;
            float y = py - (fy * num) / den;
            px_t s = sample(linear, locate(h, w, r0, c0, fh, fw, x, y));
            for (int c = 0; c < channels; ++c)
                acc[c] += wj * (e[c] + left * CH(s, c));
        } else {
            for (int c = 0; c < channels; ++c)
                acc[c] += wj * e[c];
        }
    }
    for (int c = 0; c < channels; ++c)
        out[(size_t)i * channels + c] = acc[c];
}

#if CP == 4
/* CPU layout (the gather's, clblur/opencl/integrate.cl): LANES = 8 consecutive pixels of a
 * crop row per work-item, as vector lanes, so every position, weight and blend is one
 * float8/float16 operation.  Per lane the arithmetic is the one of composite_layers, in the
 * same order, so the two kernels agree bit for bit:
 * - a layer is visited when any lane has it present; a lane without it samples zeros
 *   (select), which adds +-0 to e (never -0: it starts at +0) and leaves T as it is;
 * - a lane whose N samples are done, or that is not on the region (count 0), gets weight 0,
 *   which adds +-0 to its sum (never -0);
 * - past T = 0 the scalar kernel skips the rest; here they add T * s = +-0 in a lane whose T
 *   is 0 while another's is not, and are skipped once T = 0 in all eight lanes.
 * chunks: (row, first col) in the crop per work-item; counts: LANES per work-item (0 for
 * lanes off the region or past the crop); out: LANES x CHANNELS per work-item. */
#define SPREAD_LO(v) shuffle((v), (uint16)(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3))
#define SPREAD_HI(v) shuffle((v), (uint16)(4, 4, 4, 4, 5, 5, 5, 5, 6, 6, 6, 6, 7, 7, 7, 7))
#define COVER(lo, hi) ((float8)((lo).s37bf, (hi).s37bf))

/* locate() for 8 lanes: the four taps' pixel indices in the crop and the fractions. */
typedef struct {
    int8 a, b, c, d;
    float8 fx, fy;
} taps8;

DEFINE_LOCATE(locate8, taps8, float8, int8, convert_int8, AS_IS)

/* Bilinear sample of 8 lanes at full-image (x, y): the per-lane taps of locate(), and
 * sample() done per channel; 8 contiguous pixels per corner when the lanes' taps are. */
static void sample8(__global const float *img, int h, int w, int r0, int c0, int fh, int fw,
                    float8 x, float8 y, float16 *lo, float16 *hi)
{
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    taps8 t = locate8(h, w, r0, c0, fh, fw, x, y);
    int8 a = t.a, b = t.b, c = t.c, d = t.d;
    float8 tx = t.fx, ty = t.fy;
    float16 a_lo, a_hi, b_lo, b_hi, c_lo, c_hi, d_lo, d_hi;
    if (all(a == (int8)(a.s0) + lane) && all(b == a + 1) && all(c == (int8)(c.s0) + lane) &&
        all(d == c + 1)) {
        __global const float *pa = img + (size_t)a.s0 * CP, *pc = img + (size_t)c.s0 * CP;
        a_lo = vload16(0, pa); a_hi = vload16(1, pa);
        b_lo = vload16(0, pa + CP); b_hi = vload16(1, pa + CP);
        c_lo = vload16(0, pc); c_hi = vload16(1, pc);
        d_lo = vload16(0, pc + CP); d_hi = vload16(1, pc + CP);
    } else {
#define GATHER(t, lo_, hi_)                                                                   \
        lo_ = (float16)(vload4(t.s0, img), vload4(t.s1, img), vload4(t.s2, img),              \
                        vload4(t.s3, img));                                                   \
        hi_ = (float16)(vload4(t.s4, img), vload4(t.s5, img), vload4(t.s6, img),              \
                        vload4(t.s7, img));
        GATHER(a, a_lo, a_hi)
        GATHER(b, b_lo, b_hi)
        GATHER(c, c_lo, c_hi)
        GATHER(d, d_lo, d_hi)
#undef GATHER
    }
    float16 fx_lo = SPREAD_LO(tx), fx_hi = SPREAD_HI(tx);
    float16 fy_lo = SPREAD_LO(ty), fy_hi = SPREAD_HI(ty);
    float16 top_lo = a_lo * (1.0f - fx_lo) + b_lo * fx_lo;
    float16 top_hi = a_hi * (1.0f - fx_hi) + b_hi * fx_hi;
    float16 bot_lo = c_lo * (1.0f - fx_lo) + d_lo * fx_lo;
    float16 bot_hi = c_hi * (1.0f - fx_hi) + d_hi * fx_hi;
    *lo = top_lo * (1.0f - fy_lo) + bot_lo * fy_lo;
    *hi = top_hi * (1.0f - fy_hi) + bot_hi * fy_hi;
}

/* A vector field (h x w x 2) at 8 lanes' taps t (locate8), as sample_vector() per lane: the
 * same float operations, component by component. */
static void vector8(__global const float *vec, taps8 t, float8 *vx, float8 *vy)
{
    int8 a = t.a * 2, b = t.b * 2, c = t.c * 2, d = t.d * 2;  /* two floats per pixel */
    float8 fx = t.fx, fy = t.fy;
#define FIELD8(t, k) (float8)(vec[t.s0 + k], vec[t.s1 + k], vec[t.s2 + k], vec[t.s3 + k],       \
                              vec[t.s4 + k], vec[t.s5 + k], vec[t.s6 + k], vec[t.s7 + k])
    float8 ax = FIELD8(a, 0), bx = FIELD8(b, 0), cx = FIELD8(c, 0), dx = FIELD8(d, 0);
    float8 ay = FIELD8(a, 1), by = FIELD8(b, 1), cy = FIELD8(c, 1), dy = FIELD8(d, 1);
#undef FIELD8
    float8 top = ax + fx * (bx - ax), bottom = cx + fx * (dx - cx);
    *vx = top + fy * (bottom - top);
    top = ay + fx * (by - ay);
    bottom = cy + fx * (dy - cy);
    *vy = top + fy * (bottom - top);
}

/* inverse_motion() for 8 lanes as vectors: the same float operations and the same
 * safeguard per lane, so the layouts agree bit for bit. */
static void inverse_motion8(__global const float *vec, __global const float *curv, int h,
                            int w, int r0, int c0, int fh, int fw, float8 px, float8 py,
                            float8 num, float8 den, float8 tt, float8 *x, float8 *y)
{
    float8 qx = *x, qy = *y, bx = *x, by = *y;
    float8 br = (float8)(INFINITY), r = (float8)(INFINITY);
    for (int it = 0; it < INVERSE_STEPS; ++it) {
        taps8 at = locate8(h, w, r0, c0, fh, fw, qx, qy);  /* once per step, as the scalar */
        float8 dx, dy;
        vector8(vec, at, &dx, &dy);
        float8 nx = px - (dx * num) / den;
        float8 ny = py - (dy * num) / den;
#if CURVED
        float8 cx, cy;
        vector8(curv, at, &cx, &cy);
        nx = nx - cx * tt;
        ny = ny - cy * tt;
#endif
        r = fmax(fabs(nx - qx), fabs(ny - qy));  /* the residual of the iterate (qx, qy) */
        int8 better = isless(r, br);
        bx = select(bx, qx, better);
        by = select(by, qy, better);
        br = select(br, r, better);
        qx = nx;
        qy = ny;
    }
    int8 last = islessequal(r, br);  /* still contracting at the last step */
    *x = select(bx, qx, last);
    *y = select(by, qy, last);
}

__kernel void composite_lanes(__global const float *planes, __global const float *vectors,
                              __global const float *flow, __global const float *linear,
                              __global const uchar *present, __global const uchar *warped,
                              __global const float *curvature,
                              __global const int *chunks,
                              __global const int *counts, int own_counts,
                              __global const float *weights,
                              int weighted, int ends, int n, int layers, int h, int w, int r0,
                              int c0, int fh, int fw, float anchor, __global float *out)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    int row = chunks[2 * i], col0 = chunks[2 * i + 1];
    size_t plane = (size_t)h * w * CP;
    /* counts: each lane's N (0: not on the region); with own_counts, 1 on the region and N
     * counted here as composite_layers counts it: the largest over the pixel's own vector
     * and the vectors of the layers present at it (in the layer loop below) */
    int8 N = vload8(i, counts);
    int ns[LANES];
    vstore8(N, 0, ns);
    float vxs[LANES], vys[LANES], fxs[LANES], fys[LANES];
    size_t ats[LANES];
    for (int l = 0; l < LANES; ++l) {
        ats[l] = (size_t)row * w + min(col0 + l, w - 1);
        fxs[l] = flow[2 * ats[l]];
        fys[l] = flow[2 * ats[l] + 1];
#ifdef HAVE_FP64
        if (own_counts && ns[l] > 0)
            ns[l] = sample_count(fxs[l], fys[l]);
#endif
    }
    float8 fx = vload8(0, fxs), fy = vload8(0, fys);
    /* the layers that can reach any lane, front to back, with their vectors and lane masks */
    int use[MAXK];
    float8 vx[MAXK], vy[MAXK];
#if CURVED
    float8 cx[MAXK], cy[MAXK];
#endif
    int8 there[MAXK];
    int m = 0;
    for (int k = 0; k < layers; ++k) {
        int flags[LANES];
#if CURVED
        float cxs[LANES], cys[LANES];
#endif
        int any = 0;
        for (int l = 0; l < LANES; ++l) {
            size_t at = (size_t)k * h * w + ats[l];
            flags[l] = present[at] && ns[l] > 0 ? -1 : 0;
            any |= flags[l];
            vxs[l] = vectors[2 * at];
            vys[l] = vectors[2 * at + 1];
#ifdef HAVE_FP64
            if (own_counts && flags[l])
                ns[l] = max(ns[l], sample_count(vxs[l], vys[l]));
#endif
#if CURVED
            cxs[l] = curvature[2 * at];
            cys[l] = curvature[2 * at + 1];
#endif
        }
        if (!any)
            continue;
        use[m] = k;
        vx[m] = vload8(0, vxs);
        vy[m] = vload8(0, vys);
#if CURVED
        cx[m] = vload8(0, cxs);
        cy[m] = vload8(0, cys);
#endif
        there[m] = vload8(0, flags);
        ++m;
    }
    N = vload8(0, ns);
    int nmax = max(max(max(N.s0, N.s1), max(N.s2, N.s3)), max(max(N.s4, N.s5), max(N.s6, N.s7)));
    float8 den = convert_float8(max(N - 1, 1));
    float8 n1 = convert_float8(N - 1);
    float8 px = (float8)((float)(c0 + col0)) + (float8)(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f);
    float8 py = (float8)((float)(r0 + row));
    /* the weight of a sample that is no end (all of them without ends), and of an end:
     * end_weight() per lane */
    float8 wn = ends ? select(1.0f / convert_float8(N - 1), (float8)(1.0f), N == 1)
                     : 1.0f / convert_float8(N);
    float8 wend = ends ? select(0.5f * (1.0f / convert_float8(N - 1)), (float8)(1.0f), N == 1)
                       : wn;
    /* A layer (or the image's own vectors) standing still in every lane samples at the
     * pixel itself at every j (px - (0 * num) / den is px exactly): sampled once. */
    bool still[MAXK];
    float16 still_lo[MAXK], still_hi[MAXK];
    for (int q = 0; q < m; ++q) {
        still[q] = all(vx[q] == 0.0f) && all(vy[q] == 0.0f);
#if CURVED
        still[q] = still[q] && all(cx[q] == 0.0f) && all(cy[q] == 0.0f);
#endif
        if (still[q]) {
            sample8(planes + use[q] * plane, h, w, r0, c0, fh, fw, px, py, &still_lo[q],
                    &still_hi[q]);
            still_lo[q] = select((float16)(0.0f), still_lo[q], SPREAD_LO(there[q]));
            still_hi[q] = select((float16)(0.0f), still_hi[q], SPREAD_HI(there[q]));
        }
    }
    bool own_still = all(fx == 0.0f) && all(fy == 0.0f);
    float16 own_lo = 0.0f, own_hi = 0.0f;
    if (own_still)
        sample8(linear, h, w, r0, c0, fh, fw, px, py, &own_lo, &own_hi);
    float16 acc_lo = 0.0f, acc_hi = 0.0f;
    for (int j = 0; j < nmax; ++j) {
        float8 num = (float8)((float)j) - anchor * n1;
#if CURVED
        float8 tt = (num * num) / (den * den);
#else
        float8 tt = 0.0f;  /* unread */
#endif
        float8 left = 1.0f;
        float16 e_lo = 0.0f, e_hi = 0.0f, s_lo, s_hi;
        for (int q = 0; q < m; ++q) {
            if (still[q]) {
                s_lo = still_lo[q];
                s_hi = still_hi[q];
            } else {
                float8 x = px - (vx[q] * num) / den;
                float8 y = py - (vy[q] * num) / den;
                BEND(x, y, q);
                if (warped[use[q]]) {
                    size_t field = (size_t)use[q] * h * w * 2;
                    inverse_motion8(vectors + field, curvature + (CURVED ? field : 0), h, w,
                                    r0, c0, fh, fw, px, py, num, den, tt, &x, &y);
                }
                sample8(planes + use[q] * plane, h, w, r0, c0, fh, fw, x, y, &s_lo, &s_hi);
                s_lo = select((float16)(0.0f), s_lo, SPREAD_LO(there[q]));
                s_hi = select((float16)(0.0f), s_hi, SPREAD_HI(there[q]));
            }
            e_lo += SPREAD_LO(left) * s_lo;
            e_hi += SPREAD_HI(left) * s_hi;
            left = left * (1.0f - COVER(s_lo, s_hi));
            if (!any(left != 0.0f))
                break;  /* opaque in every lane: the rest would add +-0 (as the scalar kernel) */
        }
        float8 wj = select((float8)(0.0f),
                           weighted ? (float8)(weights[j])
                                    : select(wn, wend, ((int8)(j) == 0) | ((int8)(j) == N - 1)),
                           (int8)(j) < N);
        if (!any(left != 0.0f)) {  /* e + T * s with T = +-0 is e */
            acc_lo += SPREAD_LO(wj) * e_lo;
            acc_hi += SPREAD_HI(wj) * e_hi;
            continue;
        }
        if (own_still) {
            s_lo = own_lo;
            s_hi = own_hi;
        } else {
            float8 x = px - (fx * num) / den;
            float8 y = py - (fy * num) / den;
            sample8(linear, h, w, r0, c0, fh, fw, x, y, &s_lo, &s_hi);
        }
        acc_lo += SPREAD_LO(wj) * (e_lo + SPREAD_LO(left) * s_lo);
        acc_hi += SPREAD_HI(wj) * (e_hi + SPREAD_HI(left) * s_hi);
    }
    float a[2 * 16];
    vstore16(acc_lo, 0, a);
    vstore16(acc_hi, 1, a);
    for (int l = 0; l < LANES; ++l)
        for (int c = 0; c < CHANNELS; ++c)
            out[((size_t)i * LANES + l) * CHANNELS + c] = a[l * CP + c];
}
#endif
