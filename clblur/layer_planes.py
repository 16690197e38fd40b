"""The layers of layered exposure: premultiplied planes, their vectors, and what lies hidden.

Builds :class:`Layers` for a crop of the image (``clblur.layered_exposure`` states the model):
each layer a premultiplied image ``(M L, M)`` with a vector field, hidden pixels reconstructed
from the nearest visible pixel at or behind them (the stated assumption; an intermediate layer
also inside the convex hull of its visible pieces, and round under what hides it where its
visible silhouette is round, :func:`hidden_completion`), mixed pixels split by a coverage
fitted to their light (:func:`split_coverage`).
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from clblur.halo import halo_for_reach, reach
from clblur.layering import layer_labels

__all__ = ["ARC_FIT_RMS", "ARC_MAX_RADIUS", "ARC_MIN_PX", "HOST", "INPAINT_RADIUS", "Layers",
           "MID_EXTEND_PX", "SPLIT_PRIOR", "Transforms", "bounding_box", "crop_margin",
           "distance_to", "harmonic_fill", "hidden_completion", "hidden_hull", "prepare",
           "split_coverage"]

# px the reconstruction of hidden light extends beyond the pixels a sample reads, so that
# what is read is filled from a filled neighbourhood (the radius the Navier-Stokes
# inpainting this fill replaced read)
INPAINT_RADIUS = 3
MID_EXTEND_PX = 2.0
SPLIT_PRIOR = 1e-4  # (linear light)^2: below this contrast a mixed pixel stays half and half


@dataclass
class Layers:
    """The layers of a crop of the image, ready to composite (module Conventions).

    ``origin``: (row, col) of the crop in the full image (the region's bounding box plus the
    halo its samples reach, ``clblur.halo``); ``planes``: K x h x w x (C + 1) premultiplied
    ``(M L, M)``; ``vectors``: K x h x w x 2 float32 ``D_k``; ``flow`` and ``linear``: the
    crop of the image's own vectors and linear image (for uncovered light); ``region``: h x w
    bool, the pixels to composite; ``present``: K x h x w bool, whether layer ``k`` can cover
    the pixel at any sample (farther than its reach plus the bilinear footprint it reads only
    zeros, so skipping it changes nothing but the sample count); ``warped``: K bool, whether
    layer ``k``'s vectors vary (not a rigid translation).  ``curvature``: None (straight
    paths), or K x h x w x 2 float32 ``C_k``, the quadratic term of a curved path
    (``clblur.layered_exposure``, curved paths; built by ``clblur.render_layers`` and, for
    one frame, by :func:`prepare`; a layer is ``warped`` when its ``D_k`` or its ``C_k``
    vary).  ``inverse_steps``: fixed-point
    steps of a warped layer's inverse motion (``clblur.layered_exposure``); None is
    ``INVERSE_STEPS``, the count for estimated flow; ``clblur.render_layers`` sets its own for
    a renderer's exact vectors.  ``reach``: None, or K x h x w bool, the pixels at which
    layer ``k``'s vectors set the sample count (``clblur.layered_exposure.counts``) where
    ``present`` is tighter than that (``clblur.render_layers``); None: ``present``.
    ``present`` holds values at the
    region's pixels only (False elsewhere: nothing reads it); a rigid layer's ``vectors`` are
    its one vector at every pixel (read at the region's pixels only), and a warped layer's
    cover the whole crop, because the composite reads them where its samples land
    (``clblur.layered_exposure``, inverse motion).
    """

    origin: tuple[int, int]
    planes: np.ndarray
    vectors: np.ndarray
    flow: np.ndarray
    linear: np.ndarray
    region: np.ndarray
    present: np.ndarray
    warped: np.ndarray
    curvature: np.ndarray | None = None
    inverse_steps: int | None = None
    reach: np.ndarray | None = None


# cv2's exact transform returns float32 distances; squared, they round back to the exact
# integer squared distance while d * ulp(d) < 1/2 (about 2000 px; half that kept as margin)
_EXACT_FLOAT32_PX = 1024.0


def distance_to(inside: np.ndarray,
                at: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Euclidean distance (float64, H x W) from every pixel to the nearest ``inside`` pixel:
    ``scipy.ndimage.distance_transform_edt(~inside)`` bit for bit, several times faster.
    With ``at`` (rows, cols), only at those pixels (a flat array).

    Why: the distance bands of :func:`prepare` and ``region_mask`` ask only for distances.
    OpenCV's exact transform (Felzenszwalb and Huttenlocher, "Distance transforms of sampled
    functions", 2012; ``cv2.DIST_MASK_PRECISE``) gives them in float32; squaring and rounding
    recovers the exact integer squared distance, whose float64 square root is what scipy
    returns.  Farther than ``_EXACT_FLOAT32_PX`` (where float32 could round the square to the
    wrong integer) scipy answers.  ``inside`` must hold at least one True pixel.
    """
    import cv2

    d = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    if at is not None:
        d = d[at]
    if float(d.max(initial=0.0)) > _EXACT_FLOAT32_PX:
        from scipy.ndimage import distance_transform_edt

        exact = distance_transform_edt(~inside)
        return exact if at is None else exact[at]
    d = d.astype(np.float64)
    return np.sqrt(np.rint(d * d))


def bounding_box(values: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
    """The bounding box of the pixels of ``values`` (H x W [x C]) that are nonzero in any
    channel, grown by ``margin`` (clipped to the image), or None when there are none.

    The reductions run along memory order (rows, then the rows' columns): reducing a
    H x W x C float array over its last axis cost more than the rest of building a layer."""
    h, w = values.shape[:2]
    rows = np.flatnonzero(values.reshape(h, -1).any(axis=1))
    if rows.size == 0:
        return None
    band = values[rows[0]:rows[-1] + 1]
    cols = np.flatnonzero((band != 0).reshape(band.shape[0], -1).any(axis=0)
                          .reshape(w, -1).any(axis=1))
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)))


