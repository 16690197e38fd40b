/* Exact Euclidean distance transform with nearest feature pixels (clblur/opencl/nearest.py is
 * the host side; scipy.ndimage.distance_transform_edt is the specification).
 *
 * Conventions
 * - mask: h x w uchar, row-major; a pixel is a *feature* where (mask != 0) == (feature_on != 0)
 *   (nearest_transform passes `outside` with feature_on = 0, distance passes `inside` with 1).
 * - Felzenszwalb and Huttenlocher, "Distance transforms of sampled functions" (Theory of
 *   Computing 8, 2012), separably in two passes:
 *   nearest_columns, one work-item per column: the nearest feature row in the column (two
 *   linear scans; ties: the upper one), -1 where the column holds no feature;
 *   nearest_rows, one work-item per row: the lower envelope of the parabolas
 *   (x - x')^2 + g(x')^2 over the row's columns x' that hold a feature, g = |row - frow|.
 * - Everything is integer: the envelope is kept in the form of Meijster, Roerdink and
 *   Hesselink ("A general algorithm for computing distance transforms in linear time", 2000):
 *   per envelope entry its column and the first integer x where it is the minimum, found by
 *   an exact floor division.  Only integer x are ever queried, so the squared distances are
 *   exact (no floating point, hence no FP_CONTRACT question).  Products are formed in long:
 *   the numerator of an intersection reaches 2 * 32766^2 for a 32767 px side.
 * - Outputs: d2, the squared distance (int), and with want_index != 0 index, the flat index
 *   frow * w + col of a nearest feature pixel (ties: the leftmost envelope column).
 * - Global sizes may be padded past w (columns) or h (rows): extra work-items return.
 */

/* One work-item per column c: frow[r, c] = the row of the nearest feature pixel of column c to
 * row r (the upper one of two at equal distance), or -1 when the column has none (then every
 * row of it is -1: its parabola is absent from every row's envelope). */
__kernel void nearest_columns(__global const uchar *mask, const int feature_on, const int h,
                              const int w, __global int *frow)
{
    const int c = get_global_id(0);
    if (c >= w)
        return;
    const uchar on = feature_on != 0;
    /* downwards: the nearest feature at or above each row, kept in frow for the way back */
    int above = -1;
    for (int r = 0; r < h; ++r) {
        const size_t i = (size_t)r * w + c;
        if ((mask[i] != 0) == on)
            above = r;
        frow[i] = above;
    }
    /* upwards: the nearest feature at or below; the one above wins a tie (r - above ==
     * below - r), as it must be strictly farther to lose */
    int below = -1;
    for (int r = h - 1; r >= 0; --r) {
        const size_t i = (size_t)r * w + c;
        const int up = frow[i];
        if (up == r)
            below = r; /* the pixel itself is a feature */
        if (below >= 0 && (up < 0 || below - r < r - up))
            frow[i] = below;
    }
}

/* g(x')^2 of column x' of the current row: its nearest feature row fr is never -1 here */
inline long column_cost(const int fr, const int r)
{
    const long g = (long)(fr - r);
    return g * g;
}

/* One work-item per row r: the lower envelope of the row's parabolas, then d2 (and index).
 * site[r, k] is the column of the k-th envelope entry, start[r, k] the first integer x where
 * that entry is the minimum (scratch, h x w each: a row's envelope holds at most w entries). */
__kernel void nearest_rows(__global const int *frow, const int h, const int w,
                           __global int *site, __global int *start,
                           __global int *d2, __global int *index, const int want_index)
{
    const int r = get_global_id(0);
    if (r >= h)
        return;
    const size_t row = (size_t)r * w;
    __global const int *fr = frow + row;
    __global int *s = site + row;
    __global int *t = start + row;
    int q = -1; /* top of the envelope stack */
    for (int u = 0; u < w; ++u) {
        const int fu_row = fr[u];
        if (fu_row < 0)
            continue; /* a column without a feature: no parabola */
        const long fu = column_cost(fu_row, r);
        /* pop the entries that u's parabola beats strictly at their first x: u lies to their
         * right, so it then beats them on all of their range (the difference is linear in x
         * with a positive slope); equal costs keep the left column */
        while (q >= 0) {
            const long tq = t[q], sq = s[q];
            const long before = (tq - sq) * (tq - sq) + column_cost(fr[sq], r);
            const long after = (tq - u) * (tq - u) + fu;
            if (before > after)
                --q;
            else
                break;
        }
        if (q < 0) {
            q = 0;
            s[0] = u;
            t[0] = 0;
        } else {
            /* u beats column sq strictly at x iff 2 x (u - sq) > num: from x = floor(num /
             * den) + 1.  num >= 2 t[q] (u - sq) >= 0 here (u did not beat sq at t[q]), so
             * integer division is the floor */
            const long sq = s[q];
            const long num = (long)u * u - sq * sq + fu - column_cost(fr[sq], r);
            const long first = num / (2 * ((long)u - sq)) + 1;
            if (first < w) {
                ++q;
                s[q] = u;
                t[q] = (int)first;
            }
        }
    }
    /* right to left along the envelope: each x reads the entry whose range holds it.  q < 0
     * only if no column holds a feature (the host refuses a mask without any) */
    for (int x = w - 1; x >= 0; --x) {
        if (q < 0) {
            d2[row + x] = -1;
            if (want_index)
                index[row + x] = -1;
            continue;
        }
        const int sq = s[q];
        const int fq = fr[sq];
        const long dx = (long)(x - sq);
        d2[row + x] = (int)(dx * dx + column_cost(fq, r));
        if (want_index)
            index[row + x] = fq * w + sq;
        if (x == t[q])
            --q;
    }
}
