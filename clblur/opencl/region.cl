/* The pixels that take the layered path (clblur/opencl/region.py is the host side;
 * clblur/layered_exposure.py region_mask is the specification).
 *
 * Conventions
 * - v: h x w x 2 float (dx, dy), row-major; a pixel is (x, y) = (column, row).
 * - Tiles of `tile` px; th x tw tiles cover the image, the last row / column of tiles padded
 *   by repeating the image's edge (numpy's pad mode "edge"): a padded pixel repeats an image
 *   pixel, so it adds no new value to a min or a max, and reading the clamped pixel is the
 *   same thing.
 * - Six kernels, in this order, the buffers staying on the device:
 *   tile_extrema  per tile the min and max of each component (tmin, tmax: th x tw x 2),
 *                 and its longest vector (the host finishes the reach R from them: one small
 *                 download, the only wait before the mask's);
 *   tile_flags    per tile the min / max over the (2 around + 1)^2 tiles around it, borders
 *                 "nearest" (clamped: again no new value, so the window is cut at the grid),
 *                 flagged where max - min > spread in x or y (flags: th x tw uchar);
 *   tile_wanted   the tiles within reach of a flagged tile's `near` search;
 *   pixel_bits    per pixel of a wanted tile the 3 x 3 spread (max - min) of each component,
 *                 outside the image ignored (what repeating the edge gives for a 3 x 3
 *                 window): bit 0 `edge` (spread > `spread` in x or y), bit 1 `varies`
 *                 (spread > 0 in x or y);
 *   edge_gaps     per column, in segments of `seg` rows that meet a wanted tile, the
 *                 vertical distance from each pixel to the nearest edge pixel of its column,
 *                 capped at bound + 1;
 *   region        per pixel of a flagged tile: `near` (an edge pixel at squared distance
 *                 <= k2), else where `varies` the inverse departure > spread (`warped`);
 *                 out = (near | warped) & flagged tile, uchar 0/1 for every pixel.
 * - `near` is exact: the reference takes sqrt(d2) <= r + 2 in double, d2 the integer squared
 *   distance; sqrt is monotonic, so that is d2 <= k2 with k2 the largest such integer, found
 *   on the host with the same correctly rounded double sqrt (no fp64 needed here).  Only
 *   distances up to sqrt(k2) matter, so the search is bounded: bound = floor(sqrt(k2)) rows
 *   per column (edge_gaps), then the columns within bound of the pixel (region).
 * - Every comparison that decides a bit is formed as numpy forms it in float32: a single
 *   subtraction (max - min) compared with spread as a float (numpy compares a float32 array
 *   with a Python float in float32).  The inverse departure's reading position x - dx * t is
 *   numpy's float32 product, then the subtraction: contraction is off so no fma merges them.
 * - The reference reads the vectors at the departure position with cv2.remap, which rounds
 *   positions to 1/32 px; here they are read bilinearly in float.  Where the vectors vary by
 *   at most `spread` between neighbours (every pixel the read can touch: they are within
 *   r + sqrt(2) of a pixel that is not `near`) the two differ by at most spread / 32 * |t|,
 *   so the result differs only at pixels whose departure lies that close to spread.
 * - Global sizes may be padded past the array sizes: extra work-items return.
 */
#pragma OPENCL FP_CONTRACT OFF

/* One work-item per tile (x: tile column, y: tile row): the extrema, and for the reach the
 * vector of the largest x * x + y * y in the tile, float32 as numpy forms it (two products,
 * then their sum, each rounded: contraction is off).  The host passes the tiles' vectors to
 * clblur.halo.reach, whose maximum over them is its maximum over the whole field.  The edge
 * tiles' padding repeats their own last row / column, so their extrema are those of their
 * pixels in the image. */
__kernel void tile_extrema(__global const float *v, const int h, const int w, const int tile,
                           const int th, const int tw, __global float *tmin,
                           __global float *tmax, __global float *longest)
{
    const int tx = get_global_id(0), ty = get_global_id(1);
    if (tx >= tw || ty >= th)
        return;
    float2 lo = (float2)(INFINITY), hi = (float2)(-INFINITY), pick = (float2)(0.0f);
    float top = -1.0f;
    const int x0 = tx * tile, x1 = min(x0 + tile, w);
    const int y1 = min(ty * tile + tile, h);
    for (int y = ty * tile; y < y1; ++y) {
        __global const float *row = v + (size_t)y * w * 2;
        for (int x = x0; x < x1; ++x) {
            const float2 d = vload2(x, row);
            lo = fmin(lo, d);
            hi = fmax(hi, d);
            const float xx = d.x * d.x, yy = d.y * d.y;
            const float sq = xx + yy;
            if (sq > top) {
                top = sq;
                pick = d;
            }
        }
    }
    const size_t t = (size_t)ty * tw + tx;
    vstore2(lo, t, tmin);
    vstore2(hi, t, tmax);
    vstore2(pick, t, longest);
}

