"""Motion descriptions and the sampling of the shutter interval.

Conventions
-----------
* A motion vector ``v = (dx, dy)`` is in pixels, x to the right, y down: how far scene content
  travels across the sensor during the exposure.  Vectors are stored as float32.
* Gather semantics: output pixel ``p`` integrates the linearised image along its own vector,
  at points ``p - v(p) * (s_j - a)`` with ``s_j = j / (N - 1)``, ``j = 0..N-1`` (N = 1: the
  anchor time alone), ``a`` = 0, 0.5, 1 for anchor ``start``, ``center``, ``end``.
  Computed as ``p - v * (j - a (N-1)) / (N-1)`` so integer steps stay exact.
* Default sample count ``N = ceil(|v|) + 1`` (neighbouring samples at most one pixel apart),
  evaluated exactly from the float32 vector by ``sample_counts`` (both backends use it).
* Exposure (``EXPOSURES``): how the N samples are weighted when no time weights are given.
  ``frames`` (the default): equally, ``1/N`` each: the paper's Eq. 9, which averages ``K``
  pixels for a motion of ``K - 1``, and the mean of ``N`` equally spaced frames (how the GoPro
  deblurring data are made).  ``continuous``: the vector is the chord of a continuous
  exposure (what a renderer's vector pass holds); the samples, which include both ends, take
  the trapezoid rule's weights ``1/2, 1, ..., 1, 1/2`` over ``N - 1`` (:func:`sample_weight`).
  Equal weights count the shutter's two ends double, an error of first order in ``1/N``
  against a continuous exposure (``docs/studies/occlusion.md``, Shutter weights).
* Optional per-sample time weights (non-uniform velocity) are normalised to unit sum.
* A PSF (2-D weights ``h``, centre at ``(rows // 2, cols // 2)``) is a space-invariant
  displacement distribution: ``g(p) = I(sum_s h(s) I^-1(f(p - s)))`` (a true convolution).
* Borders clamp to the edge; interpolation is bilinear.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError, InputTypeError

__all__ = ["ANCHORS", "FLOW_LIMIT", "PSF", "EXPOSURES", "Field", "Uniform", "anchor_value",
           "check_flow", "check_exposure", "curved_terms", "flow_error", "parse_motion", "psf",
           "sample_counts",
           "sample_fractions", "sample_weight", "time_weights", "trapezoid_weights",
           "uniform_taps"]

ANCHORS = {"start": 0.0, "center": 0.5, "end": 1.0}
EXPOSURES = ("frames", "continuous")  # module Conventions
# Largest flow component accepted, in px: far beyond any image, small enough that sample
# positions keep 2^-8 px in float32 and the per-pixel sample count stays bounded.
FLOW_LIMIT = 65536.0
# PSF weights this far below 0, relative to the largest, are round-off (clipped to 0)
PSF_ROUNDOFF = 1e-6


@dataclass(frozen=True)
class Uniform:
    """One displacement for the whole image."""

    dx: float
    dy: float


@dataclass(frozen=True)
class Field:
    """A per-pixel displacement field, H x W x 2 float32 or float16 (dx, dy)."""

    flow: np.ndarray


@dataclass(frozen=True)
class PSF:
    """A space-invariant blur kernel, normalised to unit sum (float64)."""

    kernel: np.ndarray

    @property
    def center(self) -> tuple[int, int]:
        """(row, col) of zero displacement."""
        return self.kernel.shape[0] // 2, self.kernel.shape[1] // 2


Motion = Uniform | Field | PSF


def anchor_value(anchor: str) -> float:
    if not isinstance(anchor, str) or anchor not in ANCHORS:
        raise InputError(f"unknown anchor {anchor!r}; use one of {', '.join(ANCHORS)}")
    return ANCHORS[anchor]


def _finite_vector(values: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        raise InputError(f"{what} contains {int(bad.sum())} NaN or infinite value(s)")


def flow_error(nonfinite: int, beyond: int) -> str:
    """The refusal of a flow field with ``nonfinite`` / ``beyond``-limit components."""
    if nonfinite:
        return f"flow field contains {nonfinite} NaN or infinite value(s)"
    return f"flow field contains {beyond} value(s) beyond +-{FLOW_LIMIT:g} px"


def check_flow(flow: np.ndarray) -> None:
    """Refuse non-finite components and components beyond ``FLOW_LIMIT`` (host pass; the
    OpenCL backend counts the same on the device while it reads the flow)."""
    if flow.size:
        # the usual case in two reductions without temporaries (NaN propagates through
        # both, inf fails the bounds): a tenth of the counting below, which only a field
        # to refuse pays for its message
        lo, hi = float(flow.min()), float(flow.max())
        if -FLOW_LIMIT <= lo and hi <= FLOW_LIMIT:
            return
    finite = np.isfinite(flow)
    nonfinite = int(flow.size - np.count_nonzero(finite))
    beyond = 0 if flow.dtype == np.float16 else (  # finite halves never exceed 65504
        int(np.count_nonzero(np.abs(np.where(finite, flow, 0)) > FLOW_LIMIT)))
    if nonfinite or beyond:
        raise InputError(flow_error(nonfinite, beyond))


def parse_motion(motion, shape: tuple[int, int], check: bool = True) -> Motion:
    """Validate ``motion`` for an image of ``shape`` (H, W).

    Accepts ``(dx, dy)``, an H x W x 2 array, a 2-D PSF array, or a ``Uniform``/``Field``/
    ``PSF`` instance.  A float16 flow stays float16 (every half is exactly a float32).
    ``check=False`` leaves the flow's values to the backend (the OpenCL kernels count bad
    values while they read them; ``check_flow`` gives the same refusal).
    """
    if isinstance(motion, Uniform):
        motion = (motion.dx, motion.dy)
    elif isinstance(motion, Field):
        motion = motion.flow
    elif isinstance(motion, PSF):
        return psf(motion.kernel)
    arr = np.asarray(motion)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number)
                                   or arr.dtype == np.bool_):
        raise InputTypeError("motion must be (dx, dy), an H x W x 2 flow array or a 2-D PSF, "
                             f"got {type(motion).__name__}")
    if arr.shape == (2,):
        _finite_vector(arr.astype(np.float64), "motion vector")
        v = arr.astype(np.float32)
        return Uniform(float(v[0]), float(v[1]))
    if arr.ndim == 3:
        h, w = shape
        if arr.shape != (h, w, 2):
            raise InputError(f"flow field has shape {arr.shape}, expected ({h}, {w}, 2) to "
                             f"match the image")
        dtype = np.float16 if arr.dtype == np.float16 else np.float32
        flow = np.ascontiguousarray(arr, dtype=dtype)
        if check:
            check_flow(flow)
        return Field(flow)
    if arr.ndim == 2:
        if arr.shape in ((1, 2), (2, 1)):  # vecs[i:i+1] looks like a vector and is not one
            warnings.warn(f"a {arr.shape[0]} x {arr.shape[1]} motion array is a PSF of two "
                          "taps, not a vector (dx, dy); pass a tuple or a flat array of two "
                          "for a vector", stacklevel=3)
        return psf(arr)
    raise InputError(f"motion has shape {arr.shape}; expected (2,), (H, W, 2) or a 2-D PSF")


def psf(kernel: np.ndarray) -> PSF:
    """Validate and normalise a PSF kernel to unit sum."""
    k = np.asarray(kernel, dtype=np.float64)
    if k.ndim != 2 or k.size == 0:
        raise InputError(f"PSF must be a non-empty 2-D array, got shape {k.shape}")
    _finite_vector(k, "PSF")
    if (k < 0).any():
        # a resampled or rotated kernel leaves round-off just below 0: that is no weight
        floor = PSF_ROUNDOFF * float(np.abs(k).max())
        low = float(k.min())
        if low < -floor:
            at = np.unravel_index(int(np.argmin(k)), k.shape)
            raise InputError(f"PSF weights must be non-negative, got {low:.3g} at (row, col) "
                             f"{tuple(int(i) for i in at)} (values within {PSF_ROUNDOFF:g} of "
                             "the largest below 0 count as round-off, 0)")
        k = np.maximum(k, 0.0)
    total = k.sum()
    if total <= 0:
        raise InputError("PSF weights sum to zero")
    return PSF(k / total)


def curved_terms(first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The parabola through a bent path's three points, ``P(t) - P(0) = D t + C t^2`` for
    ``t`` in ``[-1/2, 1/2]`` (anchor ``center``): ``first`` (H x W x 2) ends at the frame
    time, ``second`` starts there; returns float32 ``(D, C) = (first + second, 2 (second -
    first))``, formed in float64.  It passes the start (``-first``) and the end (``second``)
    and is exact for a constant acceleration; ``C = 0`` is the straight chord."""
    f = np.asarray(first, np.float64)
    s = np.asarray(second, np.float64)
    return (f + s).astype(np.float32), (2.0 * (s - f)).astype(np.float32)


