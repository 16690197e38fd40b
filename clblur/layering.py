"""Ordering signals to layers: which surface each pixel belongs to, front to back.

The first step of layered exposure (``clblur.layered_exposure``, whose Conventions state the
model).  A float depth (a distance, ``> 0``; ``+inf`` is the sky) is cut into continuous
surfaces at depth discontinuities between neighbouring pixels (scale-invariant, in inverse
depth); integer layer IDs are taken as given; speed (faster = nearer) is cut where its sorted
values jump by more than ``GAP_FRACTION`` of their range.  At most ``MAX_LAYERS`` layers.
"""

from __future__ import annotations

import math

import numpy as np

from clblur.errors import InputError

__all__ = ["DEPTH_TAU", "GAP_FRACTION", "MAX_LAYERS", "NAMED_ORDERS", "departure_order",
           "depth_components", "layer_labels", "layer_of_components", "median_keys",
           "named_order", "order_components", "rank_components", "sliver_targets", "speed_order"]

# the orderings computed from the motion itself (``clblur.blur``'s ``depth="speed"`` etc.)
NAMED_ORDERS = ("speed", "departure")

MAX_LAYERS = 4  # the OpenCL kernels hold LAYERED_MAXK = 8 (clblur.opencl.constants)
GAP_FRACTION = 0.05  # speed ordering: a layer boundary is a gap of 5 % of the speed range
# Float depth: neighbours whose distances differ by more than 5 % (beyond what the slope of a
# plane predicts) lie on different surfaces.  A renderer's Z is exact, so any small value
# separates objects; 5 % keeps an object that far in front of its background apart (0.5 m in
# front of a wall 10 m away) while staying above the relative noise of a depth estimate, and
# fragments that noise does make are merged back by the layer cap, least separated first.
DEPTH_TAU = 0.05


def speed_order(v: np.ndarray) -> np.ndarray:
    """The speed ordering signal: ``-|v|`` as a depth (faster = nearer)."""
    return -np.hypot(v[..., 0].astype(np.float64), v[..., 1].astype(np.float64))


def departure_order(v: np.ndarray) -> np.ndarray:
    """The departure ordering signal, a float depth: ``1 / (1 + |v - median v|)`` (px).

    What moves against the image's dominant (median) motion is nearer.  Assumption: the
    dominant motion is the background's, as when the camera pans over or tracks across a
    static scene and objects move against it (then speed orders wrongly: a tracked subject
    is slow and the background fast).  Wrong when a moving object fills most of the frame.
    A float depth (> 0, cut into continuous surfaces like any other, :func:`layer_labels`):
    motion that departs smoothly stays one surface."""
    v = np.asarray(v, np.float64)
    dominant = np.median(v.reshape(-1, 2), axis=0)
    return 1.0 / (1.0 + np.hypot(v[..., 0] - dominant[0], v[..., 1] - dominant[1]))


def named_order(name: str, v: np.ndarray | None = None) -> np.ndarray | None:
    """The ordering ``name`` (one of ``NAMED_ORDERS``, checked) computed from the vectors
    ``v``: :func:`speed_order` or :func:`departure_order`; None without ``v``."""
    if name not in NAMED_ORDERS:
        raise InputError(f"unknown depth ordering {name!r}; use an H x W array or one of "
                         f"{', '.join(map(repr, NAMED_ORDERS))}")
    if v is None:
        return None
    return speed_order(v) if name == "speed" else departure_order(v)


def layer_labels(order: np.ndarray, max_layers: int = MAX_LAYERS,
                 rule: str = "depth") -> np.ndarray:
    """Layer index per pixel (0 = nearest, int32) from an ordering signal.

    Integer maps: every distinct ID is a layer.  ``rule="speed"`` (a float ``-|v|``): the
    sorted distinct values are cut where consecutive values differ by more than
    ``GAP_FRACTION`` of their range.  Float depth (``rule="depth"``): the continuous surfaces
    of :func:`depth_components`, ordered front to back by :func:`order_components`; components
    at the same depth (key gap below ``log(1 + DEPTH_TAU)``) share a layer.  Either way at most
    ``max_layers`` layers remain: the widest gaps cut, the least separated neighbours in the
    order merge.
    """
    if np.issubdtype(order.dtype, np.integer):
        u, inverse = np.unique(order, return_inverse=True)
        return _cut(np.ones(max(u.size - 1, 0)), np.ones(max(u.size - 1, 0), bool),
                    max_layers)[inverse.reshape(order.shape)]
    if rule == "speed":
        u, inverse = np.unique(order, return_inverse=True)
        vals = u.astype(np.float64)
        gaps = np.diff(vals)
        cut = gaps > GAP_FRACTION * (vals[-1] - vals[0]) if gaps.size else gaps > 0
        return _cut(gaps, cut, max_layers)[inverse.reshape(order.shape)]
    if rule != "depth":
        raise InputError(f"unknown layering rule {rule!r}; use 'depth' or 'speed'")
    if order.ndim == 1:  # a row of pixels
        return layer_labels(order[None], max_layers, rule)[0]
    comp, n = depth_components(order)
    if n == 1:
        return np.zeros(order.shape, np.int32)
    ranked, keys = order_components(order, comp, n)
    return layer_of_components(ranked, keys, max_layers)[comp]


