/* Continuous surfaces of a float depth map: the joins and connected components of
 * clblur.layering.depth_components on the device (clblur/opencl/labels.py is the host side;
 * clblur/layering.py _inverse_depth, _continuous and _components are the specification).
 *
 * Conventions
 * - depth: h x w DEPTH_T (float or double), row-major; n = h * w pixels, flat index
 *   p = row * w + col.  Inverse depth w = 1.0 / (double)z (+inf gives 0, the sky), in double
 *   with contraction off: every value and comparison is numpy's float64 one, bit for bit.
 * - Build options: DEPTH_T, LABELS_TILE (side of the square tiles of labels_tiles and
 *   labels_seams), LABELS_WG (work-items of the 1-D groups, a multiple of 32).
 * - Five kernels before the host's read, one after, the buffers staying on the device:
 *   labels_tiles   per pixel the join bits to its 4 neighbours (edges; from the inverse
 *                  depths of the tile and a HALO px margin, each computed once into local
 *                  memory) and, per tile of LABELS_TILE^2 pixels, union-find in local
 *                  memory: parent = the tile-local root (the smallest flat index of the
 *                  pixel's component within the tile);
 *   labels_seams   the joins across tile seams, merged by lock-free union-find on the
 *                  global parent array (atomic_min links the larger root under the smaller),
 *                  so a root ends as the smallest flat index = the first pixel in raster
 *                  order of its component;
 *   labels_roots   parent[p] = root (path compression), and a bit per root in `words`
 *                  (32 pixels a word, raster order);
 *   labels_scan    one group: the exclusive prefix sum of the words' popcounts (offset),
 *                  counters[0] = the number of components; zeroes counters[1..3];
 *   labels_stats   comp[p] = the root's rank among the roots (offset + popcount below it):
 *                  components numbered 0..n-1 in raster order of their first pixel, as
 *                  cv2's and scipy's labelling number them.  Also the compact data the host
 *                  needs: each pair of 4-neighbours in different components (`records`,
 *                  3 ints: code = 2 p + (0 right | 1 down), x = comp[p], y = comp of the
 *                  neighbour), the runs of equal comp in each group's LABELS_WG pixels
 *                  (`runs`, 6 ints: comp, pixels, non-sliver pixels, 0, then the sum of the
 *                  finite inverse depths as the two halves of a double: the host's per
 *                  component sums), and the count of invalid pixels (counters[3]);
 *   labels_map     labels[p] = table[comp[p]] (the host's component -> layer table).
 * - Record lists are appended through atomic counters (counters[1]: runs, counters[2]: edges)
 *   in no particular order; the host sorts them where the order matters and allows for the
 *   rounding of sums taken in another order (labels.py).
 * - Global sizes may be padded past the array: extra work-items take part in the barriers
 *   and write nothing.
 */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#define J_RIGHT 1
#define J_DOWN 2
#define J_LEFT 4
#define J_UP 8
#define F_THIN 16 /* cut from both neighbours along a row or a column: a sliver pixel */
#define F_BAD 32  /* NaN or <= 0: the host raises _inverse_depth's error */

#define TILE_PX (LABELS_TILE * LABELS_TILE)

/* 1 / z of pixel `idx` in double (+inf -> 0). */
inline double inv_depth(__global const DEPTH_T *depth, const long idx)
{
    return 1.0 / (double)depth[idx];
}

/* The joins read the inverse depth from a tile of local memory with a HALO px margin: a join
 * (i, i + 1) reads w[i - 3 .. i + 4] (the steps two and three beyond either neighbour). */
#define HALO 4
#define SIDE (LABELS_TILE + 2 * HALO)

/* d[k] = w[k + 1] - w[k] along a line of the local tile: line position k at lw[at + k * stride]
 * (`at` may index before the tile: only positions within the margin are read). */
inline double line_step(__local const double *lw, const int at, const int stride, const int k)
{
    return lw[at + (k + 1) * stride] - lw[at + k * stride];
}

/* Whether d[i + offset] predicts the jump d within tol (False beyond the line's n - 1 steps):
 * _continuous's `predicts`. */
inline bool predicts(__local const double *lw, const int at, const int stride, const int n,
                     const int i, const int offset, const double d, const double tol)
{
    const int j = i + offset;
    if (j < 0 || j >= n - 1)
        return false;
    return fabs(d - line_step(lw, at, stride, j)) <= tol;
}

