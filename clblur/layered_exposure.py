"""Layered exposure: occlusion-correct motion blur, ordered by depth, layer IDs or speed.

Why: the plain gather (``clblur.reference.integrate``) integrates each output pixel along its
own vector, so a static background next to a moving object never receives the object's light
and the object's streak stops at its silhouette.  A camera records, at every instant of the
shutter, the *nearest* surface covering each pixel.  This module integrates exactly that, in
the linear domain, for scenes made of layers that each move along their own vectors.

Conventions
-----------
* Ordering signal, H x W: a float **depth** (smaller = nearer), integer **layer IDs** (smaller =
  nearer), **speed** (``depth="speed"``: faster = nearer, the default of
  ``clblur video --layers``) or **departure** (``depth="departure"``: what moves against the
  dominant motion is nearer, a float depth, ``clblur.layering.departure_order``).  Each
  distinct integer ID is its own layer.  A float depth is
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
  ``SPREAD_PX`` in x or y; within such tiles, only pixels near a motion edge or inside a
  turning or stretching layer (:func:`region_mask`).  Elsewhere every surface that can reach a
  pixel moves alike, nothing is revealed or hidden, and the result is the plain gather, bit
  for bit.  Pieces of the region far apart (no ``TILE`` tile of one within about
  ``2 crop_margin(R)`` of a tile of another) are layered apart, each on its own crop, its
  surfaces cut and ordered there (:func:`region_parts`).
* Each layer ``k`` is a premultiplied image ``P_k = (M_k L, M_k)`` (linear light ``L``, 0/1
  coverage ``M_k``) with a vector field ``D_k``: a pixel's own vector on the layer, and the
  vector of the nearest layer pixel elsewhere (a layer moves locally as one piece).  At shutter
  sample ``j`` pixel ``p`` reads each layer at ``q = p - D_k(p) (s_j - a)`` (bilinear, clamp
  to edge; the positions and sample counts of ``clblur.motion``, with ``N(p) = ceil(max_k
  |D_k(p)|) + 1`` by default) and composites front to back, ``E_j = sum_k T_k C_k``,
  ``T_{k+1} = T_k (1 - W_k)`` with ``(C_k, W_k)`` the sampled ``P_k``.  For a layer in rigid
  translation, sampling ``P_k`` along ``D_k`` equals splatting (scattering) the layer's pixels
  along their motion with bilinear weights, so a foreground's light lands on what lies behind
  it with the right coverage at every sample.  Light no layer covers (``T`` left over) is read
  from the image along ``p``'s own vector (the gather).
* **Inverse motion.**  A layer whose vectors vary (it turns, scales or bends: ``warped``) is
  read where the layer point that is at ``p`` at that sample was at the anchor time, the
  solution of ``q = p - D_k(q) (s_j - a)``: ``INVERSE_STEPS`` fixed-point steps (the count
  for estimated flow; ``Layers.inverse_steps`` overrides it, ``clblur.render_layers``) from the
  rigid guess, ``D_k`` read bilinearly (``clblur.reference.lerp_at``, exact where it does not
  vary).  ``p - D_k(p) t`` follows ``p``'s own point instead, which for a body that moves
  while it turns is off by about ``turn * |v| * t^2`` (the gather's error inside a spinning
  object).  The steps are safeguarded: where the map does not contract (estimated flow that
  jumps within a layer, ``|t| |grad D_k| > 1``) a step can move the reading position away
  from the solution, so the last iterate is kept only where its step (the residual
  ``|q + D_k(q) t - p|`` of the iterate before it) is the smallest so far; elsewhere the
  iterate with the smallest residual is read.
* **Curved paths** (``Layers.curvature``, from a bent path's two halves: built by
  ``clblur.render_layers`` for a multi-layer render, by :func:`prepare` for one frame,
  ``clblur.video.blur_curved``, whose region :func:`curved_region` also takes the pixels
  whose path bends away from its chord): layer ``k`` moves along ``D_k t + C_k t^2``,
  ``t = (s_j - a)``, read at the solution of ``q = p - D_k(q) t - C_k(q) t^2`` (the same
  fixed-point steps, ``C_k`` read as ``D_k`` is), and a pixel's default sample count takes
  ``|D_k| + |C_k| / 2`` (a bound on the path's length over a unit time span) in place of
  ``|D_k|``.
* **What is behind an object is not in the image.**  Assumption: a hidden pixel of a farther
  layer continues the visible pixels of the layers at or behind it smoothly (its light the
  membrane fill of ``clblur.layer_planes.harmonic_fill``) and moves with the nearest of them
  (its vector, ``scipy.ndimage.distance_transform_edt``), within ``2 R + 2`` pixels of the
  visible part (nothing deeper can be revealed during the shutter).  Pixels hidden under a
  nearer object join layer ``k`` only when that nearest pixel is on layer ``k``.
* **Mixed pixels** (within one pixel of a layer boundary) hold light of both layers.  They
  join the nearer layer with coverage ``a`` fitted to their light, ``I = a F + (1 - a) B``
  (``F`` the nearest unmixed pixel of that layer, ``B`` the reconstruction behind; least
  squares over the channels, the colour-line model of alpha matting, pulled towards 1/2
  where ``F`` and ``B`` are alike), and carry ``I - (1 - a) B`` premultiplied, so the
  composite at the anchor time is the image.  A surface whose every pixel is mixed (at most
  2 px wide) joins the layers in front of it whole: it is no layer.
* Tiling windows (``plan.extent``) are not supported with an ordering: layered exposure needs
  the whole image.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from clblur.errors import InputError
from clblur.halo import reach
from clblur.layer_planes import (
    SPLIT_PRIOR,
    Layers,
    crop_margin,
    distance_to,
    prepare,
    split_coverage,
)
from clblur.layering import (
    DEPTH_TAU,
    GAP_FRACTION,
    MAX_LAYERS,
    depth_components,
    layer_labels,
    order_components,
    speed_order,
)
from clblur.motion import PSF, Field, Uniform, sample_counts, sample_weight
from clblur.request import BlurPlan

__all__ = ["DEPTH_TAU", "GAP_FRACTION", "INVERSE_STEPS", "MAX_LAYERS", "SPLIT_PRIOR",
           "SPREAD_PX", "TILE", "Layers",
           "boundary_mask", "depth_components", "order_components", "region_mask",
           "built_parts", "integrate", "integrator", "layer_labels", "layered_half", "prepare",
           "region_parts",
           "speed_order", "split_coverage", "steps_of", "composite"]

SPREAD_PX = 1.0
TILE = 16
# fixed-point steps of a warped layer's inverse motion (module Conventions): each one
# multiplies the position error by about |t| |grad D_k|, for a layer turning by theta over
# the exposure about theta / 2 at the far ends of a centred shutter (0.23 for 26 degrees)
INVERSE_STEPS = 2


def _flagged_tiles(v: np.ndarray, r: float, tile: int, spread: float) -> np.ndarray:
    """The tile-level mask of :func:`boundary_mask` (``ceil(H / tile) x ceil(W / tile)``),
    for vectors ``v`` of reach ``r``."""
    from scipy.ndimage import maximum_filter, minimum_filter

    h, w = v.shape[:2]
    th, tw = -(-h // tile), -(-w // tile)
    if th * tile != h or tw * tile != w:
        v = np.pad(v, ((0, th * tile - h), (0, tw * tile - w), (0, 0)), mode="edge")
    # rows of a tile first (whole rows at a time: contiguous, hence fast), then its columns
    # on the 1/tile as large result
    rows = v.reshape(th, tile, tw * tile, 2)
    tmax = rows.max(axis=1).reshape(th, tw, tile, 2).max(axis=2)
    tmin = rows.min(axis=1).reshape(th, tw, tile, 2).min(axis=2)
    size = 2 * math.ceil((r + 2.0) / tile) + 1
    nmax = maximum_filter(tmax, size=(size, size, 1), mode="nearest")
    nmin = minimum_filter(tmin, size=(size, size, 1), mode="nearest")
    return ((nmax - nmin) > spread).any(axis=2)


def boundary_mask(v: np.ndarray, anchor: float, tile: int = TILE,
                  spread: float = SPREAD_PX) -> np.ndarray:
    """Pixels whose neighbourhood moves non-uniformly: the ones that need the layered path.

    Per tile the min and max of each vector component; a tile is flagged when, over the tiles
    within ``ceil((R + 2) / tile)`` of it, max minus min exceeds ``spread`` pixels (module
    Conventions).  Returns an H x W bool mask (whole tiles).
    """
    h, w = v.shape[:2]
    flagged = _flagged_tiles(v, reach(v, anchor), tile, spread)
    return np.repeat(np.repeat(flagged, tile, axis=0), tile, axis=1)[:h, :w]


def _inverse_departure(v: np.ndarray, anchor: float, at: tuple[np.ndarray, np.ndarray]
                       ) -> np.ndarray:
    """How far (px, the larger of x and y) the first fixed-point step of the inverse motion
    moves the reading positions of the pixels ``at`` (rows, cols) at the two ends of the
    shutter: ``|t| |D(p - D(p) t) - D(p)|`` for ``t = -a`` and ``1 - a`` (vectors read
    bilinearly, edges repeated).  A measure of the motion itself, so flow noise of a few
    tenths of a pixel stays far below ``SPREAD_PX`` while a body that turns as it moves does
    not."""
    import cv2

    v = np.ascontiguousarray(v, np.float32)
    # by flat index (np.take): fancy indexing of a frame's vectors is several times slower
    own = np.take(v.reshape(-1, 2), np.ravel_multi_index(tuple(at), v.shape[:2]), axis=0)
    n = own.shape[0]
    ys, xs = (a.astype(np.float32) for a in at)
    out = np.zeros(n, np.float32)
    # cv2.remap takes maps narrower than 2^15: the positions as rows of at most 4096
    width = max(min(n, 4096), 1)
    pad = -n % width

    def rows(a: np.ndarray) -> np.ndarray:
        return np.pad(a, (0, pad)).reshape(-1, width)
    for t in (-anchor, 1.0 - anchor):
        if t == 0.0 or not n:
            continue
        mx = rows(xs - own[:, 0] * np.float32(t))
        my = rows(ys - own[:, 1] * np.float32(t))
        there = cv2.remap(v, mx, my, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)[:n]
        step = np.abs(there - own)
        # the larger of x and y (two columns compared, not a reduction over pairs)
        np.maximum(out, abs(t) * np.maximum(step[:, 0], step[:, 1]), out=out)
    return out


def region_mask(v: np.ndarray, anchor: float, tile: int = TILE,
                spread: float = SPREAD_PX, r: float | None = None) -> np.ndarray:
    """The pixels that take the layered path: the flagged tiles of :func:`boundary_mask`,
    narrowed to the pixels within ``R + 2`` of a motion edge (a pixel whose 3 x 3
    neighbourhood's vectors differ by more than ``spread`` in x or y) and the pixels whose
    inverse motion departs from their own vector by more than ``spread`` in x or y (one
    fixed-point step at either end of the shutter, :func:`_inverse_departure`: inside a
    turning or stretching object).  Elsewhere every surface that can reach a pixel moves as
    the pixel does, and the gather is kept.  ``r``: the samples' reach, when it is more than
    ``reach(v, anchor)`` (a curved path, :func:`curved_reach`)."""
    import cv2
    from scipy.ndimage import maximum_filter, minimum_filter

    h, w = v.shape[:2]
    out = np.zeros((h, w), bool)
    r = reach(v, anchor) if r is None else r
    flagged = _flagged_tiles(v, r, tile, spread)
    if not flagged.any():
        return out
    margin = int(math.ceil(r)) + 4
    rows, cols = np.nonzero(flagged.any(axis=1))[0], np.nonzero(flagged.any(axis=0))[0]
    r0, r1 = max(rows[0] * tile - margin, 0), min((rows[-1] + 1) * tile + margin, h)
    c0, c1 = max(cols[0] * tile - margin, 0), min((cols[-1] + 1) * tile + margin, w)
    crop = v[r0:r1, c0:c1]
    edge = np.zeros(crop.shape[:2], bool)
    varies = np.zeros(crop.shape[:2], bool)
    square = np.ones((3, 3), np.uint8)
    for c in range(2):
        comp = np.ascontiguousarray(crop[..., c])
        if comp.dtype in (np.float32, np.float64):
            # OpenCV's 3 x 3 max / min: outside the image it ignores the border, which for
            # a 3 x 3 window is what repeating the edge gives (scipy's "nearest")
            spread_c = cv2.dilate(comp, square) - cv2.erode(comp, square)
        else:
            spread_c = (maximum_filter(comp, size=3, mode="nearest")
                        - minimum_filter(comp, size=3, mode="nearest"))
        edge |= spread_c > spread
        varies |= spread_c > 0
    near = distance_to(edge) <= r + 2.0 if edge.any() else np.zeros(edge.shape, bool)
    # Away from motion edges, only a pixel whose vectors vary around it can read points its
    # own vector does not (a smooth field with a flat 3 x 3 patch is taken as translating)
    at = np.nonzero(varies & ~near)
    warped = np.zeros(edge.shape, bool)
    warped[at] = _inverse_departure(crop, anchor, at) > spread
    tiles = flagged[(np.arange(r0, r1) // tile)[:, None], (np.arange(c0, c1) // tile)]
    out[r0:r1, c0:c1] = (near | warped) & tiles
    return out


def curved_reach(v: np.ndarray, c: np.ndarray, anchor: float) -> float:
    """Farthest a sample of the curved path ``D t + C t^2`` lands from its pixel, ``t`` in
    ``[-a, 1 - a]``: at most ``max (|D| s + |C| s^2)``, ``s = max(a, 1 - a)``."""
    if not v.size:
        return 0.0
    s = max(anchor, 1.0 - anchor)
    far = np.hypot(v[..., 0], v[..., 1], dtype=np.float64) * s
    far += np.hypot(c[..., 0], c[..., 1], dtype=np.float64) * (s * s)
    return float(far.max()) * (1 + 1e-6)


def curved_region(v: np.ndarray, c: np.ndarray, anchor: float,
                  r: float | None = None) -> np.ndarray:
    """The pixels that take the layered path on a curved path: :func:`region_mask` with the
    curved path's reach, and every pixel within that reach (+ 2 px) of a pixel whose path
    bends away from its chord by more than ``SPREAD_PX / 2`` (``|C| s^2``, ``s = max(a,
    1 - a)``): there the straight gather of the chord misses the curve, even where
    everything moves alike (a camera that accelerates).  ``r``: :func:`curved_reach`, where
    the caller has it."""
    s = max(anchor, 1.0 - anchor)
    r = curved_reach(v, c, anchor) if r is None else r
    out = region_mask(v, anchor, r=r)
    bends = np.hypot(c[..., 0], c[..., 1]) * (s * s) > 0.5 * SPREAD_PX
    if bends.any():
        out |= distance_to(bends) <= r + 2.0
    return out


def _where_present(field: np.ndarray, pick: np.ndarray | None, there: np.ndarray,
                   rigid: bool) -> np.ndarray:
    """A layer's field (vectors or curvature, h x w x 2) at the ``pick`` pixels (flat
    indices; None: every pixel) where it is ``there``, n x 2; for a rigid layer, whose field
    is one value wherever it is present, that value once (1 x 2)."""
    flat = field.reshape(-1, 2)
    where = np.flatnonzero(there) if pick is None else pick[there]
    return flat[where[:1]] if rigid else np.take(flat, where, axis=0)


def counts(layers: Layers, samples: int | None,
           at: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Samples per pixel: ``samples``, or ``ceil(max |v|) + 1`` over the pixel's own vector
    and the vectors ``D_k`` of the layers that reach it (``Layers.reach``, else ``present``)
    (int32, h x w; with ``at``, (rows, cols) of the crop, only at those pixels, as a flat
    array)."""
    shape = layers.region.shape if at is None else at[0].shape
    if samples is not None:
        return np.full(shape, samples, np.int32)
    # flat indices of the crop (np.take): fancy or boolean indexing of the large fields
    # was most of this function's time on real flows
    pick = None if at is None else np.ravel_multi_index(tuple(at), layers.region.shape)

    def of(a: np.ndarray) -> np.ndarray:  # a (h x w [x 2]) at the picked pixels
        return a.reshape(shape + a.shape[2:]) if pick is None else \
            np.take(a.reshape((-1,) + a.shape[2:]), pick, axis=0)
    flow = of(layers.flow)
    n = sample_counts(flow[..., 0], flow[..., 1])
    reach = layers.present if layers.reach is None else layers.reach
    for k, (d, there) in enumerate(zip(layers.vectors, reach, strict=True)):
        # a layer that can reach the pixel: its D_k there (one layer at a time, only where
        # it is present: far fewer pixels than the crop times the layers)
        there = of(there)
        if there.any():
            rigid = not layers.warped[k]
            dk = _where_present(d, pick, there, rigid)
            if layers.curvature is None:
                n[there] = np.maximum(n[there], sample_counts(dk[:, 0], dk[:, 1]))
            else:  # a curved path: |D_k| + |C_k| / 2 bounds its length (module Conventions)
                ck = _where_present(layers.curvature[k], pick, there, rigid).astype(np.float64)
                length = np.hypot(dk[:, 0], dk[:, 1]) + 0.5 * np.hypot(ck[:, 0], ck[:, 1])
                n[there] = np.maximum(n[there], sample_counts(length, 0.0 * length))
    return n