def _cut(gaps: np.ndarray, cut: np.ndarray, max_layers: int) -> np.ndarray:
    """Layer of each of ``gaps.size + 1`` ordered items, cut where ``cut``; at most
    ``max_layers`` layers (only the widest cut gaps are kept)."""
    if cut.sum() > max_layers - 1:
        widest = np.argsort(-np.where(cut, gaps, -np.inf), kind="stable")[:max_layers - 1]
        cut = np.zeros_like(cut)
        cut[widest] = True
    return np.concatenate([[0], np.cumsum(cut)]).astype(np.int32)


def _inverse_depth(depth: np.ndarray) -> np.ndarray:
    """``1 / z`` (0 for +inf, the sky); refuses NaN, -inf and z <= 0 with a one-line error."""
    z = np.asarray(depth, np.float64)
    if np.isnan(z).any() or (z <= 0).any():
        raise InputError("float depth must be > 0 (distance, smaller = nearer) or +inf (sky); "
                         f"got {int(np.isnan(z).sum())} NaN and {int((z <= 0).sum())} value(s) "
                         "<= 0 (pass integer layer IDs for a rank order)")
    with np.errstate(divide="ignore"):
        return 1.0 / z


def _continuous(w: np.ndarray, axis: int) -> np.ndarray:
    """Whether each pair of neighbours along ``axis`` (``w`` inverse depth) lies on one
    surface: the jump ``d`` between them is within ``DEPTH_TAU * min(w)`` of 0, or of both of
    the two steps beyond either of them, skipping the adjacent step (a plane's inverse depth is
    affine in the image, so a slanted plane's steps are predicted exactly; the adjacent step is
    skipped so that a mixed pixel between two surfaces does not predict the jump it sits in,
    and two steps are asked for so that a one- or two-pixel sliver of a middle surface, whose
    step to the far one may equal the jump by chance, does not either)."""
    m = np.moveaxis(w, axis, 0)
    n = m.shape[0]
    d = m[1:] - m[:-1]                          # jump between i and i + 1, n - 1 of them
    tol = DEPTH_TAU * np.minimum(m[1:], m[:-1])
    ok = np.abs(d) <= tol
    if n >= 5:
        # only the jumps are tested against the steps around them (a few boundary pixels,
        # not the whole array); a step beyond the array predicts nothing
        at = np.nonzero(~ok)
        i, d_at, tol_at = at[0], d[at], tol[at]

        def predicts(offset: int) -> np.ndarray:
            """Whether d[i + offset] is within tol of d[i] (False beyond the array)."""
            j = i + offset
            inside = (j >= 0) & (j < n - 1)
            out = np.zeros(i.size, bool)
            there = (j[inside],) + tuple(a[inside] for a in at[1:])
            out[inside] = np.abs(d_at[inside] - d[there]) <= tol_at[inside]
            return out
        ok[at] = (predicts(-2) & predicts(-3)) | (predicts(2) & predicts(3))
    sky = m == 0  # +inf depth: only sky continues sky
    ok = np.where(sky[1:] | sky[:-1], sky[1:] & sky[:-1], ok)
    return np.moveaxis(ok, 0, axis)


