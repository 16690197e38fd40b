/* Forward camera responses and output quantisation (clblur.responses, clblur.pixels).
 *
 * Conventions
 * - Shared constants (RESP_STRIDE, QHEAD, KIND_*, OUT_*, IN_*, LANES, GROUP) come from the
 *   host as -D build options (clblur/opencl/constants.py); this file never spells them.
 * - A channel's response is RESP_STRIDE floats in a __constant array:
 *   [kind, parameter, table offset, table length], kind codes KIND_* (clblur.responses).
 *   exp: parameter = k;  gamma: parameter = 1/gamma (precomputed on the host);
 *   table: `tables[offset .. offset+len)` holds exposures, the next `len` floats the values.
 * - Float images are linearised here too (inverse_response8); integer images through the
 *   host's float64 tables (integrate.cl linear_channel).
 * - Quantisation: integer outputs are rint(clamp(v, 0, 1) * Imax) (clblur.pixels), found by
 *   comparing the exposure with the host's float64 inverse response at the code boundaries,
 *   never by evaluating the response on the device.  float32 outputs evaluate the response
 *   in float32 and are stored unrounded.
 */

/* The parameters every integrating kernel ends with: packed responses, quantisation tables
 * and the output (kind, channel count, first channel and size of this pass's group). */
#define STORE_PARAMS                                                                      \
    __constant const float *resp, __global const float *tables,                            \
    __global const float *thresholds, __global const int *buckets,                         \
    __global uchar *restrict out, int out_kind, int channels, int cbase, int cg

/* Their names, to hand them on to the store helpers. */
#define STORE_ARGS resp, tables, thresholds, buckets, out, out_kind, channels, cbase, cg

/* np.interp on a strictly increasing table: hold the end values outside. */
static float table_forward(float x, __global const float *xs, __global const float *vs, int n)
{
    if (x <= xs[0]) return vs[0];
    if (x >= xs[n - 1]) return vs[n - 1];
    int lo = 0, hi = n - 1;              /* invariant: xs[lo] <= x < xs[hi] */
    while (hi - lo > 1) {
        int mid = (lo + hi) >> 1;
        if (xs[mid] <= x) lo = mid; else hi = mid;
    }
    return vs[lo] + (x - xs[lo]) * ((vs[hi] - vs[lo]) / (xs[hi] - xs[lo]));
}

/* x^p for x in [0, 1] and p > 0, as exp2(p log2 x) (x = 0: exp2(-inf) = 0).  PoCL's scalar
 * powr is a slow library call on CPUs: 12.6 M values took 932 ms against 109 ms for this form
 * (one thread per value, 2-core VM).  Its error, about |p log2 x| float32 ulps of the result
 * (under 3e-6 relative down to x = 2^-24), is far inside the float-output bound of
 * docs/tolerances.md. */
static float power01(float x, float p)
{
    return exp2(p * log2(x));
}

static float forward_response(float x, __constant const float *resp, __global const float *tables)
{
    int kind = (int)resp[0];
    float p = resp[1];
    switch (kind) {
    case KIND_EXP:
        return -expm1(-p * x);
    case KIND_GAMMA:
        return power01(clamp(x, 0.0f, 1.0f), p);  /* bounded: full scale at x >= 1 */
    case KIND_SRGB: {
        float xc = clamp(x, 0.0f, 1.0f);
        /* knee at the exact image of the value knee 0.04045, as clblur.responses.SRGB */
        return xc <= 0.04045f / 12.92f ? 12.92f * xc : 1.055f * power01(xc, 1.0f / 2.4f) - 0.055f;
    }
    case KIND_TABLE: {
        int off = (int)resp[2], n = (int)resp[3];
        return table_forward(x, tables + off, tables + off + n, n);
    }
    default:  /* KIND_LINEAR */
        return x;
    }
}

/* forward_response for a pixel's channel group (cg channels) at once: one vector evaluation
 * where its channels share a closed-form kind (per-channel parameters), else channel by
 * channel.  Lanes past cg are computed but never stored. */
