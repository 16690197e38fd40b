"""The shared response interface, the kernel kind codes and the valid parameter ranges.

Conventions
-----------
* ``forward(x)`` maps linear exposure ``x >= 0`` (time x irradiance, arbitrary units) to a
  normalised pixel value ``v`` in [0, 1] (code value / Imax).
* ``inverse(v)`` maps ``v`` back to exposure.  It may be infinite at ``v == 1`` (the paper's
  Eq. 3 reaches Imax only at infinite exposure); the blur's saturation policy handles that.
* ``Parametric`` families expose a parameter vector (``param_names``, ``vector()``,
  ``from_vector``) that ``clblur.calibration`` and ``clblur.study`` adjust.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from clblur.errors import InputError, InputTypeError

if TYPE_CHECKING:
    from clblur.responses.kernel_curves import Table

__all__ = ["Response", "Parametric", "KIND_CODES", "RANGES", "FORMAT_VERSION"]


FORMAT_VERSION = 1

# Response kind codes; the kernels get them as -D options (clblur/opencl/constants.py).
KIND_CODES = {"linear": 0, "exp": 1, "gamma": 2, "srgb": 3, "table": 4}

# Accepted parameter ranges (inclusive).  ``gamma``: the float32 kernels evaluate v ** gamma and
# x ** (1 / gamma); beyond 10 the inverse of a uint16 code's half-step (7.6e-6 ** 10 ~ 6e-52)
# underflows float32 and beyond 0.1 the forward of a small exposure does (measured: gamma:100
# differs by 89 codes between the backends, gamma:1e-10 by 242).  ``k``: only the exposure
# unit (it cancels in Eq. 9), kept where float32 represents every code's exposure.
RANGES: dict[str, tuple[float, float]] = {
    "gamma": (0.1, 10.0),
    "k": (1e-6, 1e6),
    "black": (0.0, 0.5),
    "rho": (1e-3, 1.0),
}



class Response:
    """Base class: a monotone increasing map between exposure and normalised value."""

    kind: str = ""
    bounded: bool = True

    def forward(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def inverse(self, v: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def params(self) -> dict:
        return {}

    def device_params(self) -> tuple[float, ...]:
        """Up to four float parameters the kernels read (see clblur/opencl/response.cl)."""
        return ()

    def as_table(self, n: int = 1024) -> Table:
        """The curve sampled densely in value (how families without a kernel code run)."""
        from clblur.responses.kernel_curves import Table  # Table is itself a Response

        top = 1.0 - 1e-6 if not np.isfinite(self.inverse(np.array([1.0]))[0]) else 1.0
        v = np.linspace(0.0, top, 4 * n)
        x = np.asarray(self.inverse(v), dtype=np.float64)
        start = int(np.flatnonzero(x <= 0.0)[-1]) if x[0] <= 0.0 else 0  # black level
        v = np.linspace(v[start], top, n)
        x = _strictly_increasing(np.maximum(self.inverse(v), 0.0))
        return Table(x, v, meta={"family": self.kind, "params": self.params()})

    def to_dict(self) -> dict:
        return {"format": "clblur-response", "version": FORMAT_VERSION, "kind": self.kind,
                "params": self.params()}

    def save(self, path: str | os.PathLike) -> None:
        """Write the response as a small JSON document (atomically)."""
        from clblur.io import atomic_write_text

        atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=2) + "\n")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Response) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(json.dumps(self.to_dict(), sort_keys=True))

    def __repr__(self) -> str:
        p = ", ".join(f"{k}={v!r}" for k, v in self.params().items() if k != "exposure"
                      and k != "value")
        return f"{type(self).__name__}({p})"


def _positive_finite(name: str, value: float, key: str | None = None) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputTypeError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise InputError(f"{name} must be a positive finite number, got {value}")
    if key is not None:
        _in_range(name, value, key)
    return value


def _in_range(name: str, value: float, key: str) -> float:
    lo, hi = RANGES[key]
    if not (math.isfinite(value) and lo <= value <= hi):
        raise InputError(f"{name} must be within [{lo:g}, {hi:g}], got {value:g}")
    return float(value)


class Parametric(Response):
    """A family with a parameter vector (``param_names`` in order) that fitters adjust."""

    param_names: tuple[str, ...] = ()

    def vector(self) -> np.ndarray:
        """The parameters as a float64 vector, in ``param_names`` order."""
        return np.array([getattr(self, n) for n in self.param_names], dtype=np.float64)

    @classmethod
    def from_vector(cls, theta, **fixed) -> Parametric:
        """Build from a parameter vector (``param_names`` order) plus fixed keywords."""
        return cls(**dict(zip(cls.param_names, (float(t) for t in theta), strict=True)),
                   **fixed)

    def params(self) -> dict:
        return {n: getattr(self, n) for n in self.param_names}



def _strictly_increasing(y: np.ndarray) -> np.ndarray:
    """Monotone non-decreasing samples -> strictly increasing (a ramp far below 1 DN)."""
    y = np.maximum.accumulate(np.asarray(y, dtype=np.float64))
    span = max(float(y[-1] - y[0]), 1e-12)
    return y + np.linspace(0.0, 1e-7 * span, y.size)
