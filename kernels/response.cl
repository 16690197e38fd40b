/* Forward camera responses and output quantisation (clblur.responses, clblur.pixels).
 *
 * Conventions
 * - A channel's response is RESP_STRIDE floats in a __constant array:
 *   [kind, parameter, table offset, table length].  Kind codes are
 *   clblur.responses.KIND_CODES; keep them in step.
 *   exp: parameter = k;  gamma: parameter = 1/gamma (precomputed on the host);
 *   table: `tables[offset .. offset+len)` holds exposures, the next `len` floats the values.
 * - Quantisation: integer outputs are rint(clamp(v, 0, 1) * Imax) (clblur.pixels), found by
 *   comparing the exposure with the host's float64 inverse response at the code boundaries,
 *   never by evaluating the response on the device.  float32 outputs evaluate the response
 *   in float32 and are stored unrounded.
 */

#define KIND_LINEAR 0
#define KIND_EXP 1
#define KIND_GAMMA 2
#define KIND_SRGB 3
#define KIND_TABLE 4
#define RESP_STRIDE 4

#define OUT_U8 0
#define OUT_U16 1
#define OUT_F32 2

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

static float forward_response(float x, __constant const float *resp, __global const float *tables)
{
    int kind = (int)resp[0];
    float p = resp[1];
    switch (kind) {
    case KIND_EXP:
        return -expm1(-p * x);
    case KIND_GAMMA:
        return powr(fmax(x, 0.0f), p);
    case KIND_SRGB: {
        float xc = fmax(x, 0.0f);
        /* knee at the exact image of the value knee 0.04045, as clblur.responses.SRGB */
        return xc <= 0.04045f / 12.92f ? 12.92f * xc : 1.055f * powr(xc, 1.0f / 2.4f) - 0.055f;
    }
    case KIND_TABLE: {
        int off = (int)resp[2], n = (int)resp[3];
        return table_forward(x, tables + off, tables + off + n, n);
    }
    default:
        return x;
    }
}

/* Integer output code of exposure e: the number of thresholds below it.  thresholds[k] is
 * the exposure where the response crosses (k + 1/2) / Imax, so the count equals
 * rint(clamp(I(e), 0, 1) * Imax) except for e within float rounding of a threshold.  The
 * table has 2^bits entries (padded with +inf), bits = 8 or 16, searched in `bits` steps. */
static int quantise_by_thresholds(float e, __global const float *thresholds, int bits)
{
    int q = 0;
    if (bits == 16) {
        q += thresholds[q + 32767] < e ? 32768 : 0;
        q += thresholds[q + 16383] < e ? 16384 : 0;
        q += thresholds[q + 8191] < e ? 8192 : 0;
        q += thresholds[q + 4095] < e ? 4096 : 0;
        q += thresholds[q + 2047] < e ? 2048 : 0;
        q += thresholds[q + 1023] < e ? 1024 : 0;
        q += thresholds[q + 511] < e ? 512 : 0;
        q += thresholds[q + 255] < e ? 256 : 0;
    }
    /* unrolled: a loop here costs three times as much on PoCL */
    q += thresholds[q + 127] < e ? 128 : 0;
    q += thresholds[q + 63] < e ? 64 : 0;
    q += thresholds[q + 31] < e ? 32 : 0;
    q += thresholds[q + 15] < e ? 16 : 0;
    q += thresholds[q + 7] < e ? 8 : 0;
    q += thresholds[q + 3] < e ? 4 : 0;
    q += thresholds[q + 1] < e ? 2 : 0;
    q += thresholds[q] < e ? 1 : 0;
    return q;
}

/* The same count found from a bucket table (built on the host, see
 * clblur.opencl_prep.quantisation_buckets): the float bit pattern of e >= 0 is monotone in
 * e, so (bits >> shift) - base picks a narrow logarithmic bucket; buckets[4 + bucket] is
 * the count of thresholds below the bucket's start, and at most kmax more thresholds lie
 * inside any bucket.  Header: buckets[0..3] = shift, base, bucket count nb, kmax; channel
 * k's table follows at 4 + k * nb. */
static int quantise_by_buckets(float e, __global const float *thresholds,
                               __global const int *buckets, int channel)
{
    e = e > 0.0f ? e : 0.0f;  /* also maps -0.0, whose bit pattern is not monotone */
    int b = clamp((int)(as_uint(e) >> buckets[0]) - buckets[1], 0, buckets[2] - 1);
    int q = buckets[4 + channel * buckets[2] + b];
    for (int s = 0; s < buckets[3]; ++s)
        q += thresholds[q] < e ? 1 : 0;
    return q;
}

/* quantise_by_buckets for four pixels' channel groups at once (e: pixel-major, 4 channels
 * each).  The host pads the tables to four channels, so every lane has its own. */