static float4 forward_response4(float4 x, __constant const float *resp,
                                __global const float *tables, int cg)
{
    int kind = (int)resp[0];
    bool shared = (cg < 2 || (int)resp[RESP_STRIDE] == kind) &&
                  (cg < 3 || (int)resp[2 * RESP_STRIDE] == kind) &&
                  (cg < 4 || (int)resp[3 * RESP_STRIDE] == kind);
    if (shared && kind != KIND_TABLE) {
        float4 p = (float4)(resp[1], resp[1 + RESP_STRIDE], resp[1 + 2 * RESP_STRIDE],
                            resp[1 + 3 * RESP_STRIDE]);
        float4 xc = clamp(x, 0.0f, 1.0f);
        switch (kind) {
        case KIND_EXP:
            return -expm1(-p * x);
        case KIND_GAMMA:
            return exp2(p * log2(xc));  /* power01 */
        case KIND_SRGB:
            return select(1.055f * exp2((1.0f / 2.4f) * log2(xc)) - 0.055f, 12.92f * xc,
                          xc <= 0.04045f / 12.92f);
        default:  /* KIND_LINEAR */
            return x;
        }
    }
    return (float4)(forward_response(x.x, resp, tables),
                    forward_response(x.y, resp + RESP_STRIDE, tables),
                    forward_response(x.z, resp + 2 * RESP_STRIDE, tables),
                    forward_response(x.w, resp + 3 * RESP_STRIDE, tables));
}

/* The inverse responses of float images, eight values of one channel at a time (the host's
 * clblur.pixels.linearise, in float32; the saturation policy is the caller's).  `v` lies in
 * [0, top]; `gamma` is the gamma exponent itself (the packed parameter is its reciprocal).
 * Tables interpolate their samples the other way round, one value at a time. */
static float8 inverse_response8(float8 v, __constant const float *resp,
                                __global const float *tables, float gamma)
{
    switch ((int)resp[0]) {
    case KIND_EXP:
        return -log1p(-v) / resp[1];
    case KIND_GAMMA:
        return exp2(gamma * log2(v));  /* power01, eight at a time */
    case KIND_SRGB:
        return select(exp2(2.4f * log2((v + 0.055f) / 1.055f)), v / 12.92f, v <= 0.04045f);
    case KIND_TABLE: {
        int off = (int)resp[2], n = (int)resp[3];
        float e[8];
        vstore8(v, 0, e);
        for (int j = 0; j < 8; j++)
            e[j] = table_forward(e[j], tables + off + n, tables + off, n);
        return vload8(0, e);
    }
    default:  /* KIND_LINEAR */
        return v;
    }
}

/* Integer output codes.  thresholds[k] (k < Imax) is the exposure where the response crosses
 * (k + 1/2) / Imax, computed in float64 on the host and rounded to float32 (odd ones lowered
 * one step, so that exact ties round to even); later entries are +inf.  The code of an
 * exposure is the number of thresholds below it: rint(clamp(I(e), 0, 1) * Imax), except for
 * e within float rounding of a threshold.  A bucket table narrows the search: the bit
 * pattern of a float e >= 0 is monotone in e, so (bits >> shift) - base picks a narrow
 * logarithmic bucket; its entry counts the thresholds below the bucket's start, and at most
 * 2^steps - 1 more lie inside, found in `steps` halvings (one bucket and steps = log2 of
 * the table length is a plain binary search).  Header buckets[0..4]: shift, base, bucket
 * count nb, steps, threshold row stride; channel k's counts start at QHEAD + k nb, its
 * thresholds at k stride.  Rows are padded with +inf so no probe leaves its row. */

static int quantise(float e, __global const float *thresholds, __global const int *buckets,
                    int k)
{
    e = e > 0.0f ? e : 0.0f;  /* also maps -0.0, whose bit pattern is not monotone */
    int nb = buckets[2];
    int b = clamp((int)(as_uint(e) >> buckets[0]) - buckets[1], 0, nb - 1);
    __global const float *t = thresholds + k * buckets[4];
    int q = buckets[QHEAD + k * nb + b];
    for (int step = 1 << (buckets[3] - 1); step > 0; step >>= 1)
        q += t[q + step - 1] < e ? step : 0;
    return q;
}

/* quantise() for four pixels' channel groups at once (e: pixel-major, 4 channels each).
 * The host pads the tables to four channels, so every lane has its own. */
