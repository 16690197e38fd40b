"""The one public blur function; it validates once and hands the plan to a backend."""

from __future__ import annotations

import os
import warnings

import numpy as np

from clblur import reference
from clblur.plan import BlurPlan, make_plan

BACKENDS = ("auto", "numpy", "opencl")
_warned_fallback = False


def blur(image: np.ndarray, motion, response="exp", *, anchor: str = "center",
         samples: int | None = None, weights=None, backend: str = "auto",
         saturation: float = 1.0, device: str | None = None) -> np.ndarray:
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
    backend : ``"auto"`` (OpenCL when a device can build and run a kernel, else numpy with one
        warning), ``"numpy"`` (the float64 reference) or ``"opencl"``.
    saturation : exposure given to full-scale pixels, in units of the least exposure that
        saturates (>= 1; see ``clblur.pixels``).
    device : OpenCL device selector (overrides ``CLBLUR_DEVICE``); see ``clblur info``.

    Returns the blurred image with the input's dtype and shape.  A ``pyopencl.array.Array``
    image (and flow) stays on its device and the result is one too
    (``clblur.opencl.blur_array``).
    """
    check_backend(backend)
    if type(image).__module__.startswith("pyopencl"):
        from clblur import opencl

        return opencl.blur_array(image, motion, response, anchor=anchor, samples=samples,
                                 weights=weights, saturation=saturation, device=device)
    chosen = resolve_backend(backend, device)
    plan = make_plan(image, motion, response, anchor=anchor, samples=samples, weights=weights,
                     saturation=saturation, check_flow=chosen == "numpy")
    return blur_plan(plan, chosen, device)


def check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; use one of {', '.join(BACKENDS)}")


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


def blur_plan(plan: BlurPlan, backend: str = "auto", device: str | None = None) -> np.ndarray:
    """Run a validated plan (whole image or a tiling window) on a backend."""
    if resolve_backend(backend, device) == "numpy":
        return reference.blur(plan)
    from clblur import opencl

    return opencl.blur(plan, device=device)


def _warn_fallback(why: str) -> None:
    global _warned_fallback
    if not _warned_fallback and not os.environ.get("CLBLUR_QUIET"):
        warnings.warn(f"clblur: no usable OpenCL device ({why}); using the numpy reference "
                      "backend, which is much slower", RuntimeWarning, stacklevel=3)
    _warned_fallback = True
