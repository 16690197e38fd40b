/* Layered exposure: front-to-back composite of every shutter sample (clblur/layered_exposure.py,
 * function composite, is the float64 specification).
 *
 * Conventions
 * - Arrays cover a crop (h x w) starting at full-image (r0, c0) of an fh x fw image; positions
 *   are full-image coordinates, clamped to the image (clamp-to-edge), then to the crop.
 * - Build option -DCHANNELS=C (the light channels).
 * - planes: K x h x w x CP floats, premultiplied (colour * coverage ..., coverage), CP = C + 1.
 * - vectors: K x h x w x 2 (dx, dy) per layer; flow: h x w x 2, the image's own vectors;
 *   linear: h x w x C, the linear image (light no layer covers is read from it).
 * - present: K x h x w, 0 where layer k cannot reach the pixel at any sample (skipped).
 * - One work-item per listed pixel (pix: n x 2 (row, col) in the crop); counts: its sample
 *   count N; weights: N time weights when weighted != 0, else 1/N each.
 * - Sample j of a pixel p reads each layer k at p - D_k(p) (j - a (N-1)) / max(N-1, 1).
 * - Floating-point contraction is off: every a*b+c is rounded as written.
 */
#pragma OPENCL FP_CONTRACT OFF

/* CHANNELS (light channels, C) is a build option: loops over channels unroll and the
 * per-sample accumulators stay in registers. */
#ifndef CHANNELS
#define CHANNELS 3
#endif
#define CP (CHANNELS + 1)

static void sample(__global const float *img, const int cp, int h, int w, int r0, int c0, int fh,
                   int fw, float x, float y, float *out)
{
    x = clamp(x, 0.0f, (float)(fw - 1));
    y = clamp(y, 0.0f, (float)(fh - 1));
    float fx0 = floor(x), fy0 = floor(y);
    int x0 = (int)fx0, y0 = (int)fy0;
    int x1 = min(x0 + 1, fw - 1), y1 = min(y0 + 1, fh - 1);
    float fx = x - fx0, fy = y - fy0;
    x0 = clamp(x0 - c0, 0, w - 1);
    x1 = clamp(x1 - c0, 0, w - 1);
    y0 = clamp(y0 - r0, 0, h - 1);
    y1 = clamp(y1 - r0, 0, h - 1);
    __global const float *a = img + ((size_t)y0 * w + x0) * cp;
    __global const float *b = img + ((size_t)y0 * w + x1) * cp;
    __global const float *c = img + ((size_t)y1 * w + x0) * cp;
    __global const float *d = img + ((size_t)y1 * w + x1) * cp;
    for (int i = 0; i < cp; ++i) {
        float top = a[i] * (1.0f - fx) + b[i] * fx;
        float bottom = c[i] * (1.0f - fx) + d[i] * fx;
        out[i] = top * (1.0f - fy) + bottom * fy;
    }
}

__kernel void composite_layers(__global const float *planes, __global const float *vectors,
                               __global const float *flow, __global const float *linear,
                               __global const uchar *present, __global const int *pix, __global const int *counts,
                               __global const float *weights, int weighted, int n,
                               int layers, int h, int w, int r0, int c0,
                               int fh, int fw, float anchor, __global float *out)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    int row = pix[2 * i], col = pix[2 * i + 1];
    float px = (float)(c0 + col), py = (float)(r0 + row);
    const int channels = CHANNELS, cp = CP;
    int N = counts[i];
    float den = (float)max(N - 1, 1);
    size_t plane = (size_t)h * w * cp;
    size_t at = (size_t)row * w + col;
    float acc[CHANNELS], e[CHANNELS], s[CP];
    for (int c = 0; c < channels; ++c)
        acc[c] = 0.0f;
    for (int j = 0; j < N; ++j) {
        float num = (float)j - anchor * (float)(N - 1);
        float left = 1.0f;
        for (int c = 0; c < channels; ++c)
            e[c] = 0.0f;
        for (int k = 0; k < layers; ++k) {
            if (!present[(size_t)k * h * w + at])
                continue;  /* the layer cannot reach this pixel: it would add zeros */
            __global const float *v = vectors + ((size_t)k * h * w + at) * 2;
            float x = px - (v[0] * num) / den;
            float y = py - (v[1] * num) / den;
            sample(planes + k * plane, cp, h, w, r0, c0, fh, fw, x, y, s);
            for (int c = 0; c < channels; ++c)
                e[c] += left * s[c];
            left = left * (1.0f - s[channels]);
        }
        float x = px - (flow[2 * at] * num) / den;
        float y = py - (flow[2 * at + 1] * num) / den;
        sample(linear, channels, h, w, r0, c0, fh, fw, x, y, s);
        float wj = weighted ? weights[j] : 1.0f / (float)N;
        for (int c = 0; c < channels; ++c)
            acc[c] += wj * (e[c] + left * s[c]);
    }
    for (int c = 0; c < channels; ++c)
        out[(size_t)i * channels + c] = acc[c];
}