def depth_components(depth: np.ndarray) -> tuple[np.ndarray, int]:
    """Continuous surfaces of a float depth map: (H x W int labels 0..n-1, n).

    Neighbours (4-connected) belong to one surface unless the depth jumps between them
    (:func:`_continuous`, threshold ``DEPTH_TAU``, scale-invariant: depth * c gives the same
    surfaces); +inf (sky) is a surface of its own.  A sliver (a component one pixel thick
    everywhere, cut from both neighbours along a row or column, e.g. the mixed pixels between
    two surfaces) joins the nearest component it touches in front of it (and with it, where
    that is a sliver too), as ``prepare`` puts mixed pixels on the nearer layer.
    """
    w = _inverse_depth(depth)
    h, wd = w.shape
    right = _continuous(w, 1)
    down = _continuous(w, 0)
    n, comp = _components(right, down)
    if n == 1:
        return comp.astype(np.int32), 1
    # slivers: every pixel of the component is cut from both of its neighbours along a row or
    # a column (one pixel thick, as the mixed pixels of an antialiased Z are)
    cut_l, cut_r, cut_u, cut_d = (np.zeros((h, wd), bool) for _ in range(4))
    cut_r[:, :-1], cut_l[:, 1:] = ~right, ~right
    cut_d[:-1, :], cut_u[1:, :] = ~down, ~down
    thin = (cut_l & cut_r) | (cut_u & cut_d)
    interior = np.bincount(comp[~thin], minlength=n) > 0
    if not interior.all():
        # mean inverse depth of each component, and of its nearest (largest w) neighbour
        wf = np.where(np.isfinite(w), w, 0.0)
        mean_w = np.bincount(comp.ravel(), wf.ravel(), n) / np.bincount(comp.ravel(), None, n)
        neighbours = [(x, y) for a, b in ((comp[:, :-1][~right], comp[:, 1:][~right]),
                                          (comp[:-1, :][~down], comp[1:, :][~down]))
                      for x, y in ((a, b), (b, a))]  # x's neighbour y
        target = sliver_targets(interior, mean_w, neighbours)
        # renumber the surviving components 0..n-1 in the order of their ids (what
        # np.unique(target[comp], return_inverse=True) gives, without sorting every pixel:
        # every component has a pixel, so the ids in use are target's values)
        used = np.zeros(n, bool)
        used[target] = True
        comp = (np.cumsum(used) - 1)[target][comp]
        n = int(used.sum())
    return comp.astype(np.int32), n