def _nearest_transform(outside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``scipy.ndimage.distance_transform_edt(outside, return_indices=True)`` with the
    indices as flat (row-major) indices into the image: (distance, flat index), H x W each.

    Why flat: gathering an image at them with ``np.take`` is several times faster than
    fancy indexing with the two index planes (the same values, copied)."""
    from scipy.ndimage import distance_transform_edt

    dist, idx = distance_transform_edt(outside, return_indices=True)
    return dist, idx[0] * outside.shape[1] + idx[1]


def _at(a: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``a`` (H x W [x C]) at the flat indices ``flat`` (any shape): ``a[rows, cols]``."""
    return np.take(a.reshape((-1,) + a.shape[2:]), flat, axis=0)


# Jacobi sweeps of harmonic_fill at its finest level, doubled at each coarser one (up to
# FILL_SWEEPS_MAX): the error left by upsampling a coarser solution is mostly a few pixels
# long, which a few sweeps damp
FILL_SWEEPS = 4
FILL_SWEEPS_MAX = 64
_NEIGHBOUR_MEAN = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], np.float32) / 4


def harmonic_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` (h x w x C float32) with the pixels outside ``known`` (h x w bool, at least
    one True) filled smoothly from the known ones; known pixels are returned unchanged.

    The fill approximates the membrane (harmonic) interpolant, the solution of Laplace's
    equation in the hole with the known pixels as boundary values: the smoothest fill, exact
    for a linear ramp, which a hole's middle then follows rather than bending towards the
    hole's mean.  It is computed coarse to fine (a cascadic multigrid, Bornemann and
    Deuflhard, Numer. Math. 75, 1996): a pyramid of weight-premultiplied values and weights
    (the *pull* of Gortler et al.'s pull-push, "The Lumigraph", SIGGRAPH 1996;
    ``cv2.pyrDown``) until every pixel of the coarsest level has weight; then at each finer
    level the upsampled coarser solution, blended with the level's own mean by its
    confidence ``min(1, 4 w)`` (the weight sum of a pixel's four children), relaxed by
    Jacobi sweeps (each free pixel to its 4-neighbours' mean, ``FILL_SWEEPS`` at the finest
    level, doubled per coarser one).  The cost is linear in the array.
    """
    import cv2

    c = values.shape[2]
    weight = known.astype(np.float32)
    # one array per level: the values premultiplied by the weight, and the weight last
    level = np.concatenate([values * weight[..., None], weight[..., None]], axis=2)
    pyramid = [level]
    while min(level.shape[:2]) > 1 and not (level[..., c] > 0).all():
        level = cv2.pyrDown(level).reshape(-1, -(-level.shape[1] // 2), c + 1)
        pyramid.append(level)
    coarse = pyramid[-1]
    estimate = coarse[..., :c] / np.maximum(coarse[..., c:], np.float32(1e-30))
    for depth in range(len(pyramid) - 2, -1, -1):
        level = pyramid[depth]
        lh, lw = level.shape[:2]
        wt = level[..., c:]
        trust = np.minimum(np.float32(4) * wt, np.float32(1)) if depth else wt
        held = trust * (level[..., :c] / np.maximum(wt, np.float32(1e-30)))
        free = np.float32(1) - trust
        estimate = held + free * cv2.pyrUp(estimate, dstsize=(lw, lh)).reshape(lh, lw, c)
        for _ in range(min(FILL_SWEEPS << depth, FILL_SWEEPS_MAX)):
            mean = cv2.filter2D(estimate, -1, _NEIGHBOUR_MEAN,
                                borderType=cv2.BORDER_REPLICATE).reshape(lh, lw, c)
            estimate = held + free * mean
    out = values.copy()
    out[~known] = estimate[~known]
    return out


@dataclass(frozen=True)
class Transforms:
    """The array transforms that building layers spends most of its time in, as one
    swappable set: a device backend passes its own (``clblur.opencl.layered.transforms``), with
    the same contracts.

    ``nearest(outside)``: (distance, flat index of a nearest pixel that is not ``outside``),
    as :func:`_nearest_transform` (where two pixels are equally near, another implementation
    may pick the other one); ``distance(inside, at=None)``: :func:`distance_to`, exact;
    ``fill(values, known)``: :func:`harmonic_fill`, to float32 rounding.
    ``labels(order, rule=...)``: ``clblur.layering.layer_labels``, exactly.  ``threads``:
    whether independent ``nearest`` calls run on threads side by side (a device queue
    serialises them anyway).
    """

    nearest: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    distance: Callable[..., np.ndarray]
    fill: Callable[[np.ndarray, np.ndarray], np.ndarray]
    labels: Callable[..., np.ndarray] = layer_labels
    threads: bool = True  # independent transforms may run side by side (scipy's release the GIL)


HOST = Transforms(nearest=_nearest_transform, distance=distance_to, fill=harmonic_fill)


def _pool(transforms: Transforms, tasks: int) -> ThreadPoolExecutor | None:
    """Threads for ``tasks`` independent transforms where they can run side by side (more
    than one task, more than one core, transforms that release the interpreter lock), else
    None: run them in turn."""
    cores = os.cpu_count() or 1
    if transforms.threads and tasks > 1 and cores > 1:
        return ThreadPoolExecutor(min(tasks, cores))
    return None


def _inpaint(lin: np.ndarray, known: np.ndarray, depth: float,
             nearest: tuple[np.ndarray, np.ndarray] | None = None,
             needed: np.ndarray | None = None,
             window: tuple[slice, slice] = (slice(None), slice(None)),
             fill: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """``lin`` with the pixels outside ``known`` reconstructed from the known ones
    (:func:`harmonic_fill`) up to ``depth`` pixels from them; deeper pixels, which no sample
    reads, take their nearest known pixel and join the known ones for the fill.
    ``nearest``: the distance transform of ``~known`` with its flat indices
    (:func:`_nearest_transform`), if already computed; ``needed``: the pixels any sample can
    read (others take their nearest known pixel too), and the fill runs only on the bounding
    box of the hole they leave, plus a margin.  Returns the result on ``window`` only (the
    part the caller reads)."""
    if not known.any():
        return lin[window].copy()
    dist, flat = nearest if nearest is not None else _nearest_transform(~known)
    deep = dist > depth + INPAINT_RADIUS + 1
    if needed is not None:
        deep |= ~needed
    hole = ~known & ~deep
    # known pixels are their own nearest known pixel: everywhere but in the hole, the
    # nearest known pixel's light is the result
    out = _at(lin, flat[window])
    if not hole.any():
        return out
    # the fill's cost grows with the array it is given: only the hole's box and a margin
    box = bounding_box(hole, INPAINT_RADIUS + 2)
    # the fill's input (float32): as the result outside the hole, and in it too where there
    # is anything deep (else the image itself)
    base = (_at(lin, flat[box]) if deep.any() else lin[box]).astype(np.float32)
    # the box's part of the window, in window and in box coordinates
    h, w = known.shape
    (wr0, wr1, _), (wc0, wc1, _) = window[0].indices(h), window[1].indices(w)
    (br0, br1, _), (bc0, bc1, _) = box[0].indices(h), box[1].indices(w)
    r_lo, r_hi, c_lo, c_hi = max(wr0, br0), min(wr1, br1), max(wc0, bc0), min(wc1, bc1)
    if r_lo >= r_hi or c_lo >= c_hi:
        return out
    in_win = (slice(r_lo - wr0, r_hi - wr0), slice(c_lo - wc0, c_hi - wc0))
    in_box = (slice(r_lo - br0, r_hi - br0), slice(c_lo - bc0, c_hi - bc0))
    # in the box, whatever is not known comes back from the fill: filled (the hole) or its
    # nearest known pixel's light rounded to float32 (deep); known pixels keep lin exactly
    fresh = ~known[box][in_box]
    filled = (fill or HOST.fill)(base, ~hole[box])
    np.copyto(out[in_win], filled[in_box], where=fresh[..., None])  # a mask's fancy write is slower
    return out


def hidden_hull(labels: np.ndarray, k: int) -> np.ndarray:
    """The pixels of layer ``k``'s amodal completion: the convex hull of each of its connected
    pieces (8-connected), where a nearer layer covers it (the stated assumption: a surface
    hidden by a nearer one continues under it as far as its visible part's convex hull)."""
    import cv2

    mine = np.ascontiguousarray(labels == k).view(np.uint8)  # OpenCV draws on C order
    contours, _ = cv2.findContours(mine, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    hull = np.zeros(mine.shape, np.uint8)
    hulls = [cv2.convexHull(c) for c in contours if len(c) >= 3]
    if hulls:
        cv2.fillPoly(hull, hulls, 1)
    return hull.view(bool) & (labels < k)


# The round completion (hidden_completion): how many visible silhouette pixels a piece needs,
# how well one circle must fit their edge points (px rms; a digitised circle fits to 0.22 -
# 0.31 px), the largest radius taken, in units of the visible silhouette's extent (a flatter
# arc says little about where the circle closes, and a straight edge fits a huge one), and
# the share of the arc (one pixel inside it) allowed over pixels seen to lie behind the layer
ARC_MIN_PX = 16
ARC_FIT_RMS = 0.5
ARC_MAX_RADIUS = 1.0
ARC_SEEN_BEHIND = 0.1
_STEPS4 = ((1, 0), (-1, 0), (0, 1), (0, -1))


def _cyclic_runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each cyclic run of True in ``flags`` (some entry False)."""
    start = int(np.argmin(flags))  # a False entry: no run wraps past it
    edges = np.diff(np.concatenate([[0], np.roll(flags, -start).astype(np.int8), [0]]))
    firsts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    n = flags.size
    return [(int((f + start) % n), int((e - 1 + start) % n)) for f, e in zip(firsts, ends,
                                                                             strict=True)]


def _circle(points: np.ndarray) -> tuple[float, float, float, float] | None:
    """Least-squares circle through ``points`` (N x 2, x y; Kasa's linear fit): centre x,
    centre y, radius and the rms of the points' distances from it; None if degenerate."""
    x, y = points[:, 0], points[:, 1]
    sol, *_ = np.linalg.lstsq(np.column_stack([x, y, np.ones_like(x)]), x * x + y * y,
                              rcond=None)
    cx, cy = sol[0] / 2.0, sol[1] / 2.0
    r2 = sol[2] + cx * cx + cy * cy
    if not (np.isfinite(r2) and r2 > 0.0):
        return None
    r = math.sqrt(r2)
    return cx, cy, r, float(np.sqrt(np.mean((np.hypot(x - cx, y - cy) - r) ** 2)))


def _round_arcs(raw: np.ndarray, k: int, contour: np.ndarray, seen_nearer: np.ndarray,
                out: np.ndarray) -> None:
    """Set in ``out`` (uint8) what each hidden run of one piece's silhouette ``contour``
    (N x 2 pixels x y, in order) encloses with the circle its whole visible silhouette lies
    on, if it lies on one (see :func:`hidden_completion`)."""
    import cv2

    n = len(contour)
    hidden = seen_nearer[contour[:, 1], contour[:, 0]]
    if not hidden.any() or (~hidden).sum() < ARC_MIN_PX:
        return
    h, w = raw.shape
    seen = contour[~hidden]
    # the silhouette lies between a layer's last pixel and the first one behind it
    xs, ys = seen[:, 0], seen[:, 1]
    edge = []
    for dx, dy in _STEPS4:
        nx, ny = xs + dx, ys + dy
        inb = (nx >= 0) & (nx < w) & (ny >= 0) & (ny < h)
        behind = np.zeros(xs.size, bool)
        behind[inb] = raw[ny[inb], nx[inb]] > k
        edge.append(np.column_stack([xs[behind] + dx / 2.0, ys[behind] + dy / 2.0]))
    edge = np.vstack(edge)
    fit = _circle(edge) if len(edge) >= ARC_MIN_PX else None
    extent = float(np.ptp(seen, axis=0).max()) + 1.0
    if fit is None or fit[3] > ARC_FIT_RMS or fit[2] > ARC_MAX_RADIUS * extent:
        return
    cx, cy, r, _ = fit
    # the way the silhouette turns about the centre, which its hidden runs keep
    rel = seen - (cx, cy)
    step = np.roll(contour, -1, axis=0)[~hidden] - seen
    sense = 1.0 if float(np.sum(rel[:, 0] * step[:, 1] - rel[:, 1] * step[:, 0])) > 0 else -1.0
    for first, last in _cyclic_runs(hidden):
        a, b = contour[(first - 1) % n], contour[(last + 1) % n]  # the visible ends
        ta = math.atan2(a[1] - cy, a[0] - cx)
        sweep = (sense * (math.atan2(b[1] - cy, b[0] - cx) - ta)) % (2.0 * math.pi)
        theta = ta + sense * sweep * np.linspace(0.0, 1.0, int(math.ceil(sweep * r)) + 2)
        inner = np.rint(np.column_stack([cx + (r - 1.0) * np.cos(theta),
                                         cy + (r - 1.0) * np.sin(theta)])).astype(int)
        ok = (inner[:, 0] >= 0) & (inner[:, 0] < w) & (inner[:, 1] >= 0) & (inner[:, 1] < h)
        if not ok.any() or (raw[inner[ok, 1], inner[ok, 0]] > k).mean() > ARC_SEEN_BEHIND:
            continue  # the circle would cross what is seen behind the layer: not this shape
        arc = np.column_stack([cx + r * np.cos(theta), cy + r * np.sin(theta)])
        run = contour[[(first + i) % n for i in range((last - first) % n + 1)]][::-1]
        poly = np.rint(np.vstack([arc, run])).astype(np.int32)
        lo = np.maximum(poly.min(axis=0), 0)
        hi = np.minimum(poly.max(axis=0) + 1, (w, h))
        if (hi <= lo).any():
            continue  # wholly outside the crop
        region = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)  # the polygon's box
        cv2.fillPoly(region, [poly - lo], 1)
        ys, xs = np.nonzero(region)
        ys, xs = ys + lo[1], xs + lo[0]
        inside = np.hypot(xs - cx, ys - cy) < r  # pixel centres inside the circle
        out[ys[inside], xs[inside]] = 1


def hidden_completion(labels: np.ndarray, k: int, raw: np.ndarray | None = None) -> np.ndarray:
    """The pixels of layer ``k``'s amodal completion where a nearer layer covers it: the
    convex hull of each visible piece (:func:`hidden_hull`) and, for a piece whose whole
    visible silhouette lies on one circle (``ARC_MIN_PX`` pixels or more, their edge points
    within ``ARC_FIT_RMS`` of it, a radius of at most ``ARC_MAX_RADIUS`` times the
    silhouette's extent), that circle's disc under what hides it, unless the circle crosses
    pixels seen behind the layer.  The stated assumption: a round silhouette stays round
    where it is hidden (a ball, a wheel, a disc; any other shape keeps the hull).  ``raw``:
    the labels before mixed pixels joined the nearer layer (the silhouette is read there;
    default ``labels``)."""
    import cv2

    raw = np.ascontiguousarray(labels if raw is None else raw)
    out = np.ascontiguousarray(hidden_hull(labels, k)).view(np.uint8)
    seen_nearer = cv2.dilate((raw < k).view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    contours, _ = cv2.findContours((raw == k).astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_NONE)
    for c in contours:
        _round_arcs(raw, k, c[:, 0, :], seen_nearer, out)
    return out.view(bool) & (labels < k)


_BRUTE_PAIRS = 1 << 21  # pairs of pixels _nearest_pixel measures directly (16 MB of int64)
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)  # 4-neighbours and the pixel

# offsets of the 7 x 7 square nearer than 4 px (the corners, at 4.24 px, could hide a pixel
# at 4 - 4.2 px outside the square), nearest first (ties in a fixed order)
_NEAR = sorted(((dy, dx) for dy in range(-3, 4) for dx in range(-3, 4)
                if 0 < dy * dy + dx * dx < 16), key=lambda o: (o[0] * o[0] + o[1] * o[1], o))
_NEAR_FOOTPRINT = np.zeros((7, 7), np.uint8)  # the offsets of _NEAR as a dilation kernel
for _dy, _dx in _NEAR:
    _NEAR_FOOTPRINT[3 + _dy, 3 + _dx] = 1


def _nearest_pixel(inside: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a nearest ``inside`` pixel (not empty) to each ``at`` pixel (row-major
    order of ``at``): looked up under 4 px, then for the rest by distances to every
    ``inside`` pixel where there are few pairs, else by a distance transform of the box
    around them (mixed pixels lie next to their layer, so the lookup nearly always
    succeeds)."""
    import cv2
    from scipy.ndimage import distance_transform_edt

    h, w = inside.shape
    ys, xs = np.nonzero(at)
    ry, rx = np.full(ys.size, -1), np.full(ys.size, -1)
    # the lookup visits only the pixels with an inside pixel among the offsets (a dilation by
    # the offsets' footprint; deep in a hidden part most have none), and each offset only
    # those still without one
    near = cv2.dilate(np.ascontiguousarray(inside).view(np.uint8), _NEAR_FOOTPRINT).view(bool)
    active = np.flatnonzero(near[ys, xs])
    for dy, dx in _NEAR:
        if not active.size:
            break
        y, x = ys[active] + dy, xs[active] + dx
        ok = (y >= 0) & (y < h) & (x >= 0) & (x < w)
        hit = np.zeros(active.size, bool)
        hit[ok] = inside[y[ok], x[ok]]
        found = active[hit]
        ry[found], rx[found] = y[hit], x[hit]
        active = active[~hit]
    todo = ry < 0
    if not todo.any():
        return ry, rx
    # the rest (few: pixels of a sliver far from its layer's core; a whole-frame transform
    # for them was most of this function's time on real flows)
    ty, tx = ys[todo], xs[todo]
    iy, ix = np.nonzero(inside)
    if not iy.size:
        raise ValueError("_nearest_pixel: no inside pixel")
    if iy.size * ty.size <= _BRUTE_PAIRS:
        # few pixels of the layer (a layer of slivers): every pair, the first nearest in
        # row-major order
        d2 = (ty[:, None] - iy[None, :]) ** 2 + (tx[:, None] - ix[None, :]) ** 2
        pick = np.argmin(d2, axis=1)
        ry[todo], rx[todo] = iy[pick], ix[pick]
        return ry, rx
    # else the transform of a box around them, grown until each one's nearest pixel is
    # nearer than the box's cut edges (then every pixel at that distance lies in the box, and
    # the transform picks among them as it does on the whole array); growing the box by the
    # largest shortfall settles it in one more transform, as no pixel's distance grows
    margin = 8
    while True:
        b0, b1 = max(ty.min() - margin, 0), min(ty.max() + 1 + margin, h)
        a0, a1 = max(tx.min() - margin, 0), min(tx.max() + 1 + margin, w)
        if 2 * (b1 - b0) * (a1 - a0) >= h * w:
            b0, b1, a0, a1 = 0, h, 0, w  # most of the array: the whole of it
        box = inside[b0:b1, a0:a1]
        if not box.any():
            margin *= 2
            continue
        dist, idx = distance_transform_edt(~box, return_indices=True)
        py, px = ty - b0, tx - a0
        d = dist[py, px]
        # distance from each pixel to the box's edges that cut the array (inf: none)
        edge = np.full(ty.size, np.inf)
        for cut, gap in ((b0 > 0, py + 1), (b1 < h, b1 - b0 - py), (a0 > 0, px + 1),
                         (a1 < w, a1 - a0 - px)):
            if cut:
                edge = np.minimum(edge, gap)
        short = d >= edge
        if not short.any():
            ry[todo], rx[todo] = idx[0][py, px] + b0, idx[1][py, px] + a0
            return ry, rx
        margin += int(np.ceil((d[short] - edge[short]).max())) + 1


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


def crop_margin(r: float) -> int:
    """How far beyond its region (px) :func:`prepare` reads the image, vectors and ordering
    for samples that reach ``r``: the rearmost layer's reconstruction (``2 r + 2`` under what
    hides it) read from up to ``r`` away, plus the bilinear footprint."""
    return int(math.ceil(2.0 * r + 2.0 + r)) + 3


def prepare(lin, v: np.ndarray, order: np.ndarray, anchor: float,
            region: np.ndarray, background: np.ndarray | None = None,
            split_edges: bool = True, rule: str = "depth",
            dtype: type = np.float64, transforms: Transforms | None = None,
            r: float | None = None, curvature: np.ndarray | None = None) -> Layers | None:
    """Build the layers around ``region`` (H x W bool) from the linear image, the vectors and
    the ordering signal; ``background``: the linear clean plate, if known.  Composed on the
    host and shared by both backends (a device supplies its ``transforms``).  ``lin``: the
    linear image, or a function that returns the linear image of a crop ``(row slice, col
    slice)`` (so only the crop is linearised).  None when the ordering gives one layer
    there and the path is straight: a single surface is what the gather integrates.
    ``rule``: how a float ``order`` becomes layers (:func:`layer_labels`); ``dtype``: of
    the planes (a device backend takes float32: the same values as float64 planes rounded,
    built without the float64 copy); ``transforms``: the labels, the distance transforms and
    the fill (:class:`Transforms`; None: :data:`HOST`); ``r``: ``reach(v, anchor)`` where the caller
    has it already (a pass over the whole field otherwise; with ``curvature``, give the reach
    of the curved path, :func:`clblur.layered_exposure.curved_reach`).  ``curvature``: H x W
    x 2, the quadratic term ``C`` of a curved path (``Layers.curvature``); it travels with
    the vectors (a hidden pixel takes its nearest visible pixel's ``C`` as it takes its
    ``D``)."""
    import cv2
    from scipy.ndimage import maximum_filter, minimum_filter

    transforms = HOST if transforms is None else transforms
    h, w = region.shape
    r = reach(v, anchor) if r is None else r
    band = 2.0 * r + 2.0
    crop = bounding_box(region, crop_margin(r))
    (r0, r1), (c0, c1) = (crop[0].start, crop[0].stop), (crop[1].start, crop[1].stop)
    labels = transforms.labels(order[crop], rule=rule)
    last = int(labels.max())
    if last == 0 and background is None and curvature is None:
        return None  # one surface on a straight path: what the gather integrates
    lin_c = lin(crop) if callable(lin) else lin[crop]
    v_c = v[crop].astype(np.float32)
    own = v_c  # the image's own vectors, for light no layer covers
    if curvature is not None:  # D and C side by side: every step below moves both alike
        v_c = np.concatenate([v_c, curvature[crop].astype(np.float32)], axis=2)
    span = max(anchor, 1.0 - anchor)
    # Mixed pixels: a pixel next to another layer holds light of both; it is split between the
    # nearer layer around it (coverage fitted to its light, split_coverage) and what lies
    # behind (reconstructed), so the composite at the anchor time is the image itself.
    if last < 256:
        # OpenCV's 3 x 3 min / max on the labels as bytes: outside the image it ignores the
        # border, which for a 3 x 3 window is scipy's "nearest"
        square = np.ones((3, 3), np.uint8)
        lab8 = labels.astype(np.uint8)
        front = cv2.erode(lab8, square).astype(labels.dtype)
        back = cv2.dilate(lab8, square).astype(labels.dtype)
    else:
        front = minimum_filter(labels, size=3, mode="nearest")
        back = maximum_filter(labels, size=3, mode="nearest")
    split = (front != back) if split_edges else np.zeros(labels.shape, bool)
    raw, labels = labels, np.where(split, front, labels)
    # a surface whose every pixel is mixed (a line at most 2 px wide) has joined the layers
    # in front of it whole: behind the deepest layer left there is no pixel at all, so no
    # transform to the nearest one (a layer without pixels is no layer)
    deepest = int(labels.max())
    v_c = v_c.copy() if curvature is None else v_c
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
    from_region = transforms.distance(region[crop])
    pad = 2.0 + INPAINT_RADIUS + 1
    l2 = v_c[..., 0] * v_c[..., 0] + v_c[..., 1] * v_c[..., 1]
    if curvature is not None:  # |D t + C t^2| <= |D| span + |C| span^2 over the shutter
        c2 = v_c[..., 2] * v_c[..., 2] + v_c[..., 3] * v_c[..., 3]
        l2 = np.square(np.sqrt(l2) + np.sqrt(c2) * np.float32(span))
    # reach() of the vectors at or behind each layer: the largest square, rearmost first
    longest = np.maximum.accumulate(
        [float(l2[labels == k].max(initial=0.0)) for k in range(last, -1, -1)])[::-1]
    reach_at_or_behind = [math.sqrt(x) * (1 + 1e-6) * span for x in longest]

    def needed(k: int) -> np.ndarray:
        out = from_region <= reach_at_or_behind[k] + pad
        mixed = split & (labels == k - 1)
        if mixed.any():
            # scipy's binary_dilation(mixed, iterations=INPAINT_RADIUS + 1) (a cross, so
            # an L1 ball), by OpenCV: outside the image counts as not mixed in both
            near_mixed = cv2.dilate(mixed.view(np.uint8), _CROSS,
                                    iterations=INPAINT_RADIUS + 1).view(bool)
            out |= near_mixed & (from_region <= reach_at_or_behind[k - 1] + pad)
        return out

    def behind_edt(k: int) -> tuple[np.ndarray, np.ndarray]:
        """Distance to, and flat index of, the nearest pixel at or behind layer ``k``."""
        if k not in nearest_at_or_behind:
            nearest_at_or_behind[k] = transforms.nearest(labels < k)
        return nearest_at_or_behind[k]

    # every layer behind the first reads its transform below (the rearmost one not when a
    # plate stands for it); scipy releases the interpreter lock, so they run side by side
    wanted = [k for k in range(1, deepest + 1) if not (k == last and background is not None)]
    pool = _pool(transforms, len(wanted))
    if pool is not None:
        with pool:
            found = list(pool.map(lambda k: transforms.nearest(labels < k), wanted))
        nearest_at_or_behind.update(zip(wanted, found, strict=True))

    def fill(k: int) -> np.ndarray:
        """The linear image with everything nearer than layer ``k`` reconstructed (on the
        window ``win``)."""
        if k not in fills and k > deepest:  # nothing at or behind k: nothing to reconstruct
            fills[k] = lin_c[win].copy()
        if k not in fills:
            # an intermediate layer extends MID_EXTEND_PX under what hides it, and a mixed
            # pixel lies within 2 px of what is behind it: deeper, nothing reads the fill
            depth = band if k == last else MID_EXTEND_PX + 2.0
            fills[k] = _inpaint(lin_c, labels >= k, depth, behind_edt(k), needed(k), win,
                                transforms.fill)
        return fills[k]

    # The composite reads the layers only within the reach of the region's pixels, plus the
    # bilinear neighbour and a margin for float32 positions (the halo rule of clblur.halo):
    # the planes are built on that window of the crop, and the vectors and the presence of
    # each layer at the region's pixels only (nothing else reads them).
    hal = halo_for_reach(r)
    inner = bounding_box(region, hal)
    win = (slice(max(inner[0].start, r0) - r0, min(inner[0].stop, r1) - r0),
           slice(max(inner[1].start, c0) - c0, min(inner[1].stop, c1) - c0))
    reg = region[crop][win]
    at = np.nonzero(reg)
    # the region's pixels as flat indices of the window: read with np.take and written by
    # index (a boolean mask of a large window is many times slower either way)
    reg_flat = np.flatnonzero(reg)
    lab_w, split_w, lin_w, v_w = labels[win], split[win], lin_c[win], v_c[win]
    hw, ch = reg.shape, lin_c.shape[2]
    planes = np.empty((last + 1,) + hw + (ch + 1,), dtype)
    # D_k, and C_k of a curved path, each contiguous as Layers holds them: every layer kept
    # writes its own (no zeroing pass, no split copy of a D-and-C array at the end)
    flows = np.empty((last + 1,) + hw + (2,), np.float32)
    bends = None if curvature is None else np.empty((last + 1,) + hw + (2,), np.float32)
    present = np.zeros((last + 1,) + hw, bool)
    warped = np.zeros(last + 1, bool)
    # Each layer's extent and vectors first (cheap), then the transforms that find how far
    # its region pixels are from it (a transform of the window per layer) side by side with
    # the fills and the planes' assembly, where the transforms may run on threads.
    shapes = []  # (k, extent, vectors, own mixed pixels) of the layers a sample can read
    completed: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # k: (hull pixels, core), crop
    for k in range(last + 1):
        if k == last and background is not None:
            # the clean plate is what lies behind everything, and it does not move
            ext_w = np.ones(hw, bool)
            vec_w = np.where((lab_w >= k)[..., None], v_w, np.float32(0))
            mine_w = np.zeros(hw, bool)
        elif k > deepest:
            continue  # no pixel left on it (above)
        else:
            if k == 0:
                ext_w, vec_w = lab_w == 0, v_w
            else:
                dist, flat = behind_edt(k)
                # nearest pixel at or behind layer k (itself there)
                nearest_w = flat[win]
                # only the rearmost layer is assumed to continue far under what hides it
                ext_w = (_at(labels, nearest_w) == k) & (dist[win] <= (band if k == last
                                                                       else MID_EXTEND_PX))
                vec_w = _at(v_c, nearest_w)
                if k < last:
                    # beyond its 2 px, an intermediate layer continues under what hides it
                    # as far as its pieces' convex hulls (round pieces: their circles),
                    # with the vectors of its nearest pixel and light filled from its own
                    # pixels only
                    more_w = hidden_completion(labels, k, raw)[win] & ~ext_w
                    core = (labels == k) & ~split if more_w.any() else None
                    if core is not None and core.any():
                        more = np.zeros(labels.shape, bool)  # the same pixels in the crop
                        more[win] = more_w
                        ys, xs = _nearest_pixel(core, more)  # row-major, as more_w's
                        vec_w[more_w] = v_c[ys, xs]
                        ext_w = ext_w | more_w
                        completed[k] = (more, core)
            mine_w = split_w & (lab_w == k)
        if ext_w.any():  # else no sample of the region reads this layer
            shapes.append((k, ext_w, vec_w, mine_w))

    # D_k: the vector of the nearest pixel of the (extended) layer.  A layer nearer to a
    # region pixel than its reach plus 1.5 lies inside the window, so the transform of the
    # window finds it.  A layer in rigid translation (one vector) needs only the distance:
    # every nearest pixel carries that vector, and the composite reads it at the region's
    # pixels only.  A warped layer's field covers the window: the composite reads it where
    # its samples land.
    def rigid_vector(ext_w: np.ndarray, vec_w: np.ndarray) -> np.ndarray | None:
        first = vec_w[np.unravel_index(np.argmax(ext_w), hw)]
        differs = (vec_w[..., 0] != first[0]) | (vec_w[..., 1] != first[1])
        for c in range(2, vec_w.shape[2]):  # a curved path: C too
            differs |= vec_w[..., c] != first[c]
        same = ~(differs & ext_w).any()
        return first if same else None

    rigid = [rigid_vector(ext_w, vec_w) for _, ext_w, vec_w, _ in shapes]

    def reach_of(i: int):
        ext_w = shapes[i][1]
        return transforms.distance(ext_w, at) if rigid[i] is not None else \
            transforms.nearest(~ext_w)

    pool = _pool(transforms, len(shapes))
    with pool or contextlib.nullcontext():
        reaches = None if pool is None else [pool.submit(reach_of, i)
                                             for i in range(len(shapes))]
        for i, (k, ext_w, vec_w, mine_w) in enumerate(shapes):
            if k == last and background is not None:
                colour_w = np.where((lab_w >= k)[..., None], lin_w, background[crop][win])
            else:
                colour_w = lin_w if k == 0 else fill(k)
                more, core = completed.get(k, (None, None))
                box = None if more is None else bounding_box(more, INPAINT_RADIUS + 2)
                if box is not None and core[box].any():
                    # the membrane fill on the hull's box with the layer's own pixels as the
                    # only boundary: nothing of what lies behind or in front leaks in
                    filled = transforms.fill(lin_c[box].astype(np.float32), core[box])
                    colour_w = colour_w.copy()  # fill(k) is shared with the layer before
                    colour_w[more[win]] = filled[more[box]]  # both row-major: the same order
            cover_w = np.ones(hw, dtype)
            if mine_w.any():
                behind_w = (background[crop][win] if background is not None and k == last - 1
                            else fill(k + 1))
                cover_w[mine_w] = split_coverage(lin_w[mine_w], pure[win][mine_w],
                                                 behind_w[mine_w])
            m = ext_w * cover_w
            plane = planes[i]
            np.multiply(colour_w, m[..., None], out=plane[..., :ch])
            plane[..., ch] = m
            if mine_w.any():
                # premultiplied: what the pixel holds beyond the light behind it, so the
                # composite at the anchor time is the image itself
                plane[..., :ch][mine_w] = ((lin_w[mine_w] - (1.0 - cover_w[mine_w][:, None])
                                            * behind_w[mine_w]) * ext_w[mine_w][:, None])
            found = reach_of(i) if reaches is None else reaches[i].result()
            if rigid[i] is not None:
                dist_at = found
                d_at = np.broadcast_to(rigid[i].astype(np.float32),
                                       (at[0].size, rigid[i].size))
                # read at the region's pixels only; writing all is cheaper
                flows[i] = rigid[i][:2]
                if bends is not None:
                    bends[i] = rigid[i][2:]
            else:
                dist, nearest = found
                dist_at = _at(dist, reg_flat)
                moved = _at(vec_w, nearest)
                flows[i] = moved[..., :2]
                if bends is not None:
                    bends[i] = moved[..., 2:]
                d_at = _at(moved, reg_flat)
                warped[i] = True
            farthest = np.hypot(d_at[:, 0], d_at[:, 1]) * span
            if curvature is not None:
                farthest = farthest + np.hypot(d_at[:, 2], d_at[:, 3]) * (span * span)
            # a bilinear footprint reaches sqrt(2) px
            present[i].reshape(-1)[reg_flat] = dist_at <= farthest + 1.5
    kept = len(shapes)
    return Layers(origin=(int(r0 + win[0].start), int(c0 + win[1].start)),
                  planes=planes[:kept], vectors=flows[:kept], flow=own[win],
                  linear=lin_w, region=reg, present=present[:kept], warped=warped[:kept],
                  curvature=None if bends is None else bends[:kept])
