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
 *   count N; weights: N time weights when weighted != 0, else 1/N each.
 * - Sample j of a pixel p reads each layer k at p - D_k(p) (j - a (N-1)) / max(N-1, 1).
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
#define CP (CHANNELS + 1)

/* Bilinear taps at full-image (x, y), clamped to the image, then to the crop. */
typedef struct {
    size_t a, b, c, d;
    float fx, fy;
} taps;

static taps locate(int h, int w, int r0, int c0, int fh, int fw, float x, float y)
{
    taps t;
    x = clamp(x, 0.0f, (float)(fw - 1));
    y = clamp(y, 0.0f, (float)(fh - 1));
    float fx0 = floor(x), fy0 = floor(y);
    int x0 = (int)fx0, y0 = (int)fy0;
    int x1 = min(x0 + 1, fw - 1), y1 = min(y0 + 1, fh - 1);
    t.fx = x - fx0;
    t.fy = y - fy0;
    x0 = clamp(x0 - c0, 0, w - 1);
    x1 = clamp(x1 - c0, 0, w - 1);
    y0 = clamp(y0 - r0, 0, h - 1);
    y1 = clamp(y1 - r0, 0, h - 1);
    t.a = (size_t)y0 * w + x0;
    t.b = (size_t)y0 * w + x1;
    t.c = (size_t)y1 * w + x0;
    t.d = (size_t)y1 * w + x1;
    return t;
}

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
    const int channels = CHANNELS;
    int N = counts[i];
    float den = (float)max(N - 1, 1);
    size_t plane = (size_t)h * w * CP;
    size_t at = (size_t)row * w + col;
    /* the layers that can reach this pixel, front to back, with their vectors */
    int use[MAXK];
    float vx[MAXK], vy[MAXK];
    int m = 0;
    for (int k = 0; k < layers; ++k) {
        if (!present[(size_t)k * h * w + at])
            continue;  /* the layer cannot reach this pixel: it would add zeros */
        use[m] = k;
        vx[m] = vectors[((size_t)k * h * w + at) * 2];
        vy[m] = vectors[((size_t)k * h * w + at) * 2 + 1];
        ++m;
    }
    float fx = flow[2 * at], fy = flow[2 * at + 1];
    float acc[CHANNELS], e[CHANNELS];
    for (int c = 0; c < channels; ++c)
        acc[c] = 0.0f;
    for (int j = 0; j < N; ++j) {
        float num = (float)j - anchor * (float)(N - 1);
        float left = 1.0f;
        for (int c = 0; c < channels; ++c)
            e[c] = 0.0f;
        for (int q = 0; q < m && left != 0.0f; ++q) {
            float x = px - (vx[q] * num) / den;
            float y = py - (vy[q] * num) / den;
            px_t s = sample(planes + use[q] * plane, locate(h, w, r0, c0, fh, fw, x, y));
            for (int c = 0; c < channels; ++c)
                e[c] += left * CH(s, c);
            left = left * (1.0f - CH(s, channels));
        }
        float wj = weighted ? weights[j] : 1.0f / (float)N;
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
