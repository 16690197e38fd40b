"""When half-float storage of the linear intermediate is safe: a propagated error bound.

Conventions
-----------
* Half storage is used only for uint8 outputs and only when the bound on the output error it
  causes stays at or below ``HALF_MAX_LSB`` code steps (``docs/tolerances.md``).
"""

from __future__ import annotations

import math

import numpy as np

from clblur.request import BlurPlan
from clblur.responses import Response, Table

__all__ = ["HALF_MAX_LSB", "half_error_lsb", "half_storage_ok"]

HALF_MAX_LSB = 0.25  # largest allowed output error from half storage, in uint8 code steps
HALF_UNIT_ROUNDOFF = 2.0**-11
HALF_SUBNORMAL_HALF_STEP = 2.0**-25
HALF_LARGEST = 65504.0


def half_error_lsb(resp: Response, exposures: np.ndarray) -> float:
    """Bound on the uint8 output error (code steps) caused by storing exposures in half.

    A weighted mean of half-rounded values ``E_t (1 + e_t) + d_t`` (``|e_t| <= 2^-11``,
    ``|d_t| <= 2^-25`` in the subnormal range) is off by at most ``E u + d`` from the exact
    mean ``E``; the output moves by at most ``max |f(E +- (E u + d)) - f(E)|`` over the
    exposures the blur can produce, i.e. ``[0, max LUT entry]``.
    """
    top = float(np.max(exposures))
    if not math.isfinite(top) or top * (1 + HALF_UNIT_ROUNDOFF) >= HALF_LARGEST:
        return math.inf
    if float(np.min(exposures)) < 0:
        return math.inf
    grid = np.unique(np.concatenate([
        np.linspace(0.0, top, 4097), np.geomspace(1e-9, max(top, 2e-9), 4097),
        np.asarray(exposures, dtype=np.float64),
        resp.exposure if isinstance(resp, Table) else np.zeros(0)]))
    grid = grid[grid <= top]
    slack = grid * HALF_UNIT_ROUNDOFF + HALF_SUBNORMAL_HALF_STEP
    f = resp.forward(grid)
    err = np.maximum(np.abs(resp.forward(grid + slack) - f),
                     np.abs(f - resp.forward(np.maximum(grid - slack, 0.0))))
    return float(np.max(err) * 255.0)


def half_storage_ok(plan: BlurPlan, luts: np.ndarray | None) -> bool:
    """Half storage only for uint8 images whose propagated error bound is small enough."""
    if plan.dtype != np.uint8 or luts is None:
        return False
    return all(_bound_ok(_curve_key(r), r, luts[c].tobytes())
               for c, r in enumerate(plan.responses))


def _curve_key(resp: Response) -> tuple:
    """What the bound depends on besides the exposures: the response's kind and parameters
    (a table's samples as bytes)."""
    if isinstance(resp, Table):
        return ("table", resp.exposure.tobytes(), resp.value.tobytes())
    return (resp.kind, tuple(sorted(resp.params().items())))


_BOUNDS: dict[tuple, bool] = {}  # (curve key, exposures) -> bound ok; small, bounded below


def _bound_ok(key: tuple, resp: Response, exposures: bytes) -> bool:
    """``half_error_lsb <= HALF_MAX_LSB``, once per response and table: the bound sorts
    some 8000 exposures, 2 ms of every small image's call (an augmentation's 32 x 32 uint8
    took 3x its float32 time).  The cache is keyed by the curve's parameters (``key``, a
    table's samples as bytes) and the exposures, not by the response itself: its hash
    serialises a table to JSON, 0.9 ms for 1024 samples, more than the bound's 0.5 ms."""
    full = (key, exposures)
    if full not in _BOUNDS:
        if len(_BOUNDS) >= 256:
            _BOUNDS.clear()
        _BOUNDS[full] = half_error_lsb(resp, np.frombuffer(exposures, np.float64)) \
            <= HALF_MAX_LSB
    return _BOUNDS[full]


