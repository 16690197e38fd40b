"""The one public blur function; it validates once and hands the plan to a backend."""

from __future__ import annotations

import os
import warnings

import numpy as np

from clblur import pipeline
from clblur.errors import InputError
from clblur.request import BlurPlan, make_plan

__all__ = ["BACKENDS", "blur", "blur_plan", "check_backend", "resolve_backend", "stages"]

BACKENDS = ("auto", "numpy", "opencl")
_warned_fallback = False


def blur(image: np.ndarray, motion, response="exp", *, anchor: str = "center",
         samples: int | None = None, weights=None, backend: str = "auto",
         saturation: float = 1.0, device: str | None = None, depth=None,
         alpha: bool = False, background: np.ndarray | None = None,
         exposure: str = "frames") -> np.ndarray:
    """Photo-consistent motion blur (Lin & Chang 2006, Eq. 8/9).

    ``g(p) = I( sum_j w_j I^-1(f(p - v(p) (s_j - a))) )``: linearise with the inverse
    response, integrate along the motion in the linear domain, re-apply the response, quantise.

    Parameters
    ----------
    image : H x W or H x W x C array, uint8 / uint16 / float32 / float64.
    motion : ``(dx, dy)`` for the whole image, an H x W x 2 flow field, or a 2-D PSF kernel
        (see ``clblur.motion`` for the conventions: x right, y down, content displacement).
    response : spec (``"linear"``, ``"exp"``, ``"gamma:2.2"``, ``"srgb"``, a JSON path), a
        ``Response``, or a sequence of them, one per channel.
    anchor : ``"start"``, ``"center"`` or ``"end"``: which time of the shutter interval the
        static image shows.
    samples : samples per pixel; default ``ceil(|v|) + 1`` per pixel.
    weights : per-sample time weights (non-uniform velocity); sets ``samples`` if not given.
    exposure : how the samples are weighted without ``weights``.  ``"frames"`` (default):
        each ``1/N``, the paper's Eq. 9 and the mean of ``N`` equally spaced frames
        (GoPro-style data).  ``"continuous"``: the vector is the chord of a continuous
        exposure (a renderer's vector pass, a real shutter): the trapezoid rule on the same
        samples.  Equal weights get a continuous exposure wrong at the shutter's two ends by
        an error of first order in ``1/N`` (0.3 - 5.2 dB on the scenes of
        ``docs/studies/occlusion.md``; ``clblur.motion``).
    backend : ``"auto"`` (OpenCL when a device can build and run a kernel, else numpy with one
        warning), ``"numpy"`` (the float64 reference) or ``"opencl"``.
    saturation : exposure given to full-scale pixels, in units of the least exposure that
        saturates (>= 1; see ``clblur.pixels``).
    device : OpenCL device selector (overrides ``CLBLUR_DEVICE``); see ``clblur info``.
    depth : occlusion ordering, H x W: a float depth (a distance > 0, smaller = nearer, +inf
        for the sky; cut into layers where it jumps between neighbouring pixels, in any unit)
        or integer layer IDs (smaller = nearer).  With it, a per-pixel flow is integrated as
        layered exposure (``clblur.layered_exposure``): every shutter sample composites the
        layers front to back, so moving objects smear over what lies behind them.
        ``"speed"``: faster is nearer; ``"departure"``: what moves against the flow's
        dominant (median) motion is nearer (a camera panning over or tracking across a static
        scene; ``clblur.layering.departure_order``).  Default None: the gather.  With a
        uniform motion or a PSF every pixel moves alike and nothing occludes: the depth
        changes nothing (the command line refuses the combination).
    background : with ``depth``, what lies behind every layer (a clean plate; the input's shape
        and dtype).  Without it, what a moving object uncovers is reconstructed from its
        neighbours (``clblur.layered_exposure``).
    alpha : the last channel is coverage, not light (straight alpha for integer images,
        premultiplied for float images; see ``clblur.reference``).  Default False.

    Returns the blurred image with the input's dtype and shape.  A ``pyopencl.array.Array``
    image (and flow) stays on its device and the result is one too
    (``clblur.opencl.blur_array``).

    Conventions
    -----------
    Motion, anchors and sampling: ``clblur.motion``; pixel values and rounding:
    ``clblur.pixels``; the pipeline order: ``clblur.pipeline``.
    """
    check_backend(backend)
    if type(image).__module__.startswith("pyopencl"):
        from clblur import opencl

        if depth is not None or alpha or background is not None:
            raise InputError("depth, alpha and background take numpy arrays, not device arrays")
        if backend == "numpy":
            raise InputError("a device array (pyopencl.array.Array) is blurred by OpenCL; "
                             "backend='numpy' takes a numpy array")

        return opencl.blur_array(image, motion, response, anchor=anchor, samples=samples,
                                 weights=weights, saturation=saturation, device=device,
                                 exposure=exposure)
    chosen = resolve_backend(backend, device)
    plan = make_plan(image, motion, response, anchor=anchor, samples=samples, weights=weights,
                     saturation=saturation, depth=depth, alpha=alpha, background=background,
                     exposure=exposure,
                     # the layered path reads the flow on the host, so it is checked there
                     check_flow=chosen == "numpy" or depth is not None)
    return blur_plan(plan, chosen, device)


def check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise InputError(f"unknown backend {backend!r}; use one of {', '.join(BACKENDS)}")


def resolve_backend(backend: str, device: str | None = None) -> str:
    """The backend that will actually run: ``"auto"`` becomes ``"opencl"`` or ``"numpy"``."""
    check_backend(backend)
    if backend != "auto":
        return backend
    try:
        from clblur import opencl
    except ImportError as e:  # pyopencl (or the backend module) missing: fall back, as promised
        _warn_fallback(f"OpenCL backend unavailable: {e}")
        return "numpy"
    ok, why = opencl.usable(device)
    if not ok:
        _warn_fallback(why)
        return "numpy"
    return "opencl"


def stages(backend: str, device: str | None = None) -> pipeline.Backend:
    """The pipeline stages of a resolved backend (``"numpy"`` or ``"opencl"``)."""
    if backend == "numpy":
        return pipeline.NUMPY
    from clblur.opencl.layered import OpenCLStages

    return OpenCLStages(device)


def blur_plan(plan: BlurPlan, backend: str = "auto", device: str | None = None) -> np.ndarray:
    """Run a validated plan (whole image or a tiling window) on a backend, through the one
    pipeline (``clblur.pipeline.run``); a depth ordering selects the layered integrator."""
    ran = resolve_backend(backend, device)
    integrate = None
    if plan.depth is not None:
        from clblur.layered_exposure import integrator

        integrate = integrator(ran, device)
    return pipeline.run(plan, stages(ran, device), integrate)


def _warn_fallback(why: str) -> None:
    global _warned_fallback
    if not _warned_fallback and not os.environ.get("CLBLUR_QUIET"):
        warnings.warn(f"clblur: no usable OpenCL device ({why}); using the numpy reference "
                      "backend, which is much slower", RuntimeWarning, stacklevel=3)
    _warned_fallback = True