/* One work-item per tile: its neighbourhood's max - min against spread. */
__kernel void tile_flags(__global const float *tmin, __global const float *tmax, const int th,
                         const int tw, const int around, const float spread,
                         __global uchar *flags)
{
    const int tx = get_global_id(0), ty = get_global_id(1);
    if (tx >= tw || ty >= th)
        return;
    float2 lo = (float2)(INFINITY), hi = (float2)(-INFINITY);
    const int j0 = max(ty - around, 0), j1 = min(ty + around, th - 1);
    const int i0 = max(tx - around, 0), i1 = min(tx + around, tw - 1);
    for (int j = j0; j <= j1; ++j)
        for (int i = i0; i <= i1; ++i) {
            const size_t t = (size_t)j * tw + i;
            lo = fmin(lo, vload2(t, tmin));
            hi = fmax(hi, vload2(t, tmax));
        }
    const float2 d = hi - lo;
    flags[(size_t)ty * tw + tx] = (d.x > spread) || (d.y > spread);
}

/* One work-item per tile: wanted where a flagged tile lies within `around` tiles (each
 * axis).  The pixels whose edges a flagged pixel's `near` test can see (within bound px)
 * lie in such tiles when around = ceil(bound / tile): the only ones pixel_bits computes. */
__kernel void tile_wanted(__global const uchar *flags, const int th, const int tw,
                          const int around, __global uchar *wanted)
{
    const int tx = get_global_id(0), ty = get_global_id(1);
    if (tx >= tw || ty >= th)
        return;
    uchar any = 0;
    const int j0 = max(ty - around, 0), j1 = min(ty + around, th - 1);
    const int i0 = max(tx - around, 0), i1 = min(tx + around, tw - 1);
    for (int j = j0; j <= j1 && !any; ++j)
        for (int i = i0; i <= i1; ++i)
            any |= flags[(size_t)j * tw + i];
    wanted[(size_t)ty * tw + tx] = any;
}

/* Bit 0 edge, bit 1 varies of pixel (x, y) (the 3 x 3 spreads).  The window's rows and
 * columns are clamped: the repeated edge adds no new value to a min or a max. */
inline uchar pixel_bit(__global const float *v, const int h, const int w, const int x,
                       const int y, const float spread)
{
    const int xs[3] = {max(x - 1, 0), x, min(x + 1, w - 1)};
    const int ys[3] = {max(y - 1, 0), y, min(y + 1, h - 1)};
    float2 lo = (float2)(INFINITY), hi = (float2)(-INFINITY);
    for (int j = 0; j < 3; ++j)
        for (int i = 0; i < 3; ++i) {
            const float2 d = vload2((size_t)ys[j] * w + xs[i], v);
            lo = fmin(lo, d);
            hi = fmax(hi, d);
        }
    const float2 s = hi - lo;
    const uchar edge = (s.x > spread) || (s.y > spread);
    const uchar varies = (s.x > 0.0f) || (s.y > 0.0f);
    return edge | (uchar)(varies << 1);
}

/* One work-item per `run` consecutive pixels of a row (run = 1 on a GPU; more on a CPU,
 * where a work-item's fixed cost, not its pixels, was most of a frame's time): their bits,
 * 0 outside the wanted tiles (nothing reads them there: zeros, not a previous call's). */
__kernel void pixel_bits(__global const float *v, const int h, const int w, const int tile,
                         const int tw, const int run, __global const uchar *wanted,
                         const float spread, __global uchar *bits)
{
    const int x0 = get_global_id(0) * run, y = get_global_id(1);
    if (x0 >= w || y >= h)
        return;
    const int x1 = min(x0 + run, w);
    __global const uchar *tiles = wanted + (size_t)(y / tile) * tw;
    for (int x = x0; x < x1; ++x)
        bits[(size_t)y * w + x] = tiles[x / tile] ? pixel_bit(v, h, w, x, y, spread) : 0;
}

/* One work-item per column x and segment of `seg` rows: gap[y, x] = |y - y'| for the nearest
 * edge pixel (x, y') of the column, bound + 1 when none lies within bound.  A segment scans
 * `bound` rows beyond each of its ends (so segments are independent: many work-items for a
 * GPU, short scans), down then up. */