/* Whether pixels i and i + 1 of a line of n pixels lie on one surface: _continuous, the same
 * float64 operations in the same order (a jump within DEPTH_TAU * min(w) of 0, or of both of
 * the two steps beyond either neighbour, skipping the adjacent one; only sky continues sky). */
inline bool joined(__local const double *lw, const int at, const int stride, const int n,
                   const int i, const double tau)
{
    const double a = lw[at + i * stride];
    const double b = lw[at + (i + 1) * stride];
    const double d = b - a;
    const double tol = tau * (b < a ? b : a); /* np.minimum: no NaN can reach here unflagged */
    bool ok = fabs(d) <= tol;
    if (!ok && n >= 5)
        ok = (predicts(lw, at, stride, n, i, -2, d, tol) &&
              predicts(lw, at, stride, n, i, -3, d, tol)) ||
             (predicts(lw, at, stride, n, i, 2, d, tol) &&
              predicts(lw, at, stride, n, i, 3, d, tol));
    if (a == 0.0 || b == 0.0)
        ok = a == 0.0 && b == 0.0;
    return ok;
}

/* Find and union on a parent array where parent[x] <= x (roots point to themselves), for
 * local (within a tile) and global (across seams) memory alike: OpenCL C 1.2 has no generic
 * address space, so one macro writes both.
 *
 * Find: the root of x.  Union of the sets of a and b, lock-free (Playne and Hawick, "A new
 * algorithm for parallel connected-component labelling on GPUs", IEEE TPDS 2018): the larger
 * root is linked under the smaller with atomic_min; if it was no longer a root (another
 * work-item linked it), the min still left it pointing at a member of the merged set, and the
 * loop merges on from its parent.  Parents only decrease, so it terminates. */
#define UNION_FIND(space, find, unite)                                                     \
    inline int find(space volatile int *parent, int x)                                    \
    {                                                                                     \
        int up = parent[x];                                                               \
        while (up != x) {                                                                 \
            x = up;                                                                       \
            up = parent[x];                                                               \
        }                                                                                 \
        return x;                                                                         \
    }                                                                                     \
    inline void unite(space volatile int *parent, int a, int b)                           \
    {                                                                                     \
        for (;;) {                                                                        \
            a = find(parent, a);                                                          \
            b = find(parent, b);                                                          \
            if (a == b)                                                                   \
                return;                                                                   \
            if (a > b) {                                                                  \
                const int t = a;                                                          \
                a = b;                                                                    \
                b = t;                                                                    \
            }                                                                             \
            const int old = atomic_min(&parent[b], a);                                    \
            if (old == b)                                                                 \
                return;                                                                   \
            b = old;                                                                      \
        }                                                                                 \
    }
UNION_FIND(__local, local_find, local_union)
UNION_FIND(__global, global_find, global_union)

/* 2-D launch (x: column, y: row), local size LABELS_TILE x LABELS_TILE.  Per pixel the join
 * bits (each pixel computes the joins to all four neighbours itself: the same operations give
 * the same bits as its neighbour's, and nothing waits on another tile), then union-find of the
 * tile in local memory.  A tile's raster order is the image's, so its local roots are the
 * smallest flat indices. */