def sliver_targets(interior: np.ndarray, mean_w: np.ndarray,
                   neighbours: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The component each component merges into (itself if it stays), the sliver rule of
    :func:`depth_components`: a component without interior pixels (``~interior``) joins its
    nearest neighbour in front of it (the largest mean inverse depth ``mean_w`` above its
    own), and a sliver in front of a sliver follows it (the targets are strictly nearer, so
    the chain ends).  ``neighbours``: (x, y) arrays of components x next to components y, in
    the order the first such pair is taken (the host's raster scans, or a device's records
    of them)."""
    n = interior.size
    target = np.arange(n)
    best = np.full(n, -1.0)
    for x, y in neighbours:
        sel = ~interior[x] & (mean_w[y] > mean_w[x])
        np.maximum.at(best, x[sel], mean_w[y[sel]])
    for x, y in neighbours:
        sel = (best[x] >= 0) & (mean_w[y] == best[x])
        target[x[sel]] = y[sel]
    while True:
        nxt = target[target]
        if np.array_equal(nxt, target):
            return target
        target = nxt


def _components(right: np.ndarray, down: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the pixel grid whose 4-neighbours are joined where ``right``
    (H x W-1) and ``down`` (H-1 x W) say: (n, H x W int64 labels numbered in raster order
    of their first pixel, as ``scipy.sparse.csgraph.connected_components`` numbers them).

    Why: a grid twice as fine, pixels at even positions and the joins between them in
    between, labelled by OpenCV's sequential two-pass labelling (Wu et al., "Optimizing
    two-pass connected-component labeling algorithms", 2009; ``cv2.CCL_SAUF``), which also
    numbers components by their first pixel in raster order: an order of magnitude faster
    than building the sparse graph."""
    import cv2

    h, wd = right.shape[0], down.shape[1]
    grid = np.zeros((2 * h - 1, 2 * wd - 1), np.uint8)
    grid[::2, ::2] = 1
    grid[::2, 1::2] = right
    grid[1::2, ::2] = down
    n, lab = cv2.connectedComponentsWithAlgorithm(grid, 4, cv2.CV_32S, cv2.CCL_SAUF)
    return n - 1, lab[::2, ::2].astype(np.int64) - 1  # 0 is the (absent) background


def order_components(depth: np.ndarray, comp: np.ndarray, n: int) -> tuple[list[int], list[float]]:
    """Front-to-back order of the components of :func:`depth_components` and their keys.

    Where two components touch, the one whose pixels along the shared boundary are nearer
    (median log-depth difference over the boundary's neighbour pairs) is in front.  These
    pairwise constraints are sorted topologically; among the components free to go next the
    one with the smallest key (median log-depth of its boundary pixels, where it touches
    others: a ground plane is ordered by where it meets what stands on it, not by its far
    end) goes first, and a cycle is broken the same way.
    """

    with np.errstate(divide="ignore"):
        logz = np.log(np.asarray(depth, np.float64))  # +inf stays +inf
    pairs: dict[tuple[int, int], list[np.ndarray]] = {}
    border = np.zeros(comp.shape, bool)
    for axis in (0, 1):
        a = np.moveaxis(comp, axis, 0)
        la = np.moveaxis(logz, axis, 0)
        ca, cb = a[:-1], a[1:]
        diff = ca != cb
        if not diff.any():
            continue
        b = np.moveaxis(border, axis, 0)
        b[:-1] |= diff
        b[1:] |= diff
        x, y = ca[diff], cb[diff]
        with np.errstate(invalid="ignore"):
            dz = la[1:][diff] - la[:-1][diff]  # > 0: x nearer than y
        dz = np.where(np.isnan(dz), 0.0, dz)  # sky next to sky
        lo, hi = np.minimum(x, y), np.maximum(x, y)
        sign = np.where(x == lo, dz, -dz)  # > 0: lo nearer than hi
        key = lo.astype(np.int64) * n + hi
        srt = np.argsort(key, kind="stable")
        key, sign = key[srt], sign[srt]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        for s, e in zip(starts, np.r_[starts[1:], key.size], strict=True):
            pairs.setdefault((int(key[s] // n), int(key[s] % n)), []).append(sign[s:e])
    # median log-depth of each component's boundary pixels (of all its pixels if it has none)
    at = border if np.bincount(comp[border], minlength=n).all() else \
        border | ~np.isin(comp, np.unique(comp[border]))
    keys = median_keys(comp[at], logz[at], n)
    before = []
    for (lo, hi), parts in pairs.items():
        med = float(np.median(np.concatenate(parts)))
        if med != 0.0:
            before.append((lo, hi) if med > 0 else (hi, lo))
    return rank_components(keys, before), keys


def median_keys(c_at: np.ndarray, z_at: np.ndarray, n: int) -> list[float]:
    """Each of the ``n`` components' key for :func:`order_components`: the median (numpy's:
    the middle value, or the mean of the middle two) of the log-depths ``z_at`` of its
    pixels ``c_at`` (every component present at least once)."""
    srt = np.lexsort((z_at, c_at))
    c_at, z_at = c_at[srt], z_at[srt]
    start = np.searchsorted(c_at, np.arange(n))
    end = np.searchsorted(c_at, np.arange(n), side="right")
    lo_i, hi_i = (start + end - 1) // 2, (start + end) // 2
    with np.errstate(invalid="ignore"):
        return [float(x) for x in np.where(z_at[lo_i] == z_at[hi_i], z_at[lo_i],
                                           0.5 * (z_at[lo_i] + z_at[hi_i]))]


def rank_components(keys: list[float], before: list[tuple[int, int]]) -> list[int]:
    """The front-to-back order of :func:`order_components` from its keys and its pairwise
    constraints ``before`` ((front, back) component pairs, each unordered pair at most once):
    sorted topologically, the smallest key first among the components free to go, a cycle
    broken by the nearest remaining component."""
    import heapq

    n = len(keys)
    after: list[set[int]] = [set() for _ in range(n)]
    indeg = np.zeros(n, np.int64)
    for front, back in before:
        after[front].add(back)
        indeg[back] += 1
    ready = [(keys[c], c) for c in range(n) if indeg[c] == 0]
    heapq.heapify(ready)
    done = np.zeros(n, bool)
    ranked: list[int] = []
    while len(ranked) < n:
        if not ready:  # a cycle: the nearest remaining component goes first
            c = min((c for c in range(n) if not done[c]), key=lambda c: (keys[c], c))
            heapq.heappush(ready, (keys[c], c))
            indeg[c] = 0
        _, c = heapq.heappop(ready)
        if done[c]:
            continue
        done[c] = True
        ranked.append(c)
        for b in after[c]:
            indeg[b] -= 1
            if indeg[b] == 0 and not done[b]:
                heapq.heappush(ready, (keys[b], b))
    return ranked


def layer_of_components(ranked: list[int], keys: list[float], max_layers: int) -> np.ndarray:
    """The layer of each component (int32) from its rank and key (:func:`order_components`):
    cut where consecutive components in the order lie more than ``log(1 + DEPTH_TAU)`` apart
    in log-depth (scale-invariant; sky next to sky is no gap), at most ``max_layers``."""
    k = np.asarray(keys)[ranked]
    with np.errstate(invalid="ignore"):
        gaps = np.abs(np.diff(k))
    gaps = np.where(np.isnan(gaps), 0.0, gaps)
    layer_of_rank = _cut(gaps, gaps > math.log1p(DEPTH_TAU), max_layers)
    layer_of_comp = np.empty(len(keys), np.int32)
    layer_of_comp[ranked] = layer_of_rank
    return layer_of_comp