static int16 quantise16_by_buckets(float16 e, __global const float *thresholds,
                                   __global const int *buckets)
{
    int nb = buckets[2];
    const int16 channel = (int16)(0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3);
    e = select((float16)(0.0f), e, e > 0.0f);
    int16 b = clamp((as_int16(e) >> buckets[0]) - buckets[1], 0, nb - 1) + channel * nb;
    __global const int *counts = buckets + 4;
    int16 q = (int16)(counts[b.s0], counts[b.s1], counts[b.s2], counts[b.s3],
                      counts[b.s4], counts[b.s5], counts[b.s6], counts[b.s7],
                      counts[b.s8], counts[b.s9], counts[b.sa], counts[b.sb],
                      counts[b.sc], counts[b.sd], counts[b.se], counts[b.sf]);
    int16 at = q + (channel << 8);
    for (int s = 0; s < buckets[3]; ++s) {
        float16 t = (float16)(thresholds[at.s0], thresholds[at.s1], thresholds[at.s2],
                              thresholds[at.s3], thresholds[at.s4], thresholds[at.s5],
                              thresholds[at.s6], thresholds[at.s7], thresholds[at.s8],
                              thresholds[at.s9], thresholds[at.sa], thresholds[at.sb],
                              thresholds[at.sc], thresholds[at.sd], thresholds[at.se],
                              thresholds[at.sf]);
        int16 up = -(t < e);
        q += up;
        at += up;
    }
    return q;
}

/* Store the quantised codes of one pixel's channel group. */
static void store_codes(int4 q, __global uchar *restrict out, size_t pixel, int channels,
                        int cbase, int cg)
{
    size_t base = pixel * (size_t)channels + (size_t)cbase;
    out[base] = (uchar)q.x;
    if (cg > 1) out[base + 1] = (uchar)q.y;
    if (cg > 2) out[base + 2] = (uchar)q.z;
    if (cg > 3) out[base + 3] = (uchar)q.w;
}

/* Forward-map and quantise one channel's accumulated exposure into out[index]. */
static void store_channel(float e, __global uchar *restrict out, int out_kind, size_t index, int k,
                          __constant const float *resp, __global const float *tables,
                          __global const float *thresholds, __global const int *buckets)
{
    if (out_kind == OUT_U8)
        out[index] = (uchar)(buckets[2] > 0
                             ? quantise_by_buckets(e, thresholds + (k << 8), buckets, k)
                             : quantise_by_thresholds(e, thresholds + (k << 8), 8));
    else if (out_kind == OUT_U16)
        ((__global ushort *)out)[index] =
            (ushort)quantise_by_thresholds(e, thresholds + (k << 16), 16);
    else
        ((__global float *)out)[index] = forward_response(e, resp + k * RESP_STRIDE, tables);
}

/* Forward-map and quantise the accumulated exposures of one pixel's channel group.
 * Integer outputs compare the exposure with per-channel threshold tables (2^8 or 2^16
 * floats per channel; buckets when the host built them, else binary search); float32
 * outputs evaluate the response.  Channels are spelled out (no private array), which keeps
 * them in registers. */
static void store_pixel(float4 acc, __global uchar *restrict out, int out_kind, size_t pixel,
                        int channels, int cbase, int cg, __constant const float *resp,
                        __global const float *tables, __global const float *thresholds,
                        __global const int *buckets)
{
    size_t base = pixel * (size_t)channels + (size_t)cbase;
    if (out_kind == OUT_U8 && buckets[2] > 0) {
        /* quantise_by_buckets for the four channels at once (the host pads the threshold
         * and bucket tables to four channels, so no lane reads out of range) */
        int nb = buckets[2];
        float4 e = select((float4)(0.0f), acc, acc > 0.0f);
        int4 b = clamp((as_int4(e) >> buckets[0]) - buckets[1], 0, nb - 1);
        __global const int *counts = buckets + 4;
        int4 q = (int4)(counts[b.x], counts[nb + b.y], counts[2 * nb + b.z],
                        counts[3 * nb + b.w]);
        for (int s = 0; s < buckets[3]; ++s) {
            float4 t = (float4)(thresholds[q.x], thresholds[256 + q.y], thresholds[512 + q.z],
                                thresholds[768 + q.w]);
            q -= t < e;  /* a true vector comparison is -1 */
        }
        out[base] = (uchar)q.x;
        if (cg > 1) out[base + 1] = (uchar)q.y;
        if (cg > 2) out[base + 2] = (uchar)q.z;
        if (cg > 3) out[base + 3] = (uchar)q.w;
        return;
    }
    store_channel(acc.x, out, out_kind, base, 0, resp, tables, thresholds, buckets);
    if (cg > 1) store_channel(acc.y, out, out_kind, base + 1, 1, resp, tables, thresholds, buckets);
    if (cg > 2) store_channel(acc.z, out, out_kind, base + 2, 2, resp, tables, thresholds, buckets);
    if (cg > 3) store_channel(acc.w, out, out_kind, base + 3, 3, resp, tables, thresholds, buckets);
}