__kernel void edge_gaps(__global const uchar *bits, __global const uchar *wanted, const int h,
                        const int w, const int tile, const int tw, const int seg,
                        const int bound, __global int *gap)
{
    const int x = get_global_id(0), s = get_global_id(1);
    const int y0 = s * seg;
    if (x >= w || y0 >= h)
        return;
    const int y1 = min(y0 + seg, h); /* rows [y0, y1) */
    /* only the columns within bound of a flagged pixel are read (region): a segment
     * outside the wanted tiles is skipped */
    uchar any = 0;
    for (int ty = y0 / tile; ty <= (y1 - 1) / tile; ++ty)
        any |= wanted[(size_t)ty * tw + x / tile];
    if (!any)
        return;
    const int none = bound + 1;
    int last = -1; /* nearest edge row at or above */
    for (int y = max(y0 - bound, 0); y < y1; ++y) {
        if (bits[(size_t)y * w + x] & 1)
            last = y;
        if (y >= y0)
            gap[(size_t)y * w + x] = (last >= 0 && y - last <= bound) ? y - last : none;
    }
    int next = -1; /* nearest edge row at or below */
    for (int y = min(y1 - 1 + bound, h - 1); y >= y0; --y) {
        if (bits[(size_t)y * w + x] & 1)
            next = y;
        if (y < y1 && next >= 0 && next - y <= bound) {
            const size_t i = (size_t)y * w + x;
            gap[i] = min(gap[i], next - y);
        }
    }
}

/* D at (qx, qy), bilinear, the image's edges repeated. */
inline float2 bilinear(__global const float *v, const int h, const int w, float qx, float qy)
{
    /* clamp first: beyond one pixel outside, the edge value is read anyway, and the float to
     * int conversion stays in range */
    qx = clamp(qx, -1.0f, (float)w);
    qy = clamp(qy, -1.0f, (float)h);
    const float fx0 = floor(qx), fy0 = floor(qy);
    const float fx = qx - fx0, fy = qy - fy0;
    const int x0 = (int)fx0, y0 = (int)fy0;
    const int xa = clamp(x0, 0, w - 1), xb = clamp(x0 + 1, 0, w - 1);
    const int ya = clamp(y0, 0, h - 1), yb = clamp(y0 + 1, 0, h - 1);
    const float2 a = vload2((size_t)ya * w + xa, v), b = vload2((size_t)ya * w + xb, v);
    const float2 c = vload2((size_t)yb * w + xa, v), d = vload2((size_t)yb * w + xb, v);
    const float2 top = a + (b - a) * fx, bottom = c + (d - c) * fx;
    return top + (bottom - top) * fy;
}

/* |t| * max(|D(p - D(p) t) - D(p)|) over x and y (0 for t = 0). */
inline float departure(__global const float *v, const int h, const int w, const int x,
                       const int y, const float2 own, const float t, const float abs_t)
{
    if (t == 0.0f)
        return 0.0f;
    /* numpy: xs - own * float32(t), each product rounded (contraction off) */
    const float qx = (float)x - own.x * t, qy = (float)y - own.y * t;
    const float2 diff = fabs(bilinear(v, h, w, qx, qy) - own);
    return abs_t * fmax(diff.x, diff.y);
}

/* (near | warped) at pixel (x, y) of a flagged tile. */
inline uchar region_at(__global const float *v, __global const uchar *bits,
                       __global const int *gap, const int h, const int w, const int x,
                       const int y, const int bound, const long k2, const float t0,
                       const float t1, const float abs_t0, const float abs_t1,
                       const float spread)
{
    /* near: the columns nearest first, so the scan stops at the first edge within reach */
    __global const int *row = gap + (size_t)y * w;
    for (int dc = 0; dc <= bound; ++dc) {
        const long across = (long)dc * dc;
        const int xl = x - dc, xr = x + dc;
        if (xl < 0 && xr >= w)
            break;
        if (xl >= 0 && across + (long)row[xl] * row[xl] <= k2)
            return 1;
        if (xr < w && across + (long)row[xr] * row[xr] <= k2)
            return 1;
    }
    const size_t p = (size_t)y * w + x;
    if (!(bits[p] & 2))
        return 0;
    const float2 own = vload2(p, v);
    const float dep = fmax(departure(v, h, w, x, y, own, t0, abs_t0),
                           departure(v, h, w, x, y, own, t1, abs_t1));
    return dep > spread;
}

/* One work-item per `run` consecutive pixels of a row (as pixel_bits):
 * out = (near | warped) & flagged tile. */
__kernel void region(__global const float *v, __global const uchar *bits,
                     __global const int *gap, __global const uchar *flags, const int h,
                     const int w, const int tile, const int tw, const int run, const int bound,
                     const long k2, const float t0, const float t1, const float abs_t0,
                     const float abs_t1, const float spread, __global uchar *out)
{
    const int x0 = get_global_id(0) * run, y = get_global_id(1);
    if (x0 >= w || y >= h)
        return;
    const int x1 = min(x0 + run, w);
    __global const uchar *tiles = flags + (size_t)(y / tile) * tw;
    for (int x = x0; x < x1; ++x)
        out[(size_t)y * w + x] = tiles[x / tile] ? region_at(v, bits, gap, h, w, x, y, bound,
                                                             k2, t0, t1, abs_t0, abs_t1,
                                                             spread)
                                                 : 0;
}
