/* Forward camera responses and output quantisation (clblur.responses, clblur.pixels).
 *
 * Conventions
 * - A channel's response is RESP_STRIDE floats in a __constant array:
 *   [kind, parameter, table offset, table length].  Kind codes are
 *   clblur.responses.KIND_CODES; keep them in step.
 *   exp: parameter = k;  gamma: parameter = 1/gamma (precomputed on the host);
 *   table: `tables[offset .. offset+len)` holds exposures, the next `len` floats the values.
 * - Quantisation: integer outputs rint(clamp(v, 0, 1) * Imax), rint rounds half to even
 *   (the IEEE default, as numpy.rint).  float32 outputs are stored unrounded.
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
        return xc <= 0.0031308f ? 12.92f * xc : 1.055f * powr(xc, 1.0f / 2.4f) - 0.055f;
    }
    case KIND_TABLE: {
        int off = (int)resp[2], n = (int)resp[3];
        return table_forward(x, tables + off, tables + off + n, n);
    }
    default:
        return x;
    }
}

/* Forward-map and quantise the accumulated exposures of one pixel's channel group. */
static void store_pixel(float4 acc, __global uchar *out, int out_kind, size_t pixel,
                        int channels, int cbase, int cg, __constant const float *resp,
                        __global const float *tables)
{
    float e[4] = {acc.x, acc.y, acc.z, acc.w};
    size_t base = pixel * (size_t)channels + (size_t)cbase;
    for (int k = 0; k < cg; ++k) {
        float v = forward_response(e[k], resp + k * RESP_STRIDE, tables);
        if (out_kind == OUT_U8)
            out[base + k] = convert_uchar(rint(clamp(v, 0.0f, 1.0f) * 255.0f));
        else if (out_kind == OUT_U16)
            ((__global ushort *)out)[base + k] = convert_ushort(rint(clamp(v, 0.0f, 1.0f) * 65535.0f));
        else
            ((__global float *)out)[base + k] = v;
    }
}
