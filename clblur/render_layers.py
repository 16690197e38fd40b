"""Multi-layer renders: every layer's own image, coverage and vectors, blurred together.

Why: from one sharp frame, what a moving object uncovers and the hidden part of a far object
that a near one reveals during the shutter are not in the image (``clblur.layered_exposure``
reconstructs them, which is a guess).  A renderer or a compositing tree can hand over each
object as its own layer (Blender view layers or holdouts, Nuke's per-object renders, the
parts of a multi-part EXR): then nothing is hidden, and the layered composite of every
shutter sample is what the camera records, up to the motion model.

Conventions
-----------
* ``layers`` are listed **front to back**.  Each is ``(image, motion)``: ``image`` is
  H x W x (C + 1), colour then coverage, in the alpha convention of ``clblur.blur(...,
  alpha=True)`` (straight alpha for integer images, premultiplied for float images; coverage is
  never passed through the response); ``motion`` is the layer's own H x W x 2 vectors (clblur's
  convention, ``clblur.motion``; read only where the layer covers at least half the pixel,
  as a point-sampled vector pass sees it: a layer moves locally as one piece, so elsewhere
  it takes the vector of its nearest such pixel), or a
  pair ``(first, second)`` for a bent path (``first`` ends at the frame time, ``second``
  starts there: ``clblur.vectors.blur_bent``'s convention, what Blender's Vector pass holds as
  previous and next), followed as two straight halves or, with ``curved=True``, as the
  parabola through its three points (``clblur.layered_exposure``, curved paths).  All
  layers have the same shape, dtype and form of motion.
* Every shutter sample composites the layers front to back in linear light
  (``clblur.layered_exposure.composite``: inverse motion for layers whose vectors vary, the
  same sample positions and counts); coverage is composited as one more channel, so the result
  is premultiplied colour and coverage ``1 - prod(1 - W_k)`` and goes out in the input's alpha
  convention.  Nothing is reconstructed: light that no layer holds is not there (an opaque
  rearmost layer, a background plate, leaves none).
* Culling changes no output code: a rigid layer is visited only where its one path can bring
  its coverage (:func:`swept`), and a pixel that one still layer alone reaches is that
  layer's plane (:func:`still_alone`), never composited.  Sample counts keep the disc of
  each layer's longest vector around its coverage (``Layers.reach``, sample counts below).
* Sample counts: ``ceil`` of the longest vector among the layers whose coverage lies within
  that vector's reach of the pixel, plus one.  Counting only the layers whose path the
  pixel meets samples a slow layer beside a fast one's streak at its own one sample per
  pixel of path, and lost 0.5 - 2.0 dB on the crossings of ``docs/studies/occlusion.md``
  with equal weights: the extra samples were shrinking their first-order error at the
  shutter's ends.  With ``exposure="continuous"`` (the trapezoid rule) that error is gone
  and the two counts score within 0.02 dB on the same scenes, so the continuous exposure
  counts only the layers whose path meets the pixel (fewer samples, the same result).
* A renderer's vectors are exact, so a warped layer's inverse motion is solved to
  convergence: ``RENDER_INVERSE_STEPS`` safeguarded fixed-point steps, where estimated flow
  takes ``clblur.layered_exposure.INVERSE_STEPS`` (whose fixed point an estimate's errors
  move: on the GoPro frames a third step loses 0.1 - 0.25 dB, ``bench/results_occlusion.md``).
  On the study's turning scenes 3, 4, 6 and 8 steps agree within 0.1 dB
  (``docs/studies/occlusion.md``); 4 is where they stop moving.
* ``overscan``: the layers extend ``overscan`` pixels beyond the output on every side (an EXR
  data window larger than its display window), so what enters the frame during the shutter
  is known; the output is the inner H - 2 m x W - 2 m.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from clblur.errors import InputError
from clblur.layer_planes import Layers, bounding_box
from clblur.motion import curved_terms
from clblur.request import BlurPlan, make_plan, retime

__all__ = ["RENDER_INVERSE_STEPS", "blur_layers", "layers_for", "path_offsets", "still_alone",
           "swept"]

RENDER_INVERSE_STEPS = 4  # module Conventions: a renderer's exact vectors, solved to convergence


def _motion_form(motion, index: int):
    """``("straight", motion)`` or ``("bent", (first, second))`` for one layer's motion: a
    pair of arrays is a bent path, anything else (a field, or ``(dx, dy)``) straight."""
    if isinstance(motion, (tuple, list)) and any(np.ndim(m) > 0 for m in motion):
        if len(motion) != 2:
            raise InputError(f"layer {index}: a bent path is a pair (first, second), got "
                             f"{len(motion)} arrays")
        return "bent", tuple(motion)
    return "straight", motion


def _linear_layer(plan: BlurPlan) -> np.ndarray:
    """``clblur.reference.linearise(plan)``, evaluated on the box that holds the layer's
    coverage for an integer image: outside it the straight alpha is 0, so the premultiplied
    light and the coverage are 0 there.  An object's layer covers a small part of the frame;
    linearising all of it was a sixth of a call (``bench/results_render_layers.md``).  A float
    image is premultiplied and may hold light where it has no coverage: all of it."""
    from dataclasses import replace

    from clblur.reference import linearise

    if plan.dtype.kind != "u":
        return linearise(plan)
    out = np.zeros(plan.image.shape, np.float64)
    box = bounding_box(plan.image[..., -1])
    if box is not None:
        out[box] = linearise(replace(plan, image=plan.image[box]))
    return out


def _field_of(plan: BlurPlan) -> np.ndarray:
    """The plan's motion as an H x W x 2 field (a uniform displacement broadcast)."""
    from clblur.motion import Field, Uniform

    if isinstance(plan.motion, Field):
        return plan.motion.flow
    if isinstance(plan.motion, Uniform):
        return np.full(plan.image.shape[:2] + (2,), (plan.motion.dx, plan.motion.dy),
                       np.float32)
    raise InputError("a layer's motion must be vectors (H x W x 2) or (dx, dy), not a PSF")


