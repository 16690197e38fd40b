"""Responses the OpenCL kernels evaluate directly (one ``KIND_CODES`` entry each).

``Linear`` (the conventional box blur), ``Exp`` (the paper's Eq. 3, Lin & Chang 2006),
``Gamma``, ``SRGB`` and ``Table`` (monotone samples, how every other family runs on the device).

Conventions
-----------
Exposure ``x >= 0`` in arbitrary units; values ``v`` normalised to [0, 1] (code / Imax).
``Linear`` is unbounded (scene-linear floats pass through); the others clip ``v`` to [0, 1]:
an exposure past full scale (a saturated pixel given ``saturation > 1``) reads 1, so float
outputs stay in [0, 1] as integer ones do.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError
from clblur.responses.base import (
    Parametric,
    Response,
    _positive_finite,
)

__all__ = ["Linear", "Exp", "Gamma", "SRGB", "Table"]


class Linear(Response):
    """Identity response: the conventional box blur (the paper's Eq. 7)."""

    kind = "linear"
    bounded = False

    def forward(self, x):
        return np.asarray(x, dtype=np.float64)

    def inverse(self, v):
        return np.asarray(v, dtype=np.float64)


@dataclass(frozen=True, eq=False, repr=False)
class Exp(Parametric):
    """The paper's Eq. 3, normalised by Imax: ``v = 1 - exp(-k x)``.

    ``k`` only sets the unit of exposure.  When the static and the blurred image share one
    exposure it cancels in Eq. 9: ``g = 1 - prod_j (1 - f_j) ** w_j`` (a weighted geometric
    mean of ``1 - f``), whatever ``k`` is.
    """

    k: float = 1.0
    kind = "exp"
    param_names = ("k",)

    def __post_init__(self):
        object.__setattr__(self, "k", _positive_finite("exp response k", self.k, "k"))

    def forward(self, x):
        return -np.expm1(-self.k * np.asarray(x, dtype=np.float64))

    def inverse(self, v):
        with np.errstate(divide="ignore"):
            return -np.log1p(-np.asarray(v, dtype=np.float64)) / self.k

    def params(self):
        return {"k": self.k}

    def device_params(self):
        return (self.k,)


@dataclass(frozen=True, eq=False, repr=False)
class Gamma(Parametric):
    """Power law ``v = x ** (1 / gamma)``; ``gamma:2.2`` is the classic display gamma."""

    gamma: float = 2.2
    kind = "gamma"
    param_names = ("gamma",)

    def __post_init__(self):
        object.__setattr__(self, "gamma", _positive_finite("gamma exponent", self.gamma,
                                                           "gamma"))

    def forward(self, x):
        # bounded: an exposure past full scale reads full scale (a float output too)
        return np.power(np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0), 1.0 / self.gamma)

    def inverse(self, v):
        return np.power(np.maximum(np.asarray(v, dtype=np.float64), 0.0), self.gamma)

    def params(self):
        return {"gamma": self.gamma}

    def device_params(self):
        return (self.gamma,)


class SRGB(Response):
    """IEC 61966-2-1 sRGB transfer function (linear segment below 0.04045 / 12.92).

    The standard rounds the exposure knee to 0.0031308; we use the exact image of the value
    knee 0.04045 so that ``forward(inverse(v)) == v`` holds across the knee too.
    """

    kind = "srgb"
    knee = 0.04045 / 12.92

    def forward(self, x):
        x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)  # bounded, as Gamma
        return np.where(x <= self.knee, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)

    def inverse(self, v):
        v = np.maximum(np.asarray(v, dtype=np.float64), 0.0)
        return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))


class Table(Response):
    """Any strictly increasing curve given as samples ``value = f(exposure)``.

    Between samples both directions interpolate linearly; outside they hold the end values.
    ``meta`` carries free-form provenance (e.g. the calibrated family and its parameters).
    """

    kind = "table"

    def __init__(self, exposure: Sequence[float], value: Sequence[float],
                 meta: dict | None = None):
        try:
            x = np.asarray(exposure, dtype=np.float64).ravel()
            v = np.asarray(value, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise InputError("table response samples must be lists of numbers, got "
                             f"{str(exposure)[:40]!r} and {str(value)[:40]!r}") from None
        if x.size != v.size or x.size < 2:
            raise InputError("table response needs equally long exposure and value lists "
                             f"with at least 2 samples, got {x.size} and {v.size}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            raise InputError("table response samples must be finite")
        if np.any(np.diff(x) <= 0) or np.any(np.diff(v) <= 0):
            raise InputError("table response must be strictly increasing in both exposure "
                             "and value")
        if x[0] < 0 or v[0] < 0 or v[-1] > 1:
            raise InputError("table response needs exposure >= 0 and values within [0, 1]")
        self.exposure, self.value, self.meta = x, v, dict(meta or {})

    def forward(self, x):
        return np.interp(np.asarray(x, dtype=np.float64), self.exposure, self.value)

    def inverse(self, v):
        return np.interp(np.asarray(v, dtype=np.float64), self.value, self.exposure)

    def params(self):
        p = {"exposure": self.exposure.tolist(), "value": self.value.tolist()}
        if self.meta:
            p["meta"] = self.meta
        return p

    @classmethod
    def from_response(cls, response: Response, n: int = 1024, top: float = 1.0,
                      meta: dict | None = None) -> Table:
        """Sample another response densely in value (useful to export any model)."""
        v = np.linspace(0.0, top, n)
        return cls(response.inverse(v), v, meta=meta)