static int16 quantise16(float16 e, __global const float *thresholds,
                        __global const int *buckets)
{
    int nb = buckets[2];
    const int16 channel = (int16)(0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3);
    e = select((float16)(0.0f), e, e > 0.0f);
    int16 b = clamp((as_int16(e) >> buckets[0]) - buckets[1], 0, nb - 1) + channel * nb;
    __global const int *counts = buckets + QHEAD;
    int16 q = (int16)(counts[b.s0], counts[b.s1], counts[b.s2], counts[b.s3],
                      counts[b.s4], counts[b.s5], counts[b.s6], counts[b.s7],
                      counts[b.s8], counts[b.s9], counts[b.sa], counts[b.sb],
                      counts[b.sc], counts[b.sd], counts[b.se], counts[b.sf]);
    int16 row = channel * buckets[4];
    for (int step = 1 << (buckets[3] - 1); step > 0; step >>= 1) {
        int16 at = row + q + (step - 1);
        float16 t = (float16)(thresholds[at.s0], thresholds[at.s1], thresholds[at.s2],
                              thresholds[at.s3], thresholds[at.s4], thresholds[at.s5],
                              thresholds[at.s6], thresholds[at.s7], thresholds[at.s8],
                              thresholds[at.s9], thresholds[at.sa], thresholds[at.sb],
                              thresholds[at.sc], thresholds[at.sd], thresholds[at.se],
                              thresholds[at.sf]);
        q += select((int16)(0), (int16)(step), t < e);
    }
    return q;
}

/* quantise16() with one lookup per value (the box kernels, uint8 outputs): a uniform grid
 * over exposures (clblur/opencl/quantisation.py quantisation_grid), cell g = e * gscale
 * (truncated, clamped to the last cell), holds the code of every exposure in it, or the flag
 * GRID_SEARCH where a code boundary lies inside the cell: a vector meeting one takes the
 * search.  Same codes as quantise16; about half its loads.  `gstride` is the cells per
 * channel, 0 where the channels share one row. */
__attribute__((always_inline))
static int16 quantise16_grid(float16 e, __global const int *grid, int cells, int gstride,
                             float gscale, __global const float *thresholds,
                             __global const int *buckets)
{
    const int16 channel = (int16)(0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3);
    e = select((float16)(0.0f), e, e > 0.0f);
    int16 g = min(convert_int16(fmin(e * gscale, (float16)((float)(cells - 1)))), cells - 1)
              + channel * gstride;
    int16 q = (int16)(grid[g.s0], grid[g.s1], grid[g.s2], grid[g.s3], grid[g.s4], grid[g.s5],
                      grid[g.s6], grid[g.s7], grid[g.s8], grid[g.s9], grid[g.sa], grid[g.sb],
                      grid[g.sc], grid[g.sd], grid[g.se], grid[g.sf]);
    int8 o8 = q.lo | q.hi;  /* any lane flagged: an OR tree (any() scalarises on PoCL) */
    int4 o4 = o8.lo | o8.hi;
    int2 o2 = o4.lo | o4.hi;
    if ((o2.x | o2.y) & GRID_SEARCH)
        return quantise16(e, thresholds, buckets);
    return q;
}

/* Store the integer codes of one pixel's channel group (uint8 or uint16 output). */
static void store_codes(int4 q, __global uchar *restrict out, int out_kind, size_t pixel,
                        int channels, int cbase, int cg)
{
    size_t base = pixel * (size_t)channels + (size_t)cbase;
    if (out_kind == OUT_U8) {
        out[base] = (uchar)q.x;
        if (cg > 1) out[base + 1] = (uchar)q.y;
        if (cg > 2) out[base + 2] = (uchar)q.z;
        if (cg > 3) out[base + 3] = (uchar)q.w;
    } else {  /* OUT_U16 */
        __global ushort *o = (__global ushort *)out;
        o[base] = (ushort)q.x;
        if (cg > 1) o[base + 1] = (ushort)q.y;
        if (cg > 2) o[base + 2] = (ushort)q.z;
        if (cg > 3) o[base + 3] = (ushort)q.w;
    }
}

/* Forward-map and quantise the accumulated exposures of one pixel's channel group: integer
 * outputs by the threshold search (four channels at once), float32 outputs by evaluating
 * the response for the whole group (forward_response4). */
static void store_pixel(float4 acc, size_t pixel, STORE_PARAMS)
{
    if (out_kind != OUT_F32) {
        int4 q = (int4)(quantise(acc.x, thresholds, buckets, 0),
                        quantise(acc.y, thresholds, buckets, 1),
                        quantise(acc.z, thresholds, buckets, 2),
                        quantise(acc.w, thresholds, buckets, 3));
        store_codes(q, out, out_kind, pixel, channels, cbase, cg);
        return;
    }
    __global float *o = (__global float *)out + pixel * (size_t)channels + (size_t)cbase;
    float4 v = forward_response4(acc, resp, tables, cg);
    o[0] = v.x;
    if (cg > 1) o[1] = v.y;
    if (cg > 2) o[2] = v.z;
    if (cg > 3) o[3] = v.w;
}