def path_offsets(d: np.ndarray, anchor: float, c: np.ndarray | None = None) -> np.ndarray:
    """Whole-pixel offsets ``round(D t + C t^2)``, ``t`` in [-anchor, 1 - anchor], at steps
    of at most half a pixel along the path (unique, m x 2 as (dx, dy)).

    Every point of the continuous path lies within half a pixel (per axis) of an offset's
    unrounded point, so within one pixel of the offset."""
    d = np.asarray(d, np.float64)
    c = np.zeros(2) if c is None else np.asarray(c, np.float64)
    lo, hi = -anchor, 1.0 - anchor
    # |dP/dt| <= |D| + 2 |C| max|t|: the per-axis speed bounds the step between grid points
    speed = np.abs(d) + 2.0 * np.abs(c) * max(abs(lo), abs(hi))
    steps = int(np.ceil(2.0 * float(speed.max()) * (hi - lo))) + 1
    t = np.linspace(lo, hi, steps + 1)[:, None]
    return np.unique(np.rint(d * t + c * t * t).astype(np.int64), axis=0)


def swept(covered: np.ndarray, d: np.ndarray, anchor: float,
          c: np.ndarray | None = None) -> np.ndarray:
    """The pixels ``p`` at which a rigid layer's samples can read its coverage: some sample
    position ``q = p - D t - C t^2`` has a bilinear corner (clamped to the image) on a
    ``covered`` pixel.  Conservative, never short.

    Why: the composite visits a layer only where this holds, and takes as many samples as
    the longest vector among the layers that reach a pixel.  The disc of the vector's length
    around the coverage (what a warped layer needs) holds, for a long straight motion, about
    twice the pixels of the streak itself; the static background beside a streak then went
    through the composite at the fast layer's sample count.

    How: a bilinear corner lies within Chebyshev distance < 1 of ``q``; with ``q`` within one
    pixel of ``p - o`` for a whole-pixel offset ``o`` (:func:`path_offsets`), ``p - o`` is
    within Chebyshev distance < 2 of a covered pixel, i.e. in its 3 x 3 dilation, read with
    the index clamped to the image as the sampler clamps positions.
    """
    import cv2

    h, w = covered.shape
    near = cv2.dilate(covered.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    offsets = path_offsets(d, anchor, c)
    rows, cols = bounding_box(near)
    # the window p can lie in: the dilation's box moved by the offsets, out to the image's
    # edge on a side where the box touches it (a clamped read lands there from beyond)
    (oy0, ox0), (oy1, ox1) = offsets[:, ::-1].min(axis=0), offsets[:, ::-1].max(axis=0)
    r0 = 0 if rows.start == 0 else max(rows.start + oy0, 0)
    r1 = h if rows.stop == h else min(rows.stop + oy1, h)
    c0 = 0 if cols.start == 0 else max(cols.start + ox0, 0)
    c1 = w if cols.stop == w else min(cols.stop + ox1, w)
    out = np.zeros((h, w), bool)
    if r0 >= r1 or c0 >= c1:
        return out
    rr, cc = np.arange(r0, r1), np.arange(c0, c1)
    window = out[r0:r1, c0:c1]
    for ox, oy in offsets:
        window |= near[np.clip(rr - oy, 0, h - 1)][:, np.clip(cc - ox, 0, w - 1)]
    return out


def _within(covered: np.ndarray, radius) -> np.ndarray:
    """``distance_to(covered) <= radius`` (``radius`` one value or H x W), computed on the box
    that it can hold: the box of ``covered`` grown by the largest radius.  Every covered pixel
    lies in that box, so the distances in it are the whole image's; beyond it they exceed the
    radius.  An object's layer is small; the whole frame's transform was most of the cost."""
    from clblur.layer_planes import distance_to

    radius = np.asarray(radius)
    out = np.zeros(covered.shape, bool)
    box = bounding_box(covered, int(np.ceil(radius.max())) + 1)
    if box is not None:
        out[box] = distance_to(covered[box]) <= (radius[box] if radius.size > 1 else radius)
    return out


def layers_for(linear: Sequence[np.ndarray], flows: Sequence[np.ndarray], anchor: float,
               region: np.ndarray, curvature: Sequence[np.ndarray] | None = None,
               dtype=np.float64, reach_counts: bool = True) -> Layers:
    """The :class:`clblur.layer_planes.Layers` of a multi-layer render (module Conventions).

    ``linear``: per layer, H x W x (C + 1) premultiplied linear colour and coverage (float64);
    ``flows``: per layer, H x W x 2 vectors; ``region``: the pixels to composite;
    ``curvature``: per layer, the quadratic term of a curved path, or None; ``dtype``: of
    the planes (float32 for the device, which composites in float32).  Each plane carries its
    coverage twice, as light (so the composite sums it) and as coverage.  ``reach_counts``:
    sample counts from the disc of each layer's reach (``Layers.reach``, what equal weights
    need), else from the layers whose path meets the pixel (module Conventions, sample
    counts).
    """
    from scipy.ndimage import distance_transform_edt

    h, w, cp = linear[0].shape
    k = len(linear)
    planes = np.zeros((k, h, w, cp + 1), dtype)
    vectors = np.zeros((k, h, w, 2), np.float32)
    present = np.zeros((k, h, w), bool)
    reach = np.zeros((k, h, w), bool)
    warped = np.zeros(k, bool)
    curves = None if curvature is None else np.zeros((k, h, w, 2), np.float32)
    span = max(anchor, 1.0 - anchor)
    for i, (lin, flow) in enumerate(zip(linear, flows, strict=True)):
        held = bounding_box(lin)  # an object's layer holds light in a small box
        if held is None:
            continue  # an empty layer: nothing to read
        planes[i][held + (slice(0, cp),)] = lin[held]
        cover = lin[held + (-1,)]
        planes[i][held + (cp,)] = cover
        if not (cover > 0).any():
            continue  # no coverage: nothing hides what is behind it, nothing to read
        covered = np.zeros((h, w), bool)
        covered[held] = cover > 0
        # a vector pass is point-sampled: trust a pixel's vector where the layer covers at
        # least half of it (an anti-aliased rim pixel may hold the vector of what is behind)
        solid = cover >= 0.5
        if not solid.any():
            solid = cover > 0
        fields = [flow] if curvature is None else [flow, curvature[i]]
        owns = [f[held][solid] for f in fields]
        if all((own == own[0]).all() for own in owns):  # a rigid translation
            vectors[i] = owns[0][0]
            if curves is not None:
                curves[i] = owns[1][0]
        else:
            outside = np.ones((h, w), bool)
            outside[held] = ~solid
            nearest = distance_transform_edt(outside, return_indices=True,
                                             return_distances=False)
            vectors[i] = flow[nearest[0], nearest[1]]
            if curves is not None:
                curves[i] = curvature[i][nearest[0], nearest[1]]
            warped[i] = True
        # everything within the farthest reach of its vectors (a bilinear footprint reaches
        # sqrt(2) px): where a warped layer's inverse motion can read it, and where any
        # layer's vectors set the sample count (module Conventions, sample counts)
        pick = (Ellipsis,) if warped[i] else (slice(0, 1), slice(0, 1))
        d = vectors[i][pick]
        farthest = np.hypot(d[..., 0], d[..., 1]) * span
        if curves is not None:
            c = curves[i][pick]
            farthest += np.hypot(c[..., 0], c[..., 1]) * span * span
        reach[i] = _within(covered, farthest + 1.5) & region
        # a rigid layer's one path reaches far fewer pixels than that disc
        present[i] = reach[i] if warped[i] else swept(
            covered, vectors[i][0, 0], anchor,
            None if curves is None else curves[i][0, 0]) & region
    return Layers(origin=(0, 0), planes=planes, vectors=vectors,
                  flow=np.zeros((h, w, 2), np.float32), linear=np.zeros((h, w, cp), dtype),
                  region=region, present=present, warped=warped, curvature=curves,
                  inverse_steps=RENDER_INVERSE_STEPS, reach=reach if reach_counts else None)


def still_alone(layers: Layers) -> tuple[np.ndarray, np.ndarray]:
    """The region's pixels that exactly one layer can reach, a layer that does not move there:
    (mask, H x W; the index of that layer, H x W, meaningful under the mask).

    Why: at such a pixel every shutter sample reads that one layer at the pixel itself
    (``present`` is conservative: the other layers hold zero coverage wherever its samples
    land), so the exposure is the layer's plane there: exactly what the composite gives with
    one sample, and within the last bit of its mean of equal samples where a moving layer's
    reach sets a larger count (``Layers.reach``).  A static background with a few moving
    objects is mostly such pixels; they skip the compositing kernel (the culling asked of
    the occlusion path, issue 11).  A moving layer alone at a pixel still goes through the
    composite: its samples spread.
    """
    k = len(layers.planes)
    still = np.zeros(k, bool)
    for i in range(k):
        if layers.warped[i]:
            continue  # its vectors vary: the inverse motion may read other pixels
        # a rigid layer's field is one value wherever it is present
        moved = layers.vectors[i].any() or (layers.curvature is not None
                                            and layers.curvature[i].any())
        still[i] = not moved
    count = layers.present.sum(axis=0, dtype=np.uint8)
    which = np.argmax(layers.present, axis=0)
    return (count == 1) & still[which] & layers.region, which


def _layers_under(alone: np.ndarray, which: np.ndarray) -> np.ndarray:
    """The layers that ``which`` names at some ``alone`` pixel."""
    return np.flatnonzero(np.bincount(which[alone], minlength=1))


def _composite(layers: Layers, plan: BlurPlan, backend: str,
               device: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exposure of the region's pixels (H x W x (C + 1), zero elsewhere, float64) and
    :func:`still_alone`'s mask and layer index.

    Pixels that one still layer alone reaches take its plane; the others go through the
    compositing kernel."""
    from dataclasses import replace

    from clblur import layered_exposure

    full = layers.region.shape
    cp = layers.planes.shape[-1] - 1
    alone, which = still_alone(layers)
    out = np.zeros(full + (cp,))
    for k in _layers_under(alone, which):
        np.copyto(out, layers.planes[k][..., :cp], where=(alone & (which == k))[..., None])
    mixed = layers.region & ~alone
    box = bounding_box(mixed, _farthest_read(layers, plan.anchor))
    if box is None:
        return out, alone, which
    # the crop that every sample of the mixed pixels reads: the device reads (or, with its
    # own memory, receives) that much of the planes and fields, not the frame's
    every = (slice(None),) + box  # every layer, the box

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[every]

    crop = replace(layers, origin=(box[0].start, box[1].start), planes=cut(layers.planes),
                   vectors=cut(layers.vectors), flow=layers.flow[box],
                   linear=layers.linear[box], region=mixed[box],
                   present=cut(layers.present) & mixed[box], reach=cut(layers.reach),
                   curvature=cut(layers.curvature))
    if backend == "numpy":
        values = layered_exposure.composite(crop, plan.anchor, plan.samples, plan.weights,
                                            full, plan.ends)
        out[box][crop.region] = values[crop.region]
    else:
        from clblur.opencl.layered import composite

        out[box][crop.region] = composite(crop, plan.anchor, plan.samples, plan.weights, full,
                                          device, ends=plan.ends)
    return out, alone, which


def _farthest_read(layers: Layers, anchor: float) -> int:
    """Pixels beyond which no sample of a pixel reads (whole pixels): the longest path of
    any layer from the anchor, ``|D| t + |C| t^2`` at the farther end of the shutter (an
    inverse motion's iterates read positions ``p - D(q) t - C(q) t^2`` as well), plus the
    bilinear footprint and a pixel of margin."""
    span = max(anchor, 1.0 - anchor)
    d = layers.vectors.reshape(-1, 2).astype(np.float64)
    far = float(np.hypot(d[:, 0], d[:, 1]).max(initial=0.0)) * span
    if layers.curvature is not None:
        c = layers.curvature.reshape(-1, 2).astype(np.float64)
        far += float(np.hypot(c[:, 0], c[:, 1]).max(initial=0.0)) * span * span
    return int(np.ceil(far)) + 2


def _finish(acc: np.ndarray, plan: BlurPlan, images: Sequence[np.ndarray], alone: np.ndarray,
            which: np.ndarray, planes) -> np.ndarray:
    """``clblur.reference.finish(acc, plan)``, with the opaque pixels that one still layer
    alone reaches (``alone``, layer ``which``) of an integer image looked up per code.

    Their exposure is the layer's linearised code as the planes hold it (``planes``, the
    dtype), coverage 1, whatever the pixel: so their output is a function of the code, one
    table per channel, evaluated by ``finish`` itself on every code.  The response and the
    rounding of every pixel of the frame were a sixth of a call.  Other pixels, and float
    images (whose values are not a few codes), go through ``finish``."""
    from clblur.pixels import imax, linearisation_table
    from clblur.reference import finish

    if plan.dtype.kind != "u" or not alone.any():
        return finish(acc, plan)
    top = int(imax(plan.dtype))
    colour = plan.colour_channels
    exposure = np.ones((top + 1, 1, colour + 1))
    for c in range(colour):
        table = linearisation_table(plan.responses[c], plan.dtype, plan.saturation)
        exposure[:, 0, c] = table.astype(planes).astype(np.float64)
    lut = finish(exposure, plan)[:, 0]
    out = np.empty(acc.shape, plan.dtype)
    looked_up = np.zeros(alone.shape, bool)
    for k in _layers_under(alone, which):
        image = images[k]
        mask = alone & (which == k) & (image[..., -1] == top)
        for c in range(colour + 1):
            np.copyto(out[..., c], lut[image[..., c], c], where=mask)
        looked_up |= mask
    rest = ~looked_up
    out[rest] = finish(acc[rest][:, None], plan)[:, 0]
    return out


def _with_coverage(image) -> np.ndarray:
    """A layer's image with its coverage last: grey (H x W, or one channel) and RGB have
    none and cover every pixel (full scale appended); 2 and 4 channels carry their own."""
    from clblur.pixels import imax

    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[2] not in (1, 3):
        return image
    full = imax(image.dtype) if image.dtype.kind == "u" else 1.0
    return np.concatenate([image, np.full(image.shape[:2] + (1,), full, image.dtype)], axis=2)


def blur_layers(layers: Sequence[tuple], response="exp", *, anchor: str = "center",
                samples: int | None = None, weights=None, overscan: int = 0,
                curved: bool = False, backend: str = "auto", saturation: float = 1.0,
                device: str | None = None, exposure: str = "frames") -> np.ndarray:
    """Motion blur of a multi-layer render: each layer moves along its own vectors and the
    layers occlude each other front to back at every shutter sample, in linear light.

    Parameters
    ----------
    layers : front to back, ``(image, motion)`` per layer (module Conventions): ``image``
        H x W x (C + 1) colour and coverage (straight alpha for integer dtypes, premultiplied
        for float): grey + alpha (2 channels) or RGBA (4); a grey (H x W or 1 channel) or RGB
        layer has no alpha and is opaque (full coverage appended).  ``motion`` H x W x 2
        vectors or a bent path ``(first, second)``.
    response, samples, weights, saturation, backend, device, exposure : as ``clblur.blur``
        (a renderer's vectors are exposure chords: ``exposure="continuous"`` integrates them
        as a real shutter does).
    anchor : as ``clblur.blur``, for straight motion; a bent path is anchored at its bend.
    overscan : pixels by which the layers extend beyond the output on every side.
    curved : with a bent path, follow the parabola through its three points (the start, the
        bend at the frame time, the end) instead of two straight halves: ``P(t) - P(0) =
        (first + second) t + 2 (second - first) t^2``, ``t`` in [-1/2, 1/2] (constant
        acceleration; compare Blender's Vector Blur ``use_curved``, a Bézier through the
        frames).

    Returns
    -------
    np.ndarray
        (H - 2 overscan) x (W - 2 overscan) x (C + 1), the layers' dtype: the exposure, colour
        and coverage in the input's alpha convention.

    Raises
    ------
    clblur.errors.InputError
        No layers, layers that differ in shape, dtype or form of motion, coverage outside
        [0, 1], an anchor other than the bend or time weights with a bent path, ``curved``
        without one, or a bad overscan.
    """

    from clblur.blur import resolve_backend
    from clblur.motion import check_exposure

    if isinstance(layers, np.ndarray) or not isinstance(layers, Sequence) or not layers:
        raise InputError("layers must be a non-empty list of (image, motion) pairs, front "
                         "to back")
    forms = []
    for i, layer in enumerate(layers):
        if not isinstance(layer, (tuple, list)) or len(layer) != 2:
            raise InputError(f"layer {i} must be an (image, motion) pair")
        forms.append(_motion_form(layer[1], i))
    if len({f for f, _ in forms}) != 1:
        raise InputError("layers mix straight and bent motion: give every layer the same form")
    bent = forms[0][0] == "bent"
    if bent and weights is not None:
        raise InputError("time weights apply to a straight path, not to a bent one")
    if curved and not bent:
        raise InputError("curved=True needs a bent path: give each layer (first, second)")
    if bent and anchor != "center":
        raise InputError(f"anchor={anchor!r} applies to a straight path; a bent path is "
                         "anchored at its bend (the frame time)")
    layers = [(_with_coverage(image), motion) for image, motion in layers]
    first_image = layers[0][0]
    shape, dtype = first_image.shape, first_image.dtype
    for i, (image, _) in enumerate(layers):
        if np.shape(image) != shape or np.asarray(image).dtype != dtype:
            raise InputError(f"layer {i} is {np.shape(image)} {np.asarray(image).dtype}; "
                             f"layer 0 is {shape} {dtype}: layers must match")
    if isinstance(overscan, bool) or not isinstance(overscan, (int, np.integer)) or overscan < 0:
        raise InputError(f"overscan must be a whole number of pixels >= 0, got {overscan!r}")
    if len(shape) != 3 or 2 * overscan >= min(shape[:2]):
        raise InputError(f"layers of shape {shape} leave no output inside an overscan of "
                         f"{overscan} px" if len(shape) == 3 else
                         f"layer images must be H x W x (C + 1), got shape {shape}")
    ran = resolve_backend(backend, device)
    check_exposure(exposure, weights)
    common = dict(samples=samples, weights=weights, saturation=saturation, alpha=True,
                  check_flow=True)
    # one plan per layer and half: make_plan validates every image and field
    halves = [("end", 0), ("start", 1)] if bent else [(anchor, None)]
    plans = [[make_plan(image, motion if part is None else motion[part], response,
                        anchor=a, **common)
              for image, motion in layers] for a, part in halves]
    linear = [_linear_layer(p) for p in plans[0]]
    for i, lin in enumerate(linear):
        cover = lin[..., -1]
        if cover.min() < 0.0 or cover.max() > 1.0:
            raise InputError(f"layer {i}: coverage (the last channel) must lie in [0, 1], got "
                             f"{cover.min():.4g} to {cover.max():.4g}")
    h, w = shape[:2]
    region = np.zeros((h, w), bool)
    region[overscan:h - overscan, overscan:w - overscan] = True
    planes = np.float64 if ran == "numpy" else np.float32  # what each backend composites in
    if curved:  # one parabola through the halves' three points
        terms = [curved_terms(_field_of(f), _field_of(s))
                 for f, s in zip(plans[0], plans[1], strict=True)]
        chord, bend = [d for d, _ in terms], [c for _, c in terms]
        stack = layers_for(linear, chord, 0.5, region, curvature=bend, dtype=planes,
                           reach_counts=exposure == "frames")
        acc, alone, which = _composite(stack, retime(plans[0][0], anchor=0.5,
                                                     exposure=exposure), ran, device)
    else:  # one straight path, or two halves whose exposures are averaged
        acc = 0.0
        for i, half in enumerate(plans):
            flows = [_field_of(p) for p in half]
            stack = layers_for(linear, flows, half[0].anchor, region, dtype=planes,
                               reach_counts=exposure == "frames")
            light, still, layer = _composite(stack, retime(half[0], exposure=exposure), ran,
                                             device)
            acc = acc + light / len(plans)  # a still pixel: x / 2 + x / 2 is x exactly
            # alone in every half, with the same layer (a still layer reaches the same pixels
            # in both halves)
            alone, which = (still, layer) if i == 0 else (alone & still & (layer == which),
                                                          which)
    inner = (slice(overscan, h - overscan), slice(overscan, w - overscan))
    return _finish(np.asarray(acc)[inner], plans[0][0],
                   [p.image[inner] for p in plans[0]], alone[inner], which[inner], planes)