__kernel void labels_tiles(__global const DEPTH_T *depth, const int h, const int w,
                           const double tau, __global uchar *edges, __global int *parent)
{
    __local int lp[TILE_PX];
    __local double lw[SIDE * SIDE];
    const int col = get_global_id(0), row = get_global_id(1);
    const int lx = get_local_id(0), ly = get_local_id(1);
    const int li = ly * LABELS_TILE + lx;
    const int row0 = row - ly, col0 = col - lx;
    const bool inside = row < h && col < w;
    const long p = (long)row * w + col;
    /* the tile's inverse depths and their margin, each computed once (outside the image: 0,
     * never read) */
    for (int k = li; k < SIDE * SIDE; k += TILE_PX) {
        const int r = row0 - HALO + k / SIDE, c = col0 - HALO + k % SIDE;
        lw[k] = (r >= 0 && r < h && c >= 0 && c < w) ? inv_depth(depth, (long)r * w + c) : 0.0;
    }
    lp[li] = li;
    barrier(CLK_LOCAL_MEM_FENCE);
    uchar bits = 0;
    if (inside) {
        const double z = (double)depth[p];
        if (!(z > 0.0))
            bits |= F_BAD;
        /* this pixel's row and column in lw, as lines indexed by image position */
        const int me = (ly + HALO) * SIDE + lx + HALO;
        const int at_row = me - col, at_col = me - row * SIDE;
        if (col + 1 < w && joined(lw, at_row, 1, w, col, tau))
            bits |= J_RIGHT;
        if (col > 0 && joined(lw, at_row, 1, w, col - 1, tau))
            bits |= J_LEFT;
        if (row + 1 < h && joined(lw, at_col, SIDE, h, row, tau))
            bits |= J_DOWN;
        if (row > 0 && joined(lw, at_col, SIDE, h, row - 1, tau))
            bits |= J_UP;
        /* depth_components' `thin`: cut (an edge that exists and is not joined) on both sides
         * along a row or a column */
        const bool cut_l = col > 0 && !(bits & J_LEFT), cut_r = col + 1 < w && !(bits & J_RIGHT);
        const bool cut_u = row > 0 && !(bits & J_UP), cut_d = row + 1 < h && !(bits & J_DOWN);
        if ((cut_l && cut_r) || (cut_u && cut_d))
            bits |= F_THIN;
        edges[p] = bits;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (inside) {
        if ((bits & J_LEFT) && lx > 0)
            local_union(lp, li, li - 1);
        if ((bits & J_UP) && ly > 0)
            local_union(lp, li, li - LABELS_TILE);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (inside) {
        const int r = local_find(lp, li);
        parent[p] = (row0 + r / LABELS_TILE) * w + col0 + r % LABELS_TILE;
    }
}

/* 2-D launch as labels_tiles: the joins across tile seams (a tile's first column to the left,
 * its first row upwards), merged on the global parent array. */
__kernel void labels_seams(__global const uchar *edges, const int h, const int w,
                           __global int *parent)
{
    const int col = get_global_id(0), row = get_global_id(1);
    if (row >= h || col >= w)
        return;
    const bool seam_l = col > 0 && col % LABELS_TILE == 0;
    const bool seam_u = row > 0 && row % LABELS_TILE == 0;
    if (!seam_l && !seam_u)
        return;
    const int p = row * w + col;
    const uchar bits = edges[p];
    if (seam_l && (bits & J_LEFT))
        global_union(parent, p, p - 1);
    if (seam_u && (bits & J_UP))
        global_union(parent, p, p - w);
}

/* 1-D launch over the n pixels, local size LABELS_WG: parent[p] = its root (the path
 * compressed: in this kernel roots no longer change, so writing the root is always right), and
 * the roots' bits in `words` (bit p % 32 of word p / 32; every word of the image written). */
__kernel void labels_roots(__global int *parent, const int n, const int nwords,
                           __global uint *words)
{
    __local uint bits[LABELS_WG / 32];
    const int p = get_global_id(0), lid = get_local_id(0);
    if (lid < LABELS_WG / 32)
        bits[lid] = 0u;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (p < n) {
        __global volatile int *vp = parent;
        const int r = global_find(vp, p);
        int x = p;
        while (x != r) {
            const int up = vp[x];
            vp[x] = r;
            x = up;
        }
        if (r == p)
            atomic_or(&bits[lid / 32], 1u << (lid % 32));
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    const int word = get_group_id(0) * (LABELS_WG / 32) + lid;
    if (lid < LABELS_WG / 32 && word < nwords)
        words[word] = bits[lid];
}

/* One group of LABELS_WG work-items: offset[k] = the roots in words before k (exclusive prefix
 * sum of popcounts, each work-item a contiguous chunk of words); counters[0] = all roots, the
 * record counters zeroed for labels_stats. */
__kernel void labels_scan(__global const uint *words, const int nwords, __global int *offset,
                          __global int *counters)
{
    __local int sums[LABELS_WG];
    const int lid = get_local_id(0);
    const int chunk = (nwords + LABELS_WG - 1) / LABELS_WG;
    const int start = min(lid * chunk, nwords), end = min(start + chunk, nwords);
    int own = 0;
    for (int k = start; k < end; ++k)
        own += popcount(words[k]);
    sums[lid] = own;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int o = 1; o < LABELS_WG; o <<= 1) { /* Hillis-Steele inclusive scan */
        const int add = lid >= o ? sums[lid - o] : 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        sums[lid] += add;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    int at = sums[lid] - own;
    for (int k = start; k < end; ++k) {
        offset[k] = at;
        at += popcount(words[k]);
    }
    if (lid == LABELS_WG - 1) {
        counters[0] = sums[lid];
        counters[1] = 0;
        counters[2] = 0;
        counters[3] = 0;
    }
}

/* The component number of pixel q: its root's rank among the roots in raster order. */
inline int component(__global const int *parent, __global const uint *words,
                     __global const int *offset, const int q)
{
    const int r = parent[q];
    const uint below = (1u << (r & 31)) - 1u;
    return offset[r >> 5] + popcount(words[r >> 5] & below);
}

/* 1-D launch over the n pixels, local size LABELS_WG (module Conventions).  A run is
 * consecutive pixels of one component within a group; the sums of a component's runs, added
 * on the host, round differently from numpy's raster-order bincount, which the host allows
 * for (labels.py). */
__kernel void labels_stats(__global const DEPTH_T *depth, __global const uchar *edges,
                           __global const int *parent, __global const uint *words,
                           __global const int *offset, const int h, const int w,
                           const int capacity_runs, const int capacity_edges,
                           __global int *comp, __global int *counters, __global int *runs,
                           __global int *records)
{
    __local int lc[LABELS_WG];
    __local double ls[LABELS_WG];
    __local int li[LABELS_WG];
    /* records are counted in the group first, then reserved with one global atomic each
     * (one counter for every pair of a long boundary would serialise on a GPU) */
    __local int group_records, group_runs, base_records, base_runs;
    const int n = h * w;
    const int p = get_global_id(0), lid = get_local_id(0);
    const bool inside = p < n;
    if (lid == 0) {
        group_records = 0;
        group_runs = 0;
    }
    int c = -1, cr = -1, cd = -1, slot_r = -1, slot_d = -1, slot_run = -1;
    double wf = 0.0;
    int inner = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (inside) {
        c = component(parent, words, offset, p);
        comp[p] = c;
        const uchar bits = edges[p];
        if (bits & F_BAD)
            atomic_inc(&counters[3]);
        inner = (bits & F_THIN) ? 0 : 1;
        const double iw = inv_depth(depth, p);
        wf = isfinite(iw) ? iw : 0.0; /* depth_components' wf */
        const int row = p / w, col = p - row * w;
        if (col + 1 < w) {
            cr = component(parent, words, offset, p + 1);
            if (cr != c)
                slot_r = atomic_inc(&group_records);
        }
        if (row + 1 < h) {
            cd = component(parent, words, offset, p + w);
            if (cd != c)
                slot_d = atomic_inc(&group_records);
        }
    }
    lc[lid] = c;
    ls[lid] = wf;
    li[lid] = inner;
    barrier(CLK_LOCAL_MEM_FENCE);
    /* a run's first pixel walks it (runs end within the group: at most LABELS_WG steps, and
     * the walks of a group together read each pixel once) */
    double sum = 0.0;
    int pixels = 0, inners = 0;
    if (inside && (lid == 0 || lc[lid - 1] != c)) {
        for (int j = lid; j < LABELS_WG && lc[j] == c; ++j) {
            sum += ls[j];
            inners += li[j];
            ++pixels;
        }
        slot_run = atomic_inc(&group_runs);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) {
        base_records = atomic_add(&counters[2], group_records);
        base_runs = atomic_add(&counters[1], group_runs);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (slot_r >= 0 && base_records + slot_r < capacity_edges) {
        const size_t at = 3 * (size_t)(base_records + slot_r);
        records[at] = 2 * p;
        records[at + 1] = c;
        records[at + 2] = cr;
    }
    if (slot_d >= 0 && base_records + slot_d < capacity_edges) {
        const size_t at = 3 * (size_t)(base_records + slot_d);
        records[at] = 2 * p + 1;
        records[at + 1] = c;
        records[at + 2] = cd;
    }
    if (slot_run >= 0 && base_runs + slot_run < capacity_runs) {
        const size_t at = 6 * (size_t)(base_runs + slot_run);
        const int2 halves = as_int2(sum);
        runs[at] = c;
        runs[at + 1] = pixels;
        runs[at + 2] = inners;
        runs[at + 3] = 0;
        runs[at + 4] = halves.x;
        runs[at + 5] = halves.y;
    }
}

/* 1-D launch over the n pixels: the layer of each pixel from the host's table. */
__kernel void labels_map(__global const int *comp, __global const int *table, const int n,
                         __global int *labels)
{
    const int p = get_global_id(0);
    if (p < n)
        labels[p] = table[comp[p]];
}