def steps_of(layers: Layers) -> int:
    """The fixed-point steps of the inverse motion of ``layers``' warped layers."""
    return INVERSE_STEPS if layers.inverse_steps is None else int(layers.inverse_steps)


def _inverse_motion(d: np.ndarray, c: np.ndarray | None, x: np.ndarray, y: np.ndarray,
                    xx: np.ndarray, yy: np.ndarray, num: np.ndarray, den: np.ndarray,
                    tt: np.ndarray, origin: tuple[int, int], full_shape: tuple[int, int],
                    steps: int = INVERSE_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """Where a warped layer is read (module Conventions, inverse motion): ``steps``
    fixed-point steps ``q <- p - D_k(q) t (- C_k(q) t^2)`` from the guess ``(x, y)``,
    safeguarded: the last iterate where its step was the smallest so far, else the iterate
    whose step (its residual ``|q + D_k(q) t - p|``, the larger of x and y) was smallest."""
    from clblur.reference import lerp_at

    best_x, best_y = x, y
    best_r = np.full(np.shape(x), np.inf)
    r = best_r
    for _ in range(steps):
        dq = lerp_at(d, x, y, origin, full_shape)
        nx = xx - (dq[..., 0] * num) / den
        ny = yy - (dq[..., 1] * num) / den
        if c is not None:
            cq = lerp_at(c, x, y, origin, full_shape)
            nx = nx - cq[..., 0] * tt
            ny = ny - cq[..., 1] * tt
        r = np.maximum(abs(nx - x), abs(ny - y))  # the residual of the iterate (x, y)
        better = r < best_r
        best_x, best_y = np.where(better, x, best_x), np.where(better, y, best_y)
        best_r = np.where(better, r, best_r)
        x, y = nx, ny
    last = r <= best_r  # still contracting at the last step: take it
    return np.where(last, x, best_x), np.where(last, y, best_y)


def composite(layers: Layers, anchor: float, samples: int | None, weights: np.ndarray | None,
              full_shape: tuple[int, int], ends: bool = False) -> np.ndarray:
    """Front-to-back composite of every shutter sample, float64 (the numpy reference).

    ``ends``: per-pixel counts with the ``continuous`` exposure (``BlurPlan.ends``): each
    pixel's first and last samples take half weight.  Returns the exposure of every crop
    pixel (h x w x C); only ``layers.region`` is used.
    """
    from clblur.reference import bilinear_at

    h, w = layers.region.shape
    r0, c0 = layers.origin
    yy, xx = np.mgrid[r0:r0 + h, c0:c0 + w].astype(np.float64)
    n = counts(layers, samples).astype(np.float64)
    den = np.maximum(n - 1, 1)
    channels = layers.linear.shape[2]
    acc = np.zeros((h, w, channels))
    vectors = [d.astype(np.float64) for d in layers.vectors]  # once, not per sample
    steps = steps_of(layers)
    curves = [None] * len(vectors) if layers.curvature is None else \
        [c.astype(np.float64) for c in layers.curvature]
    for j in range(int(n.max())):
        active = j < n
        num = j - anchor * (n - 1)
        tt = (num * num) / (den * den)  # t^2 of a curved path
        left = np.ones((h, w, 1))
        e = np.zeros((h, w, channels))
        for plane, d, c, there, warped in zip(layers.planes, vectors, curves, layers.present,
                                              layers.warped, strict=True):
            x = xx - (d[..., 0] * num) / den
            y = yy - (d[..., 1] * num) / den
            if c is not None:
                x = x - c[..., 0] * tt
                y = y - c[..., 1] * tt
            if warped:
                x, y = _inverse_motion(d, c, x, y, xx, yy, num, den, tt, layers.origin,
                                       full_shape, steps)
            s = bilinear_at(plane, x, y, layers.origin, full_shape) * there[..., None]
            e += left * s[..., :channels]
            left = left * (1.0 - s[..., channels:])
        v = layers.flow.astype(np.float64)
        x = xx - (v[..., 0] * num) / den
        y = yy - (v[..., 1] * num) / den
        e += left * bilinear_at(layers.linear, x, y, layers.origin, full_shape)
        wj = weights[j] if weights is not None else sample_weight(j, n, ends)
        acc += np.where(active, wj, 0.0)[..., None] * e
    return acc


def plan_order(plan: BlurPlan) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(vectors, ordering, layering rule) when ``plan`` can occlude anything, else None (the
    gather is exact)."""
    if plan.depth is None or isinstance(plan.motion, (Uniform, PSF)):
        return None  # one displacement for every pixel: nothing moves relative to anything
    if plan.extent is not None:
        raise InputError("a depth ordering needs the whole image; it cannot run on tiles")
    assert isinstance(plan.motion, Field)
    return plan.motion.flow, plan.depth, "speed" if plan.speed_order else "depth"


def integrate(lin: np.ndarray, plan: BlurPlan, curvature: np.ndarray | None = None
              ) -> np.ndarray:
    """Layered exposure on the numpy reference (a ``clblur.pipeline`` integrator).

    ``curvature``: H x W x 2, the quadratic term ``C`` of a curved path whose chord is the
    plan's flow (module Conventions, curved paths; :func:`integrator`)."""
    from clblur.reference import integrate as gather

    acc = gather(lin, plan)
    ordered = plan_order(plan)
    if ordered is None:
        return acc
    v, order, rule = ordered
    region, r = region_and_reach(v, plan.anchor, curvature)
    if not region.any():
        return acc
    for layers in built_parts(lin, v, order, plan.anchor, region, r,
                              background_linear(plan), rule=rule, curvature=curvature):
        out = composite(layers, plan.anchor, plan.samples, plan.weights, plan.full_shape,
                        plan.ends)
        h, w = layers.region.shape
        r0, c0 = layers.origin
        view = acc[r0:r0 + h, c0:c0 + w]
        view[layers.region] = out[layers.region]
    return acc


def built_parts(lin, v: np.ndarray, order: np.ndarray, anchor: float, region: np.ndarray,
                r: float, background: np.ndarray | None, **options) -> Iterator[Layers]:
    """The layers of each part of ``region`` (:func:`region_parts`), built one after the
    other by :func:`prepare` (``options``: its keywords); a part where the ordering gives one
    surface on a straight path yields nothing (the gather's result stands there)."""
    for part in region_parts(region, r):
        layers = prepare(lin, v, order, anchor, part, background, r=r, **options)
        if layers is not None:
            yield layers


def region_parts(region: np.ndarray, r: float, tile: int = TILE) -> list[np.ndarray]:
    """``region`` (H x W bool) cut into parts whose layers are built apart (H x W bool each,
    in raster order); ``[region]`` itself when it is one part.

    Why: :func:`prepare` builds the layers on the bounding box of its region grown by
    ``crop_margin(r)``, so two objects in opposite corners made it build them on the whole
    frame: time and memory grew with the frame, not with what moves.  A part is a group of
    the region's ``tile`` x ``tile`` tiles that lie within ``2 ceil(crop_margin(r) / tile)``
    tiles of one another, in chains (8-connected after that dilation of the tile grid), so
    pieces near enough for their crops to overlap are built together, once.  Every sample of
    a part's pixel, and everything that builds the layers it reads, lies within its own crop,
    so a part's result is the one its crop gives (its surfaces cut and ordered there),
    whatever the other parts are; two parts' crops may still overlap where one part's box
    wraps around another, which costs time only."""
    from scipy.ndimage import find_objects, label, maximum_filter

    h, w = region.shape
    th, tw = -(-h // tile), -(-w // tile)
    padded = np.zeros((th * tile, tw * tile), bool)
    padded[:h, :w] = region
    tiles = padded.reshape(th, tile, tw, tile).any(axis=(1, 3))
    grow = math.ceil(crop_margin(r) / tile)
    groups, n = label(maximum_filter(tiles, size=2 * grow + 1), structure=np.ones((3, 3), bool))
    if n <= 1:
        return [region]
    groups[~tiles] = 0
    parts = []
    for k, box in enumerate(find_objects(groups), start=1):
        if box is None:
            continue
        rows = slice(box[0].start * tile, min(box[0].stop * tile, h))
        cols = slice(box[1].start * tile, min(box[1].stop * tile, w))
        on = np.repeat(np.repeat(groups[box] == k, tile, axis=0), tile, axis=1)
        part = np.zeros((h, w), bool)
        part[rows, cols] = on[:rows.stop - rows.start, :cols.stop - cols.start] & region[rows, cols]
        parts.append(part)
    return parts


def region_and_reach(v: np.ndarray, anchor: float, curvature: np.ndarray | None = None
                     ) -> tuple[np.ndarray, float]:
    """The layered region (:func:`region_mask`, or :func:`curved_region` on a curved path) and
    the samples' reach, on the host."""
    if curvature is None:
        return region_mask(v, anchor), reach(v, anchor)
    r = curved_reach(v, curvature, anchor)
    return curved_region(v, curvature, anchor, r), r


def background_linear(plan: BlurPlan) -> np.ndarray | None:
    """The clean plate of ``plan`` linearised as its image is (host, float64), or None."""
    if plan.background is None:
        return None
    from dataclasses import replace

    from clblur.reference import linearise

    return linearise(replace(plan, image=plan.background, background=None))


def integrator(backend: str, device: str | None = None, curvature: np.ndarray | None = None):
    """The layered integrator of a resolved backend (``"numpy"`` or ``"opencl"``).

    ``curvature``: H x W x 2, the quadratic term ``C`` of a curved path ``D t + C t^2`` whose
    chord ``D`` is the plan's flow (module Conventions, curved paths): the layers are read
    along the curve wherever it bends (:func:`curved_region`), and a plan without an
    ordering of its own should give one layer (IDs all 0) to be blurred along the curve."""
    if backend == "numpy":
        if curvature is None:
            return integrate
        return lambda lin, plan: integrate(lin, plan, curvature)
    from clblur.opencl.layered import integrator as opencl_integrator

    return opencl_integrator(device, curvature=curvature)


def layered_half(lin: np.ndarray, v: np.ndarray, anchor: str, *, depth=None,
                 samples: int | None = None, backend: str = "auto",
                 device: str | None = None, exposure: str = "frames") -> np.ndarray:
    """Linear exposure (H x W x C, the dtype of ``lin``) of one straight shutter segment with
    vectors ``v``, ordered by ``depth`` (default: speed).  ``lin`` is linear light and is
    blurred with the identity response (used by ``clblur.video`` for each shutter half)."""
    from clblur.blur import blur

    order = "speed" if depth is None else depth
    return blur(lin, v, "linear", anchor=anchor, samples=samples, backend=backend,
                device=device, depth=order, exposure=exposure)
