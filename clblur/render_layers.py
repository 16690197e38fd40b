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
from clblur.layer_planes import Layers
from clblur.request import BlurPlan, make_plan

__all__ = ["RENDER_INVERSE_STEPS", "blur_layers", "layers_for"]

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


def _field_of(plan: BlurPlan) -> np.ndarray:
    """The plan's motion as an H x W x 2 field (a uniform displacement broadcast)."""
    from clblur.motion import Field, Uniform

    if isinstance(plan.motion, Field):
        return plan.motion.flow
    if isinstance(plan.motion, Uniform):
        return np.full(plan.image.shape[:2] + (2,), (plan.motion.dx, plan.motion.dy),
                       np.float32)
    raise InputError("a layer's motion must be vectors (H x W x 2) or (dx, dy), not a PSF")


def layers_for(linear: Sequence[np.ndarray], flows: Sequence[np.ndarray], anchor: float,
               region: np.ndarray, curvature: Sequence[np.ndarray] | None = None,
               dtype=np.float64) -> Layers:
    """The :class:`clblur.layer_planes.Layers` of a multi-layer render (module Conventions).

    ``linear``: per layer, H x W x (C + 1) premultiplied linear colour and coverage (float64);
    ``flows``: per layer, H x W x 2 vectors; ``region``: the pixels to composite;
    ``curvature``: per layer, the quadratic term of a curved path, or None; ``dtype``: of
    the planes (float32 for the device, which composites in float32).  Each plane carries its
    coverage twice, as light (so the composite sums it) and as coverage.
    """
    from scipy.ndimage import distance_transform_edt

    from clblur.layer_planes import distance_to

    h, w, cp = linear[0].shape
    k = len(linear)
    planes = np.empty((k, h, w, cp + 1), dtype)
    vectors = np.zeros((k, h, w, 2), np.float32)
    present = np.zeros((k, h, w), bool)
    warped = np.zeros(k, bool)
    curves = None if curvature is None else np.zeros((k, h, w, 2), np.float32)
    span = max(anchor, 1.0 - anchor)
    for i, (lin, flow) in enumerate(zip(linear, flows, strict=True)):
        planes[i, ..., :cp] = lin
        planes[i, ..., cp] = lin[..., -1]
        covered = lin[..., -1] > 0
        if not covered.any():
            continue  # an empty layer: zero coverage everywhere, nothing to read
        # a vector pass is point-sampled: trust a pixel's vector where the layer covers at
        # least half of it (an anti-aliased rim pixel may hold the vector of what is behind)
        solid = lin[..., -1] >= 0.5
        if not solid.any():
            solid = covered
        fields = [flow] if curvature is None else [flow, curvature[i]]
        owns = [f[solid] for f in fields]
        if all((own == own[0]).all() for own in owns):  # a rigid translation
            vectors[i] = owns[0][0]
            if curves is not None:
                curves[i] = owns[1][0]
        else:
            nearest = distance_transform_edt(~solid, return_indices=True,
                                             return_distances=False)
            vectors[i] = flow[nearest[0], nearest[1]]
            if curves is not None:
                curves[i] = curvature[i][nearest[0], nearest[1]]
            warped[i] = True
        # how far the layer's samples reach from a pixel: one value for a rigid layer
        pick = (Ellipsis,) if warped[i] else (slice(0, 1), slice(0, 1))
        d = vectors[i][pick]
        farthest = np.hypot(d[..., 0], d[..., 1]) * span
        if curves is not None:
            c = curves[i][pick]
            farthest += np.hypot(c[..., 0], c[..., 1]) * span * span
        # a bilinear footprint reaches sqrt(2) px
        present[i] = (distance_to(covered) <= farthest + 1.5) & region
    return Layers(origin=(0, 0), planes=planes, vectors=vectors,
                  flow=np.zeros((h, w, 2), np.float32), linear=np.zeros((h, w, cp), dtype),
                  region=region, present=present, warped=warped, curvature=curves,
                  inverse_steps=RENDER_INVERSE_STEPS)


def _composite(layers: Layers, plan: BlurPlan, backend: str, device: str | None) -> np.ndarray:
    """The exposure of the region's pixels (H x W x (C + 1), zero elsewhere), float64."""
    from clblur import layered_exposure

    full = layers.region.shape
    if backend == "numpy":
        out = layered_exposure.composite(layers, plan.anchor, plan.samples, plan.weights, full)
        out[~layers.region] = 0.0
        return out
    from clblur.opencl.layered import composite

    values = composite(layers, plan.anchor, plan.samples, plan.weights, full, device)
    out = np.zeros(full + (values.shape[1],))
    out[layers.region] = values
    return out


def blur_layers(layers: Sequence[tuple], response="exp", *, anchor: str = "center",
                samples: int | None = None, weights=None, overscan: int = 0,
                curved: bool = False, backend: str = "auto", saturation: float = 1.0,
                device: str | None = None) -> np.ndarray:
    """Motion blur of a multi-layer render: each layer moves along its own vectors and the
    layers occlude each other front to back at every shutter sample, in linear light.

    Parameters
    ----------
    layers : front to back, ``(image, motion)`` per layer (module Conventions): ``image``
        H x W x (C + 1) colour and coverage (straight alpha for integer dtypes, premultiplied
        for float), ``motion`` H x W x 2 vectors or a bent path ``(first, second)``.
    response, samples, weights, saturation, backend, device : as ``clblur.blur``.
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
    from clblur.reference import finish, linearise

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
    first_image = np.asarray(layers[0][0])
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
    common = dict(samples=samples, weights=weights, saturation=saturation, alpha=True,
                  check_flow=True)
    # one plan per layer and half: make_plan validates every image and field
    halves = [("end", 0), ("start", 1)] if bent else [(anchor, None)]
    plans = [[make_plan(image, motion if part is None else motion[part], response,
                        anchor=a, **common)
              for image, motion in layers] for a, part in halves]
    linear = [linearise(p) for p in plans[0]]
    for i, lin in enumerate(linear):
        cover = lin[..., -1]
        if cover.min() < 0.0 or cover.max() > 1.0:
            raise InputError(f"layer {i}: coverage (the last channel) must lie in [0, 1], got "
                             f"{cover.min():.4g} to {cover.max():.4g}")
    h, w = shape[:2]
    region = np.zeros((h, w), bool)
    region[overscan:h - overscan, overscan:w - overscan] = True
    acc = 0.0
    planes = np.float64 if ran == "numpy" else np.float32  # what each backend composites in
    if curved:  # one parabola through the halves' three points
        from dataclasses import replace

        first, second = ([_field_of(p).astype(np.float64) for p in half] for half in plans)
        chord = [(f + s).astype(np.float32) for f, s in zip(first, second, strict=True)]
        bend = [(2.0 * (s - f)).astype(np.float32) for f, s in zip(first, second, strict=True)]
        stack = layers_for(linear, chord, 0.5, region, curvature=bend, dtype=planes)
        acc = _composite(stack, replace(plans[0][0], anchor=0.5), ran, device)
    else:  # one straight path, or two halves whose exposures are averaged
        for half in plans:
            flows = [_field_of(p) for p in half]
            stack = layers_for(linear, flows, half[0].anchor, region, dtype=planes)
            acc = acc + _composite(stack, half[0], ran, device) / len(plans)
    inner = (slice(overscan, h - overscan), slice(overscan, w - overscan))
    return finish(np.asarray(acc)[inner], plans[0][0])