def sample_counts(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Exact ``ceil(|v|) + 1`` for float32 vectors (int32 array, broadcast shape).

    ``dx**2 + dy**2`` of float32 inputs is formed in float64; the ceiling of its square root is
    then corrected with exact integer-square comparisons, so the count never depends on how a
    platform rounds ``sqrt`` (vectors with length within 1e-4 of an integer included).
    """
    x = np.asarray(dx, dtype=np.float32).astype(np.float64)
    y = np.asarray(dy, dtype=np.float32).astype(np.float64)
    l2 = x * x + y * y
    m = np.ceil(np.sqrt(l2))
    m = np.where(m * m < l2, m + 1, m)
    m = np.where((m > 0) & ((m - 1) * (m - 1) >= l2), m - 1, m)
    return (m + 1).astype(np.int32)


def time_weights(samples: int | None, weights: Sequence[float] | None) -> tuple[int | None,
                                                                               np.ndarray | None]:
    """Validate ``samples``/``weights``; return (N or None for per-pixel default, weights)."""
    if samples is not None:
        if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)):
            raise InputTypeError(f"samples must be an integer, got {samples!r}")
        if samples < 1:
            raise InputError(f"samples must be >= 1, got {samples}")
        samples = int(samples)
    if weights is None:
        return samples, None
    try:
        w = np.asarray(weights, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise InputTypeError(f"weights must be a sequence of numbers, got {weights!r}") from None
    if w.size == 0:
        raise InputError("weights must not be empty")
    _finite_vector(w, "time weights")
    if (w < 0).any() or w.sum() <= 0:
        raise InputError("time weights must be non-negative with a positive sum")
    if samples is not None and samples != w.size:
        raise InputError(f"got {w.size} time weights for samples={samples}")
    return w.size, w / w.sum()


def check_exposure(exposure, weights=None) -> str:
    """``exposure`` if it is one of ``EXPOSURES`` and, when ``continuous``, given without time
    weights (which would replace its weights); else a one-line ``InputError``."""
    if not isinstance(exposure, str) or exposure not in EXPOSURES:
        raise InputError(f"exposure must be one of {', '.join(EXPOSURES)}, got {exposure!r}")
    if exposure == "continuous" and weights is not None:
        raise InputError("time weights replace the exposure's weights: give weights or "
                         "exposure='continuous', not both")
    return exposure


def trapezoid_weights(n: int) -> np.ndarray:
    """The ``continuous`` exposure's weights for a fixed ``n`` (float64, unit sum; [1] for
    ``n = 1``)."""
    return sample_weight(np.arange(n), np.full(n, n), True)


def sample_weight(j, n, continuous: bool) -> np.ndarray:
    """Weight of sample ``j`` of ``n`` (arrays, broadcast; ``j < n``) with no time weights:
    ``1 / n`` (``frames``), or the trapezoid rule over ``n - 1`` steps (``continuous``): half
    of ``1 / (n - 1)`` at ``j = 0`` and ``j = n - 1``, all of it between; 1 when ``n = 1``
    (module Conventions)."""
    n = np.asarray(n, dtype=np.float64)
    if not continuous:
        return 1.0 / n
    j = np.asarray(j)
    end = (j == 0) | (j == n - 1)
    return np.where(n > 1, np.where(end, 0.5, 1.0) / np.maximum(n - 1.0, 1.0), 1.0)


def sample_fractions(n: int, anchor: float) -> np.ndarray:
    """Offsets ``(j - a (N-1)) / (N-1)`` for a fixed N (float64); [0] when N == 1."""
    if n == 1:
        return np.zeros(1)
    j = np.arange(n, dtype=np.float64)
    return (j - anchor * (n - 1)) / (n - 1)


def uniform_taps(motion: Uniform, n: int | None, anchor: float,
                 weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The sample offsets ``-v * (s_j - a)`` of a uniform motion: (xy offsets N x 2, weights)."""
    if n is None:
        n = int(sample_counts(np.float32(motion.dx), np.float32(motion.dy)))
    j = np.arange(n, dtype=np.float64)
    num = j - anchor * (n - 1)
    den = max(n - 1, 1)
    off = np.stack([-(motion.dx * num) / den, -(motion.dy * num) / den], axis=1)
    w = np.full(n, 1.0 / n) if weights is None else weights
    return off, w
