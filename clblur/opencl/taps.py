"""Space-invariant integer taps: uniform motion and PSFs rasterised for the kernels.

Conventions
-----------
* Uniform motion and PSFs become integer taps ``d_t`` with weights ``w_t``:
  ``g(p) = sum_t w_t L(clamp(p + d_t))``.  For uniform motion every pixel's bilinear samples
  share the same fractional offsets, so splatting each sample's four bilinear weights onto the
  integer grid is exact, clamp-to-edge included (a clamped position and a replicated border
  read the same edge pixel).
* Taps that form a run of equal weights along x with ``dy == 0`` (or along y with
  ``dx == 0``) are a box, integrated with running sums of exact 64-bit fixed-point values
  whose cost does not depend on the length (``fixed_point_scale``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clblur.motion import PSF, Field, Uniform, uniform_taps
from clblur.request import BlurPlan

__all__ = ["IntegerTaps", "fixed_point_scale", "psf_taps", "rasterise", "space_invariant_taps"]


@dataclass(frozen=True)
class IntegerTaps:
    """Space-invariant integer taps: read ``L(p + (dx, dy))`` with weight ``w``."""

    dx: np.ndarray  # int32
    dy: np.ndarray  # int32
    w: np.ndarray  # float64

    def box(self) -> tuple[int, int, int, bool] | None:
        """``(axis, lo, hi, ends)`` when the taps are a box on offsets lo..hi along x (axis 0,
        dy == 0) or y (axis 1, dx == 0): of equal weights (``ends`` False), or of half
        weights at both ends and equal ones between, the continuous exposure's trapezoid
        rule (``ends`` True, ``clblur.motion``); else None."""
        for axis, along, across in ((0, self.dx, self.dy), (1, self.dy, self.dx)):
            if np.all(across == 0):
                order = np.argsort(along, kind="stable")
                offs = along[order]
                if not np.array_equal(offs, np.arange(offs[0], offs[0] + offs.size)):
                    continue
                w = self.w[order]
                if np.all(w == w[0]):
                    return axis, int(offs[0]), int(offs[-1]), False
                if w.size >= 3 and np.all(w[1:-1] == w[1]) and w[0] == w[-1] == 0.5 * w[1]:
                    return axis, int(offs[0]), int(offs[-1]), True
        return None


def rasterise(offsets: np.ndarray, weights: np.ndarray) -> IntegerTaps:
    """Splat bilinear samples at ``p + offsets[j]`` (N x 2, x then y) onto integer taps."""
    acc: dict[tuple[int, int], float] = {}
    for (ox, oy), wj in zip(offsets, weights, strict=True):
        x0, y0 = math.floor(ox), math.floor(oy)
        fx, fy = ox - x0, oy - y0
        for dx, dy, wt in ((x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)),
                           (x0, y0 + 1, (1 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)):
            if wt * wj != 0.0:
                acc[(dx, dy)] = acc.get((dx, dy), 0.0) + wt * wj
    return _taps_from(acc)


def psf_taps(psf: PSF) -> IntegerTaps:
    """A PSF reads ``f(p - s)`` for displacement ``s = (col - cx, row - cy)``."""
    cy, cx = psf.center
    rows, cols = np.nonzero(psf.kernel)
    acc = {(int(cx - c), int(cy - r)): float(psf.kernel[r, c]) for r, c in zip(rows, cols,
                                                                               strict=True)}
    return _taps_from(acc)


def _taps_from(acc: dict[tuple[int, int], float]) -> IntegerTaps:
    keys = sorted(acc, key=lambda k: (k[1], k[0]))  # row-major order: neighbouring reads
    return IntegerTaps(dx=np.array([k[0] for k in keys], dtype=np.int32),
                dy=np.array([k[1] for k in keys], dtype=np.int32),
                w=np.array([acc[k] for k in keys], dtype=np.float64))


def space_invariant_taps(plan: BlurPlan) -> IntegerTaps | None:
    """Integer taps of a uniform motion or PSF plan; None for a per-pixel field."""
    m = plan.motion
    if isinstance(m, Uniform):
        offsets, w = uniform_taps(m, plan.samples, plan.anchor, plan.weights)
        return rasterise(offsets, w)
    if isinstance(m, PSF):
        return psf_taps(m)
    if isinstance(m, Field):
        return None
    raise TypeError(f"unknown motion {m!r}")


def fixed_point_scale(max_abs: float, count: int) -> float:
    """Power of two that maps ``count`` values of magnitude <= ``max_abs`` into int64 sums
    with headroom (the box kernel's exact running sums)."""
    max_abs = max(float(max_abs), 1e-30)
    exponent = math.floor(60 - math.log2(max_abs * (count + 2)))
    return float(2.0 ** min(exponent, 120))
