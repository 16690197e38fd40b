"""Layered exposure: occlusion-correct motion blur, ordered by depth, layer IDs or speed.

Why: the plain gather (``clblur.reference.integrate``) integrates each output pixel along its
own vector, so a static background next to a moving object never receives the object's light
and the object's streak stops at its silhouette.  A camera records, at every instant of the
shutter, the *nearest* surface covering each pixel.  This module integrates exactly that, in
the linear domain, for scenes made of layers that each move along their own vectors.

Conventions
-----------
* Ordering signal, H x W: a float **depth** (smaller = nearer), integer **layer IDs** (smaller =
  nearer), or **speed** (``depth="speed"``: faster = nearer, the default of
  ``clblur video --layers``).  Each distinct integer ID is its own layer.  A float depth is
  a distance (``> 0``; ``+inf`` is the sky; NaN, ``-inf`` and ``<= 0`` are refused) and is
  cut into continuous surfaces at depth discontinuities between neighbouring pixels: a jump in
  inverse depth beyond ``DEPTH_TAU`` of the smaller one, after the step a slanted plane's
  slope predicts (:func:`depth_components`; scale-invariant), the surfaces ordered front to
  back by their depth where they touch (:func:`order_components`).  Speed is cut where its
  sorted values jump by more than ``GAP_FRACTION`` of their range.  At most ``MAX_LAYERS``
  layers (the least separated neighbours in the order merge).  Within a layer there is no
  ordering: a layer is one surface.
* Culling (tile-max / neighbour-max velocity, after McGuire et al., "A reconstruction filter
  for plausible motion blur", I3D 2012, and Guertin et al., "A fast and stable feature-aware
  motion blur filter", HPG 2014): the image is cut into ``TILE`` x ``TILE`` tiles; a tile needs
  the layered path only when the vectors in the tiles within reach of it (``ceil((R + 2) /
  TILE)`` tiles, ``R`` = the longest vector times ``max(a, 1 - a)``) differ by more than
  ``SPREAD_PX`` in x or y.  Elsewhere every surface that can reach a pixel moves alike, nothing
  is revealed or hidden, and the result is the plain gather, bit for bit.
* Each layer ``k`` is a premultiplied image ``P_k = (M_k L, M_k)`` (linear light ``L``, 0/1
  coverage ``M_k``) with a vector field ``D_k``: a pixel's own vector on the layer, and the
  vector of the nearest layer pixel elsewhere (a layer moves locally as one piece).  At shutter
  sample ``j`` pixel ``p`` reads each layer at ``p - D_k(p) (s_j - a)`` (bilinear, clamp to
  edge; the positions and sample counts of ``clblur.motion``, with ``N(p) = ceil(max_k
  |D_k(p)|) + 1`` by default) and composites front to back, ``E_j = sum_k T_k C_k``,
  ``T_{k+1} = T_k (1 - W_k)`` with ``(C_k, W_k)`` the sampled ``P_k``.  For a layer in rigid
  translation, sampling ``P_k`` along ``D_k`` equals splatting (scattering) the layer's pixels
  along their motion with bilinear weights, so a foreground's light lands on what lies behind
  it with the right coverage at every sample.  Light no layer covers (``T`` left over) is read
  from the image along ``p``'s own vector (the gather).
* **What is behind an object is not in the image.**  Assumption: a hidden pixel of a farther
  layer looks like the nearest visible pixel of the layers at or behind it and moves with it
  (nearest-neighbour extension, ``scipy.ndimage.distance_transform_edt``), within
  ``2 R + 2`` pixels of the visible part (nothing deeper can be revealed during the shutter).
  Pixels hidden under a nearer object join layer ``k`` only when that nearest pixel is on
  layer ``k``.
* **Mixed pixels** (within one pixel of a layer boundary) hold light of both layers.  They
  join the nearer layer with coverage ``a`` fitted to their light, ``I = a F + (1 - a) B``
  (``F`` the nearest unmixed pixel of that layer, ``B`` the reconstruction behind; least
  squares over the channels, the colour-line model of alpha matting, pulled towards 1/2
  where ``F`` and ``B`` are alike), and carry ``I - (1 - a) B`` premultiplied, so the
  composite at the anchor time is the image.
* Tiling windows (``plan.extent``) are not supported with an ordering: layered exposure needs
  the whole image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clblur.motion import PSF, Field, Uniform, sample_counts
from clblur.request import BlurPlan

__all__ = ["DEPTH_TAU", "GAP_FRACTION", "MAX_LAYERS", "SPLIT_PRIOR", "SPREAD_PX", "TILE", "Layers",
           "boundary_mask", "depth_components", "order_components", "region_mask",
           "integrate", "integrator", "layer_labels", "layered_half", "prepare",
           "speed_order", "split_coverage", "composite"]

MAX_LAYERS = 4  # the OpenCL kernels hold LAYERED_MAXK = 8 (clblur.opencl.constants)
GAP_FRACTION = 0.05  # speed ordering: a layer boundary is a gap of 5 % of the speed range
# Float depth: neighbours whose distances differ by more than 5 % (beyond what the slope of a
# plane predicts) lie on different surfaces.  A renderer's Z is exact, so any small value
# separates objects; 5 % keeps an object that far in front of its background apart (0.5 m in
# front of a wall 10 m away) while staying above the relative noise of a depth estimate, and
# fragments that noise does make are merged back by the layer cap, least separated first.
DEPTH_TAU = 0.05
SPREAD_PX = 1.0
TILE = 16
INPAINT_RADIUS = 3
MID_EXTEND_PX = 2.0
SPLIT_PRIOR = 1e-4  # (linear light)^2: below this contrast a mixed pixel stays half and half


def speed_order(v: np.ndarray) -> np.ndarray:
    """The speed ordering signal: ``-|v|`` as a depth (faster = nearer)."""
    return -np.hypot(v[..., 0].astype(np.float64), v[..., 1].astype(np.float64))


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
        raise ValueError(f"unknown layering rule {rule!r}; use 'depth' or 'speed'")
    if order.ndim == 1:  # a row of pixels
        return layer_labels(order[None], max_layers, rule)[0]
    comp, n = depth_components(order)
    if n == 1:
        return np.zeros(order.shape, np.int32)
    ranked, keys = order_components(order, comp, n)
    # separation of consecutive components in the order, in log-depth (scale-invariant);
    # sky (key inf) next to sky is no gap
    k = np.asarray(keys)[ranked]
    with np.errstate(invalid="ignore"):
        gaps = np.abs(np.diff(k))
    gaps = np.where(np.isnan(gaps), 0.0, gaps)
    layer_of_rank = _cut(gaps, gaps > math.log1p(DEPTH_TAU), max_layers)
    layer_of_comp = np.empty(n, np.int32)
    layer_of_comp[ranked] = layer_of_rank
    return layer_of_comp[comp]


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
        raise ValueError("float depth must be > 0 (distance, smaller = nearer) or +inf (sky); "
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
        step = np.full((n + 5,) + m.shape[1:], np.nan)
        step[3:n + 2] = d                       # step[j + 3] = d[j]; NaN outside
        # d[i] against d[i - 2] and d[i - 3] (before), and d[i + 2] and d[i + 3] (after)
        with np.errstate(invalid="ignore"):
            before = (np.abs(d - step[1:n]) <= tol) & (np.abs(d - step[0:n - 1]) <= tol)
            after = (np.abs(d - step[5:n + 4]) <= tol) & (np.abs(d - step[6:n + 5]) <= tol)
        ok |= before | after
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
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    w = _inverse_depth(depth)
    h, wd = w.shape
    idx = np.arange(h * wd).reshape(h, wd)
    right = _continuous(w, 1)
    down = _continuous(w, 0)
    rows = np.concatenate([idx[:, :-1][right], idx[:-1, :][down]])
    cols = np.concatenate([idx[:, 1:][right], idx[1:, :][down]])
    graph = coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(h * wd,) * 2)
    n, comp = connected_components(graph, directed=False)
    comp = comp.reshape(h, wd).astype(np.int64)
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
        target = np.arange(n)
        best = np.full(n, -1.0)
        for a, b in ((comp[:, :-1][~right], comp[:, 1:][~right]),
                     (comp[:-1, :][~down], comp[1:, :][~down])):
            for x, y in ((a, b), (b, a)):  # x's neighbour y
                sel = ~interior[x] & (mean_w[y] > mean_w[x])
                np.maximum.at(best, x[sel], mean_w[y[sel]])
        for a, b in ((comp[:, :-1][~right], comp[:, 1:][~right]),
                     (comp[:-1, :][~down], comp[1:, :][~down])):
            for x, y in ((a, b), (b, a)):
                sel = (best[x] >= 0) & (mean_w[y] == best[x])
                target[x[sel]] = y[sel]
        # a sliver in front of a sliver (the mixed pixels of a corner) follows it: targets are
        # strictly nearer, so the chain ends
        while True:
            nxt = target[target]
            if np.array_equal(nxt, target):
                break
            target = nxt
        _, comp_new = np.unique(target[comp], return_inverse=True)
        comp = comp_new.reshape(h, wd)
        n = int(comp.max()) + 1
    return comp.astype(np.int32), n


def order_components(depth: np.ndarray, comp: np.ndarray, n: int) -> tuple[list[int], list[float]]:
    """Front-to-back order of the components of :func:`depth_components` and their keys.

    Where two components touch, the one whose pixels along the shared boundary are nearer
    (median log-depth difference over the boundary's neighbour pairs) is in front.  These
    pairwise constraints are sorted topologically; among the components free to go next the
    one with the smallest key (median log-depth of its boundary pixels, where it touches
    others: a ground plane is ordered by where it meets what stands on it, not by its far
    end) goes first, and a cycle is broken the same way.
    """
    import heapq

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
    c_at, z_at = comp[at], logz[at]
    srt = np.lexsort((z_at, c_at))
    c_at, z_at = c_at[srt], z_at[srt]
    start = np.searchsorted(c_at, np.arange(n))
    end = np.searchsorted(c_at, np.arange(n), side="right")
    lo_i, hi_i = (start + end - 1) // 2, (start + end) // 2
    with np.errstate(invalid="ignore"):
        keys = [float(x) for x in np.where(z_at[lo_i] == z_at[hi_i], z_at[lo_i],
                                           0.5 * (z_at[lo_i] + z_at[hi_i]))]
    after: list[set[int]] = [set() for _ in range(n)]
    indeg = np.zeros(n, np.int64)
    for (lo, hi), parts in pairs.items():
        med = float(np.median(np.concatenate(parts)))
        if med == 0.0:
            continue
        front, back = (lo, hi) if med > 0 else (hi, lo)
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
    return ranked, keys


def reach(v: np.ndarray, anchor: float) -> float:
    """Farthest any sample of ``v`` lands from its pixel: ``max |v| * max(a, 1 - a)``."""
    if not v.size:
        return 0.0
    x, y = v[..., 0], v[..., 1]
    longest = math.sqrt(float(np.max(x * x + y * y)))  # float32 squares, rounded up below
    return longest * (1 + 1e-6) * max(anchor, 1.0 - anchor)


def boundary_mask(v: np.ndarray, anchor: float, tile: int = TILE,
                  spread: float = SPREAD_PX) -> np.ndarray:
    """Pixels whose neighbourhood moves non-uniformly: the ones that need the layered path.

    Per tile the min and max of each vector component; a tile is flagged when, over the tiles
    within ``ceil((R + 2) / tile)`` of it, max minus min exceeds ``spread`` pixels (module
    Conventions).  Returns an H x W bool mask (whole tiles).
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    h, w = v.shape[:2]
    th, tw = -(-h // tile), -(-w // tile)
    pad = ((0, th * tile - h), (0, tw * tile - w))
    tmax = np.empty((th, tw, 2), v.dtype)
    tmin = np.empty((th, tw, 2), v.dtype)
    for c in range(2):  # per component, one axis at a time: contiguous, hence fast
        comp = np.ascontiguousarray(v[..., c])
        if th * tile != h or tw * tile != w:
            comp = np.pad(comp, pad, mode="edge")
        comp = comp.reshape(th, tile, tw, tile)
        tmax[..., c] = comp.max(axis=3).max(axis=1)
        tmin[..., c] = comp.min(axis=3).min(axis=1)
    size = 2 * math.ceil((reach(v, anchor) + 2.0) / tile) + 1
    nmax = maximum_filter(tmax, size=(size, size, 1), mode="nearest")
    nmin = minimum_filter(tmin, size=(size, size, 1), mode="nearest")
    flagged = ((nmax - nmin) > spread).any(axis=2)
    return np.repeat(np.repeat(flagged, tile, axis=0), tile, axis=1)[:h, :w]


def region_mask(v: np.ndarray, anchor: float, tile: int = TILE,
                spread: float = SPREAD_PX) -> np.ndarray:
    """The pixels that take the layered path: the flagged tiles of :func:`boundary_mask`,
    narrowed to the pixels within ``R + 2`` of a motion edge (a pixel whose 3 x 3
    neighbourhood's vectors differ by more than ``spread`` in x or y).  Farther away, every
    surface that can reach a pixel moves as the pixel does, and the gather is kept."""
    from scipy.ndimage import distance_transform_edt, maximum_filter, minimum_filter

    tiles = boundary_mask(v, anchor, tile, spread)
    if not tiles.any():
        return tiles
    r = reach(v, anchor)
    margin = int(math.ceil(r)) + 4
    rows, cols = np.nonzero(tiles.any(axis=1))[0], np.nonzero(tiles.any(axis=0))[0]
    h, w = tiles.shape
    r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)
    c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)
    crop = v[r0:r1, c0:c1]
    edge = np.zeros(crop.shape[:2], bool)
    for c in range(2):
        edge |= (maximum_filter(crop[..., c], size=3, mode="nearest")
                 - minimum_filter(crop[..., c], size=3, mode="nearest")) > spread
    out = np.zeros_like(tiles)
    if edge.any():
        near = distance_transform_edt(~edge) <= r + 2.0
        out[r0:r1, c0:c1] = near & tiles[r0:r1, c0:c1]
    return out


@dataclass
class Layers:
    """The layers of a crop of the image, ready to composite (module Conventions).

    ``origin``: (row, col) of the crop in the full image; ``planes``: K x h x w x (C + 1)
    premultiplied ``(M L, M)``; ``vectors``: K x h x w x 2 float32 ``D_k``; ``flow`` and
    ``linear``: the crop of the image's own vectors and linear image (for uncovered light);
    ``region``: h x w bool, the pixels to composite; ``present``: K x h x w bool, whether
    layer ``k`` can cover the pixel at any sample (farther than its reach plus the bilinear
    footprint it reads only zeros, so skipping it changes nothing but the sample count).
    """

    origin: tuple[int, int]
    planes: np.ndarray
    vectors: np.ndarray
    flow: np.ndarray
    linear: np.ndarray
    region: np.ndarray
    present: np.ndarray


def _inpaint(lin: np.ndarray, known: np.ndarray, depth: float,
             nearest: tuple[np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None,
             needed: np.ndarray | None = None) -> np.ndarray:
    """``lin`` with the pixels outside ``known`` reconstructed from the known ones
    (Navier-Stokes inpainting, Bertalmio et al. 2001, as ``cv2.inpaint``; per channel) up to
    ``depth`` pixels from them; deeper pixels, which no sample reads, take their nearest known
    pixel (so the inpainting only walks the band that can be uncovered).  ``nearest``: the
    distance transform of ``~known`` with its indices, if already computed; ``needed``: the
    pixels any sample can read (others take their nearest known pixel too), and the
    inpainting runs only on the bounding box of the hole they leave, plus a margin."""
    import cv2
    from scipy.ndimage import distance_transform_edt

    if not known.any():
        return lin.copy()
    dist, idx = nearest if nearest is not None else \
        distance_transform_edt(~known, return_indices=True)
    deep = dist > depth + INPAINT_RADIUS + 1
    if needed is not None:
        deep |= ~needed
    base = lin[idx[0], idx[1]] if deep.any() else lin
    hole = ~known & ~deep
    out = np.array(base, copy=True)
    if not hole.any():
        return np.where(known[..., None], lin, out)
    # cv2.inpaint marches over the whole array it is given: give it only the hole's box
    # plus the radius it reads (and one pixel of border) around it.
    m = INPAINT_RADIUS + 2
    rows, cols = np.nonzero(hole.any(axis=1))[0], np.nonzero(hole.any(axis=0))[0]
    box = (slice(max(rows[0] - m, 0), rows[-1] + m + 1),
           slice(max(cols[0] - m, 0), cols[-1] + m + 1))
    hole8 = hole[box].astype(np.uint8)
    for c in range(lin.shape[2]):
        out[box + (c,)] = cv2.inpaint(np.ascontiguousarray(base[box + (c,)], np.float32),
                                      hole8, INPAINT_RADIUS, cv2.INPAINT_NS)
    return np.where(known[..., None], lin, out)


# offsets within 3 px, nearest first (ties in a fixed order)
_NEAR = sorted(((dy, dx) for dy in range(-3, 4) for dx in range(-3, 4) if dy or dx),
               key=lambda o: (o[0] * o[0] + o[1] * o[1], o))


def _nearest_pixel(inside: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a nearest ``inside`` pixel to each ``at`` pixel (row-major order of
    ``at``): looked up within 3 px, then by a distance transform for the rest (mixed pixels
    lie next to their layer, so the lookup nearly always succeeds)."""
    from scipy.ndimage import distance_transform_edt

    h, w = inside.shape
    ys, xs = np.nonzero(at)
    ry, rx = np.full(ys.size, -1), np.full(ys.size, -1)
    todo = np.ones(ys.size, bool)
    for dy, dx in _NEAR:
        y, x = ys + dy, xs + dx
        hit = todo & (y >= 0) & (y < h) & (x >= 0) & (x < w)
        hit[hit] = inside[y[hit], x[hit]]
        ry[hit], rx[hit] = y[hit], x[hit]
        todo &= ~hit
        if not todo.any():
            return ry, rx
    idx = distance_transform_edt(~inside, return_indices=True)[1]
    ry[todo], rx[todo] = idx[0][ys[todo], xs[todo]], idx[1][ys[todo], xs[todo]]
    return ry, rx


def split_coverage(light: np.ndarray, front: np.ndarray, behind: np.ndarray) -> np.ndarray:
    """Coverage of the nearer layer in mixed pixels, from their light (in [0, 1]; ``light``,
    ``front`` and ``behind`` are ... x C linear light, the result has their shape but C).

    A mixed pixel holds ``a F + (1 - a) B`` (``F``: the nearest unmixed pixel of the nearer
    layer, ``B``: what lies behind); ``a`` is the least-squares fit over the channels (the
    colour-line model of alpha matting), regularised towards 1/2 by ``SPLIT_PRIOR`` (where
    ``F`` and ``B`` are alike the light cannot tell, and half and half is kept; also where
    ``F`` is unknown, NaN)."""
    fb = front - behind
    num = np.sum((light - behind) * fb, axis=-1) + 0.5 * SPLIT_PRIOR
    den = np.sum(fb * fb, axis=-1) + SPLIT_PRIOR
    a = np.clip(num / den, 0.0, 1.0)
    return np.where(np.isfinite(a), a, 0.5)


def prepare(lin, v: np.ndarray, order: np.ndarray, anchor: float,
            region: np.ndarray, background: np.ndarray | None = None,
            split_edges: bool = True, rule: str = "depth") -> Layers | None:
    """Build the layers around ``region`` (H x W bool) from the linear image, the vectors and
    the ordering signal; ``background``: the linear clean plate, if known.  Host-side, shared
    by both backends.  ``lin``: the linear image, or a function that returns the linear image
    of a crop ``(row slice, col slice)`` (so only the crop is linearised).  None when the
    ordering gives one layer there: a single surface is what the gather integrates.
    ``rule``: how a float ``order`` becomes layers (:func:`layer_labels`)."""
    from scipy.ndimage import (
        binary_dilation,
        distance_transform_edt,
        maximum_filter,
        minimum_filter,
    )

    h, w = region.shape
    r = reach(v, anchor)
    band = 2.0 * r + 2.0
    margin = int(math.ceil(band + r)) + 3
    rows, cols = np.nonzero(region.any(axis=1))[0], np.nonzero(region.any(axis=0))[0]
    r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)
    c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)
    crop = (slice(r0, r1), slice(c0, c1))
    labels = layer_labels(order[crop], rule=rule)
    last = int(labels.max())
    if last == 0 and background is None:
        return None
    lin_c = lin(crop) if callable(lin) else lin[crop]
    v_c = v[crop].astype(np.float32)
    # Mixed pixels: a pixel next to another layer holds light of both; it is split between the
    # nearer layer around it (coverage fitted to its light, split_coverage) and what lies
    # behind (reconstructed), so the composite at the anchor time is the image itself.
    front = minimum_filter(labels, size=3, mode="nearest")
    split = (front != maximum_filter(labels, size=3, mode="nearest")) if split_edges else \
        np.zeros(labels.shape, bool)
    labels = np.where(split, front, labels)
    own = v_c  # the image's own vectors, for light no layer covers
    v_c = v_c.copy()
    pure = lin_c.copy()  # at a split pixel: the light of the nearest unmixed pixel of its layer
    for k in range(last + 1):  # a split pixel moves with the layer it joined
        core = (labels == k) & ~split
        joined = split & (labels == k)
        if core.any() and joined.any():
            ys, xs = _nearest_pixel(core, joined)
            v_c[joined] = v_c[ys, xs]
            pure[joined] = lin_c[ys, xs]
        elif joined.any():
            pure[joined] = np.nan  # no unmixed pixel: the split stays half and half
    fills: dict[int, np.ndarray] = {}
    nearest_at_or_behind: dict[int, tuple] = {}
    # Samples of region pixels land within the reach of a layer's vectors (+ the bilinear
    # footprint) of the region: the reconstruction of layer k is needed only there (plus the
    # inpainting radius, so that what is read is inpainted from a filled neighbourhood), and
    # around the mixed pixels of layer k - 1, which take it as what lies behind them.  The
    # vectors of layer k all come from pixels at or behind it.
    from_region = distance_transform_edt(~region[crop])
    pad = 2.0 + INPAINT_RADIUS + 1
    l2 = v_c[..., 0] * v_c[..., 0] + v_c[..., 1] * v_c[..., 1]
    # reach() of the vectors at or behind each layer: the largest square, rearmost first
    longest = np.maximum.accumulate(
        [float(l2[labels == k].max(initial=0.0)) for k in range(last, -1, -1)])[::-1]
    reach_at_or_behind = [math.sqrt(x) * (1 + 1e-6) * max(anchor, 1.0 - anchor)
                          for x in longest]

    def needed(k: int) -> np.ndarray:
        out = from_region <= reach_at_or_behind[k] + pad
        mixed = split & (labels == k - 1)
        if mixed.any():
            out |= (binary_dilation(mixed, iterations=INPAINT_RADIUS + 1)
                    & (from_region <= reach_at_or_behind[k - 1] + pad))
        return out

    def behind_edt(k: int) -> tuple:
        """Distance to, and index of, the nearest pixel at or behind layer ``k``."""
        if k not in nearest_at_or_behind:
            nearest_at_or_behind[k] = distance_transform_edt(labels < k, return_indices=True)
        return nearest_at_or_behind[k]

    def fill(k: int) -> np.ndarray:
        """The linear image with everything nearer than layer ``k`` reconstructed."""
        if k not in fills:
            # an intermediate layer extends MID_EXTEND_PX under what hides it, and a mixed
            # pixel lies within 2 px of what is behind it: deeper, nothing reads the fill
            depth = band if k == last else MID_EXTEND_PX + 2.0
            fills[k] = _inpaint(lin_c, labels >= k, depth, behind_edt(k), needed(k))
        return fills[k]

    planes, vectors, present = [], [], []
    for k in range(last + 1):
        at_or_behind = labels >= k
        if k == last and background is not None:
            # the clean plate is what lies behind everything, and it does not move
            ext = np.ones_like(at_or_behind)
            colour = np.where(at_or_behind[..., None], lin_c, background[crop])
            vec = np.where(at_or_behind[..., None], v_c, np.float32(0))
            cover = np.ones(ext.shape)
            mine = np.zeros(ext.shape, bool)
        else:
            if k == 0:
                ext, colour, vec = labels == 0, lin_c, v_c
            else:
                dist, idx = behind_edt(k)
                source = (idx[0], idx[1])  # nearest pixel at or behind layer k (itself there)
                # only the rearmost layer is assumed to continue far under what hides it
                ext = (labels[source] == k) & (dist <= (band if k == last else MID_EXTEND_PX))
                colour = fill(k)
                vec = v_c[source]
            mine = split & (labels == k)
            cover = np.ones(ext.shape)
            if mine.any():
                behind = (background[crop] if background is not None and k == last - 1
                          else fill(k + 1))
                cover[mine] = split_coverage(lin_c[mine], pure[mine], behind[mine])
        if not ext.any():
            continue
        m = (ext * cover).astype(lin_c.dtype)[..., None]
        light = colour * m
        if mine.any():
            # premultiplied: what the pixel holds beyond the light behind it, so the
            # composite at the anchor time is the image itself
            light[mine] = ((lin_c[mine] - (1.0 - cover[mine][:, None]) * behind[mine])
                           * ext[mine][:, None])
        planes.append(np.concatenate([light, m], axis=2))
        # D_k: the vector of the nearest pixel of the (extended) layer, everywhere.
        dist, nearest = distance_transform_edt(~ext, return_indices=True)
        d = vec[nearest[0], nearest[1]].astype(np.float32)
        vectors.append(d)
        farthest = np.hypot(d[..., 0], d[..., 1]) * max(anchor, 1.0 - anchor)
        present.append(dist <= farthest + 1.5)  # a bilinear footprint reaches sqrt(2) px
    return Layers(origin=(int(r0), int(c0)), planes=np.stack(planes),
                  vectors=np.stack(vectors), flow=own, linear=lin_c,
                  region=region[crop], present=np.stack(present))


def counts(layers: Layers, samples: int | None,
           at: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Samples per pixel: ``samples``, or ``ceil(max |v|) + 1`` over the pixel's own vector
    and the vectors ``D_k`` of the layers present there (int32, h x w; with ``at``, (rows,
    cols) of the crop, only at those pixels, as a flat array)."""
    shape = layers.region.shape if at is None else at[0].shape
    if samples is not None:
        return np.full(shape, samples, np.int32)
    pick = (Ellipsis,) if at is None else (slice(None),) + tuple(at)
    d = layers.vectors[pick]
    flow = layers.flow if at is None else layers.flow[at]
    own = sample_counts(flow[..., 0], flow[..., 1])
    per_layer = np.where(layers.present[pick], sample_counts(d[..., 0], d[..., 1]), 1)
    return np.maximum(own, per_layer.max(axis=0))


def composite(layers: Layers, anchor: float, samples: int | None, weights: np.ndarray | None,
              full_shape: tuple[int, int]) -> np.ndarray:
    """Front-to-back composite of every shutter sample, float64 (the numpy reference).

    Returns the exposure of every crop pixel (h x w x C); only ``layers.region`` is used.
    """
    from clblur.reference import bilinear_at

    h, w = layers.region.shape
    r0, c0 = layers.origin
    yy, xx = np.mgrid[r0:r0 + h, c0:c0 + w].astype(np.float64)
    n = counts(layers, samples).astype(np.float64)
    den = np.maximum(n - 1, 1)
    channels = layers.linear.shape[2]
    acc = np.zeros((h, w, channels))
    for j in range(int(n.max())):
        active = j < n
        num = j - anchor * (n - 1)
        left = np.ones((h, w, 1))
        e = np.zeros((h, w, channels))
        for plane, d, there in zip(layers.planes, layers.vectors, layers.present, strict=True):
            x = xx - (d[..., 0].astype(np.float64) * num) / den
            y = yy - (d[..., 1].astype(np.float64) * num) / den
            s = bilinear_at(plane, x, y, layers.origin, full_shape) * there[..., None]
            e += left * s[..., :channels]
            left = left * (1.0 - s[..., channels:])
        v = layers.flow.astype(np.float64)
        x = xx - (v[..., 0] * num) / den
        y = yy - (v[..., 1] * num) / den
        e += left * bilinear_at(layers.linear, x, y, layers.origin, full_shape)
        wj = weights[j] if weights is not None else 1.0 / n
        acc += np.where(active, wj, 0.0)[..., None] * e
    return acc


def plan_order(plan: BlurPlan) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(vectors, ordering, layering rule) when ``plan`` can occlude anything, else None (the
    gather is exact)."""
    if plan.depth is None or isinstance(plan.motion, (Uniform, PSF)):
        return None  # one displacement for every pixel: nothing moves relative to anything
    if plan.extent is not None:
        raise ValueError("a depth ordering needs the whole image; it cannot run on tiles")
    assert isinstance(plan.motion, Field)
    return plan.motion.flow, plan.depth, "speed" if plan.speed_order else "depth"


def integrate(lin: np.ndarray, plan: BlurPlan) -> np.ndarray:
    """Layered exposure on the numpy reference (a ``clblur.pipeline`` integrator)."""
    from clblur.reference import integrate as gather

    acc = gather(lin, plan)
    ordered = plan_order(plan)
    if ordered is None:
        return acc
    v, order, rule = ordered
    region = region_mask(v, plan.anchor)
    if not region.any():
        return acc
    layers = prepare(lin, v, order, plan.anchor, region, background_linear(plan), rule=rule)
    if layers is None:
        return acc
    out = composite(layers, plan.anchor, plan.samples, plan.weights, plan.full_shape)
    h, w = layers.region.shape
    r0, c0 = layers.origin
    view = acc[r0:r0 + h, c0:c0 + w]
    view[layers.region] = out[layers.region]
    return acc


def background_linear(plan: BlurPlan) -> np.ndarray | None:
    """The clean plate of ``plan`` linearised as its image is (host, float64), or None."""
    if plan.background is None:
        return None
    from dataclasses import replace

    from clblur.reference import linearise

    return linearise(replace(plan, image=plan.background, background=None))


def integrator(backend: str, device: str | None = None):
    """The layered integrator of a resolved backend (``"numpy"`` or ``"opencl"``)."""
    if backend == "numpy":
        return integrate
    from clblur.opencl_layered import integrator as opencl_integrator

    return opencl_integrator(device)


def layered_half(lin: np.ndarray, v: np.ndarray, anchor: str, *, depth=None,
                 samples: int | None = None, backend: str = "auto",
                 device: str | None = None) -> np.ndarray:
    """Linear exposure (H x W x C, the dtype of ``lin``) of one straight shutter segment with
    vectors ``v``, ordered by ``depth`` (default: speed).  ``lin`` is linear light and is
    blurred with the identity response (used by ``clblur.video`` for each shutter half)."""
    from clblur.blur import blur

    order = "speed" if depth is None else depth
    return blur(lin, v, "linear", anchor=anchor, samples=samples, backend=backend,
                device=device, depth=order)
