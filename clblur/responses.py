"""Camera response models: normalised pixel value <-> linear exposure.

Conventions
-----------
* ``forward(x)`` maps linear exposure ``x >= 0`` (time x irradiance, arbitrary units) to a
  normalised pixel value ``v`` in [0, 1] (code value / Imax).
* ``inverse(v)`` maps ``v`` back to exposure.  It may be infinite at ``v == 1`` (the paper's
  Eq. 3 reaches Imax only at infinite exposure); the blur's saturation policy handles that.
* The ``linear`` response is unbounded: it passes any real value through, so scene-linear float
  images (values above 1) are blurred as they are.  Every other response clips ``v`` to [0, 1].

Every model shares this small interface, so the numpy reference and the OpenCL kernels read the
same description (``KIND_CODES``) and curves of any other family run as a ``table``
(``for_device``).

This module is the only place where curve formulas live.  Device kinds: ``Linear``, ``Exp``
(the paper's Eq. 3, Lin & Chang 2006), ``Gamma``, ``SRGB``, ``Table``.  Families fitted by
``clblur.calibration`` and ``clblur.study`` (each with a parameter vector: ``param_names``,
``vector()``, ``from_vector``): ``ExpOffset`` (Eq. 3 above a black level), ``GammaOffset``,
``ExpShape`` (Eq. 3 generalised: black level, power, curvature and a free smooth warp, nested
so that its null parameters give Eq. 3 exactly), ``Polynomial`` (Mitsunaga & Nayar 1999),
``Emor`` (Grossberg & Nayar 2004, basis from ``$CLBLUR_DATA/crf``) and ``MonotoneSpline`` (a
free monotone piecewise-linear curve, itself a ``Table``).

Valid parameter ranges (``RANGES``) are enforced when a response is built or parsed: outside
them float32 kernels under- or overflow on some codes and cannot match the float64 reference.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Response", "Linear", "Exp", "Gamma", "SRGB", "Table", "ExpOffset", "GammaOffset",
           "ExpShape", "Polynomial", "Emor", "EmorBasis", "MonotoneSpline", "KIND_CODES",
           "RANGES", "FAMILY_CLASSES", "response", "from_dict", "load_response", "per_channel",
           "for_device", "default_knots", "warp_basis", "channel_set_to_dict", "save_channel_set",
           "CHANNEL_SET_KIND"]

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
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    if key is not None:
        _in_range(name, value, key)
    return value


def _in_range(name: str, value: float, key: str) -> float:
    lo, hi = RANGES[key]
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} must be within [{lo:g}, {hi:g}], got {value:g}")
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
        return np.power(np.maximum(np.asarray(x, dtype=np.float64), 0.0), 1.0 / self.gamma)

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
        x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
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
        x = np.asarray(exposure, dtype=np.float64).ravel()
        v = np.asarray(value, dtype=np.float64).ravel()
        if x.size != v.size or x.size < 2:
            raise ValueError("table response needs equally long exposure and value lists "
                             f"with at least 2 samples, got {x.size} and {v.size}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            raise ValueError("table response samples must be finite")
        if np.any(np.diff(x) <= 0) or np.any(np.diff(v) <= 0):
            raise ValueError("table response must be strictly increasing in both exposure "
                             "and value")
        if x[0] < 0 or v[0] < 0 or v[-1] > 1:
            raise ValueError("table response needs exposure >= 0 and values within [0, 1]")
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


def _strictly_increasing(y: np.ndarray) -> np.ndarray:
    """Monotone non-decreasing samples -> strictly increasing (a ramp far below 1 DN)."""
    y = np.maximum.accumulate(np.asarray(y, dtype=np.float64))
    span = max(float(y[-1] - y[0]), 1e-12)
    return y + np.linspace(0.0, 1e-7 * span, y.size)


# Value grid on which families without a closed-form forward are inverted numerically.
_GRID = np.linspace(0.0, 1.0, 4097)


class _Sampled(Parametric):
    """A family defined by its inverse; the forward interpolates a dense value grid."""

    def _grid_exposure(self) -> np.ndarray:
        cache = self.__dict__.get("_grid_x")
        if cache is None:
            cache = _strictly_increasing(np.maximum(self.inverse(_GRID), 0.0))
            object.__setattr__(self, "_grid_x", cache)
        return cache

    def forward(self, x):
        return np.interp(np.asarray(x, dtype=np.float64), self._grid_exposure(), _GRID)


@dataclass(frozen=True, eq=False, repr=False)
class ExpOffset(Parametric):
    """Eq. 3 above a black level ``b``: ``v = b + (1 - b)(1 - exp(-k x))``."""

    black: float = 0.0
    k: float = 1.0
    kind = "exp-offset"
    param_names = ("black", "k")

    def __post_init__(self):
        object.__setattr__(self, "black", _in_range("black level", float(self.black), "black"))
        object.__setattr__(self, "k", _positive_finite("exp response k", self.k, "k"))

    def forward(self, x):
        b = self.black
        return b - (1.0 - b) * np.expm1(-self.k * np.asarray(x, dtype=np.float64))

    def inverse(self, v):
        w = np.clip((np.asarray(v, dtype=np.float64) - self.black) / (1.0 - self.black), 0, 1)
        with np.errstate(divide="ignore"):
            return -np.log1p(-w) / self.k


@dataclass(frozen=True, eq=False, repr=False)
class GammaOffset(Parametric):
    """A power law above a black level: ``v = b + (1 - b) min(x, 1) ** (1 / gamma)``."""

    black: float = 0.0
    gamma: float = 2.2
    kind = "gamma-offset"
    param_names = ("black", "gamma")

    def __post_init__(self):
        object.__setattr__(self, "black", _in_range("black level", float(self.black), "black"))
        object.__setattr__(self, "gamma", _positive_finite("gamma exponent", self.gamma,
                                                           "gamma"))

    def forward(self, x):
        b = self.black
        x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
        return b + (1.0 - b) * np.power(x, 1.0 / self.gamma)

    def inverse(self, v):
        w = np.clip((np.asarray(v, dtype=np.float64) - self.black) / (1.0 - self.black), 0, 1)
        return np.power(w, self.gamma)


def warp_basis(w: np.ndarray, n: int) -> np.ndarray:
    """``n`` smooth functions of ``w`` in [0, 1] that vanish at ``w = 1`` (n x len(w)).

    Shifted Legendre polynomials minus their value at 1: a constant would only rescale the
    exposure unit (which cancels in every prediction), so it is left out.
    """
    t = 2.0 * np.clip(np.asarray(w, dtype=np.float64), 0.0, 1.0) - 1.0
    return np.stack([np.polynomial.legendre.legval(t, [0.0] * m + [1.0]) - 1.0
                     for m in range(1, n + 1)]) if n else np.zeros((0, t.size))


@dataclass(frozen=True, eq=False, repr=False)
class ExpShape(_Sampled):
    """Eq. 3 generalised, nested so that the null parameters give Eq. 3 exactly.

    Inverse: ``x = (-ln(1 - rho w) / rho) ** gamma * exp(sum_m c_m B_m(w))`` with
    ``w = (v - b) / (1 - b)``, ``B_m`` from ``warp_basis``.  ``black = 0, gamma = rho = 1,
    c = 0`` is Eq. 3 (k = 1); ``rho -> 0`` gives a power law; the warp coefficients ``c`` bend
    the shape freely (toe and shoulder of S-shaped camera curves) while staying smooth.
    Monotone by construction of the sampled forward (non-increasing stretches are flattened).
    """

    black: float = 0.0
    gamma: float = 1.0
    rho: float = 1.0
    warp: tuple[float, ...] = ()
    kind = "exp-shape"
    param_names = ("black", "gamma", "rho")

    def __post_init__(self):
        object.__setattr__(self, "black", _in_range("black level", float(self.black), "black"))
        object.__setattr__(self, "gamma", _in_range("exp-shape gamma", float(self.gamma),
                                                    "gamma"))
        object.__setattr__(self, "rho", _in_range("exp-shape rho", float(self.rho), "rho"))
        warp = tuple(float(c) for c in self.warp)
        if not all(math.isfinite(c) for c in warp):
            raise ValueError(f"exp-shape warp coefficients must be finite, got {warp}")
        object.__setattr__(self, "warp", warp)

    def vector(self) -> np.ndarray:
        return np.concatenate([super().vector(), self.warp])

    @classmethod
    def from_vector(cls, theta, **fixed) -> ExpShape:
        theta = [float(t) for t in theta]
        return cls(*theta[:3], warp=tuple(theta[3:]), **fixed)

    def params(self):
        return {"black": self.black, "gamma": self.gamma, "rho": self.rho,
                "warp": list(self.warp)}

    @staticmethod
    def shape_inverse(w, gamma: float, rho: float, warp=()) -> np.ndarray:
        """The inverse above the black level, on ``w`` in [0, 1) (inf at 1 when rho = 1)."""
        w = np.asarray(w, dtype=np.float64)
        with np.errstate(divide="ignore"):
            base = np.power(-np.log1p(-rho * w) / rho, gamma)
        if len(warp):
            base = base * np.exp(np.asarray(warp) @ warp_basis(w.ravel(), len(warp))
                                 ).reshape(w.shape)
        return base

    def inverse(self, v):
        v = np.asarray(v, dtype=np.float64)
        w = np.clip((v - self.black) / (1.0 - self.black), 0.0, 1.0)
        x = self.shape_inverse(w, self.gamma, self.rho, self.warp)
        if not self.warp:
            return x
        # a strongly bent warp may turn back: keep the running maximum along the value axis
        flat = x.ravel()
        order = np.argsort(w.ravel(), kind="stable")
        flat[order] = np.maximum.accumulate(np.nan_to_num(flat[order], nan=0.0))
        return flat.reshape(x.shape)

    def forward(self, x):
        if self.warp:
            return super().forward(x)
        x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
        w = -np.expm1(-self.rho * np.power(x, 1.0 / self.gamma)) / self.rho
        return self.black + (1.0 - self.black) * np.minimum(w, 1.0)

    def forward_slope(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Value and its slope ``dv/dx`` at exposures ``x`` (analytic without warp, else the
        slope of the sampled segment)."""
        x = np.maximum(np.asarray(x, dtype=np.float64), 1e-12)
        scale = 1.0 - self.black
        if not self.warp:
            root = np.power(x, 1.0 / self.gamma)
            w = -np.expm1(-self.rho * root) / self.rho
            slope = np.exp(-self.rho * root) * root / (self.gamma * x)
            over = w > 1.0
            return (self.black + scale * np.where(over, 1.0, w),
                    scale * np.where(over, 0.0, slope))
        gx = self._grid_exposure()
        seg = np.clip(np.searchsorted(gx, x, side="right") - 1, 0, gx.size - 2)
        slope = np.where(x < gx[-1], (_GRID[seg + 1] - _GRID[seg]) / (gx[seg + 1] - gx[seg]),
                         0.0)
        return self.forward(x), slope

    def _grid_exposure(self) -> np.ndarray:
        cache = self.__dict__.get("_grid_x")
        if cache is None:
            x = self.inverse(_GRID[:-1])
            x = np.concatenate([x, [x[-1] * 2.0 + 1.0]])  # finite stand-in for I^-1(1)
            cache = _strictly_increasing(np.maximum(x, 0.0))
            object.__setattr__(self, "_grid_x", cache)
        return cache


@dataclass(frozen=True, eq=False, repr=False)
class Polynomial(_Sampled):
    """Mitsunaga & Nayar (1999): inverse ``g(v) = sum_n c_n v**n``, full scale at ``g(1)``.

    ``coefficients`` start at ``c_0``.  The forward inverts ``g`` on a dense value grid; a
    non-monotone stretch is flattened (the curve is made non-decreasing).
    """

    coefficients: tuple[float, ...] = (0.0, 1.0)
    kind = "polynomial"

    def __post_init__(self):
        c = tuple(float(t) for t in self.coefficients)
        if not 2 <= len(c) <= 13 or not all(math.isfinite(t) for t in c):
            raise ValueError("polynomial response needs 2..13 finite coefficients "
                             f"(c_0 first), got {c}")
        object.__setattr__(self, "coefficients", c)

    @property
    def param_names(self):  # type: ignore[override]
        return tuple(f"c{n}" for n in range(len(self.coefficients)))

    def vector(self) -> np.ndarray:
        return np.array(self.coefficients)

    @classmethod
    def from_vector(cls, theta, **fixed) -> Polynomial:
        return cls(tuple(float(t) for t in theta), **fixed)

    def params(self):
        return {"coefficients": list(self.coefficients)}

    def inverse(self, v):
        v = np.clip(np.asarray(v, dtype=np.float64), 0.0, 1.0)
        return np.polyval(self.coefficients[::-1], v)


@dataclass(frozen=True)
class EmorBasis:
    """Grossberg & Nayar's EMoR: ``f(E) = f0(E) + sum_m c_m h_m(E)`` sampled on grid E."""

    grid: np.ndarray
    mean: np.ndarray
    components: np.ndarray  # (25, len(grid))

    @classmethod
    def load(cls, folder: str | os.PathLike | None = None) -> EmorBasis:
        """Read ``emor.txt`` from ``folder`` (default: the shared data's ``crf`` folder)."""
        from clblur.io import data_dir

        if folder is None:
            root = data_dir()
            if root is None:
                raise ValueError("EMoR basis not found: pass emor_dir= (--emor-dir) or set "
                                 "CLBLUR_DATA to a folder holding crf/emor.txt")
            folder = root / "crf"
        path = Path(folder) / "emor.txt"
        cached = _EMOR_CACHE.get(str(path))
        if cached is not None:
            return cached
        if not path.is_file():
            raise ValueError(f"EMoR basis file not found: {path}")
        blocks, current = {}, None
        for line in path.read_text().splitlines():
            if "=" in line:
                current = line.split("=")[0].strip()
                blocks[current] = []
            elif current is not None and line.strip():
                blocks[current].extend(float(t) for t in line.split())
        try:
            grid, mean = np.array(blocks["E"]), np.array(blocks["f0"])
            comps = np.array([blocks[f"h({m})"] for m in range(1, 26)])
        except (KeyError, ValueError) as e:
            raise ValueError(f"{path}: missing or ragged block ({e})") from None
        if grid.size != mean.size or comps.shape[1] != grid.size:
            raise ValueError(f"{path}: blocks of different lengths")
        _EMOR_CACHE[str(path)] = basis = cls(grid, mean, comps)
        return basis


_EMOR_CACHE: dict[str, EmorBasis] = {}


@dataclass(frozen=True, eq=False, repr=False)
class Emor(Parametric):
    """Grossberg & Nayar (2004) EMoR: mean curve plus principal components of real curves.

    Forward ``v = f0(x) + sum_m c_m h_m(x)`` on the basis grid (full scale at exposure 1),
    made strictly increasing and normalised to ``f(0) = 0, f(1) = 1``.  ``emor_dir``: folder
    of ``emor.txt`` (default ``$CLBLUR_DATA/crf``).
    """

    coefficients: tuple[float, ...] = ()
    emor_dir: str | None = None
    kind = "emor"

    def __post_init__(self):
        c = tuple(float(t) for t in self.coefficients)
        if not 1 <= len(c) <= 25 or not all(math.isfinite(t) for t in c):
            raise ValueError(f"EMoR response needs 1..25 finite coefficients, got {c}")
        object.__setattr__(self, "coefficients", c)

    @property
    def param_names(self):  # type: ignore[override]
        return tuple(f"c{m}" for m in range(1, len(self.coefficients) + 1))

    def vector(self) -> np.ndarray:
        return np.array(self.coefficients)

    @classmethod
    def from_vector(cls, theta, **fixed) -> Emor:
        return cls(tuple(float(t) for t in theta), **fixed)

    def params(self):
        p = {"coefficients": list(self.coefficients)}
        if self.emor_dir is not None:
            p["emor_dir"] = str(self.emor_dir)
        return p

    def raw_curve(self) -> np.ndarray:
        """``f0 + sum c_m h_m`` on the basis grid, unconstrained (what the fit adjusts)."""
        b = EmorBasis.load(self.emor_dir)
        return b.mean + np.asarray(self.coefficients) @ b.components[:len(self.coefficients)]

    def _curve(self) -> tuple[np.ndarray, np.ndarray]:
        cache = self.__dict__.get("_c")
        if cache is None:
            f = _strictly_increasing(np.clip(self.raw_curve(), 0.0, 1.0))
            cache = (EmorBasis.load(self.emor_dir).grid, (f - f[0]) / (f[-1] - f[0]))
            object.__setattr__(self, "_c", cache)
        return cache

    def forward(self, x):
        grid, f = self._curve()
        return np.interp(np.asarray(x, dtype=np.float64), grid, f)

    def inverse(self, v):
        grid, f = self._curve()
        return np.interp(np.asarray(v, dtype=np.float64), f, grid)


class MonotoneSpline(Table):
    """A free monotone curve: piecewise linear in (exposure, value) through ``knots``.

    ``knots`` are value positions ``0 = u_0 < ... < u_K = 1``; the exposure at ``u_k`` is
    ``x_k = sum_{m <= k} exp(theta_m)`` (``x_0 = 0``), normalised so ``x_K = 1``.  Positive
    increments make it monotone by construction; codes below a black level get increments
    near zero (the toe).  It *is* a ``Table`` (kind ``table``), so the kernels run it exactly.
    """

    family = "monotone-spline"

    def __init__(self, knots: Sequence[float], log_increments: Sequence[float],
                 meta: dict | None = None):
        u = np.asarray(knots, dtype=np.float64).ravel()
        th = np.asarray(log_increments, dtype=np.float64).ravel()
        if u.size < 3 or th.size != u.size - 1:
            raise ValueError(f"monotone spline needs K + 1 >= 3 knots and K log increments, got "
                             f"{u.size} and {th.size}")
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(th))):
            raise ValueError("monotone spline parameters must be finite")
        if u[0] != 0.0 or u[-1] != 1.0 or np.any(np.diff(u) <= 0):
            raise ValueError("monotone spline knots must increase strictly from 0 to 1")
        total = float(np.log(np.sum(np.exp(th - th.max()))) + th.max())
        if abs(total) > 1e-12:  # x_K = 1 (the exposure unit); a saved curve already has it
            th = th - total
        x = np.concatenate([[0.0], np.cumsum(np.exp(th))])
        self.knots, self.log_increments = u, th
        info = {"family": self.family, "knots": u.tolist(), "log_increments": th.tolist()}
        super().__init__(_strictly_increasing(x / x[-1]), u, meta={**info, **(meta or {})})

    param_names = property(lambda self: tuple(f"t{m}" for m in range(self.log_increments.size)))

    def vector(self) -> np.ndarray:
        return self.log_increments.copy()

    @classmethod
    def from_vector(cls, theta, knots=None, **fixed) -> MonotoneSpline:
        theta = np.asarray(theta, dtype=np.float64)
        if knots is None:
            knots = default_knots(theta.size)
        return cls(knots, theta, **fixed)

    @classmethod
    def fit_to(cls, resp: Response, knots) -> MonotoneSpline:
        """The spline through another response's inverse at ``knots`` (top knot finite)."""
        u = np.asarray(knots, dtype=np.float64)
        x = np.asarray(resp.inverse(np.minimum(u, 1.0 - 1e-4)), dtype=np.float64)
        x = _strictly_increasing(np.maximum(x - x[0], 0.0))
        return cls(u, np.log(np.maximum(np.diff(x), 1e-9 * x[-1])))


def default_knots(k: int) -> np.ndarray:
    """``k + 1`` value knots, denser towards black (``u_m = (m / k) ** 2``): the toe bends
    most and dark codes stand for the widest range of exposure."""
    return (np.arange(k + 1) / k) ** 2


_BY_KIND = {"linear": Linear, "exp": Exp, "gamma": Gamma, "srgb": SRGB}
# every family a response document may name (device kinds and fitted families)
FAMILY_CLASSES = {**_BY_KIND, "exp-offset": ExpOffset, "gamma-offset": GammaOffset,
                  "exp-shape": ExpShape, "polynomial": Polynomial, "emor": Emor}


def for_device(r: Response) -> Response:
    """``r`` itself for a kernel kind (``KIND_CODES``), else its dense ``Table``."""
    return r if r.kind in KIND_CODES else r.as_table()


def from_dict(doc: dict) -> Response:
    """Build a response from its JSON document (see ``Response.to_dict``)."""
    if not isinstance(doc, dict) or "kind" not in doc:
        raise ValueError("response document must be a JSON object with a 'kind' key")
    kind, params = doc["kind"], dict(doc.get("params") or {})
    if kind == "table":
        meta = params.get("meta") or {}
        try:
            if isinstance(meta, dict) and meta.get("family") == MonotoneSpline.family:
                extra = {k: v for k, v in meta.items()
                         if k not in ("family", "knots", "log_increments")}
                return MonotoneSpline(meta["knots"], meta["log_increments"], extra)
            return Table(params["exposure"], params["value"], params.get("meta"))
        except KeyError as e:
            raise ValueError(f"table response document lacks {e.args[0]!r}") from None
    if kind == CHANNEL_SET_KIND:
        raise ValueError("this document holds one response per channel; use it where "
                         "per-channel responses are accepted (clblur.blur, clblur blur)")
    if kind not in FAMILY_CLASSES:
        raise ValueError(f"unknown response kind {kind!r}; known: "
                         f"{', '.join(sorted({*KIND_CODES, *FAMILY_CLASSES}))}")
    if kind in ("polynomial", "emor", "exp-shape"):
        for key in ("coefficients", "warp"):
            if key in params and isinstance(params[key], list):
                params[key] = tuple(params[key])
    try:
        return FAMILY_CLASSES[kind](**params)
    except TypeError as e:
        raise ValueError(f"bad parameters for {kind} response: {e}") from None


def load_response(path: str | os.PathLike) -> Response:
    """Read a response JSON file written by ``Response.save`` or ``clblur calibrate``."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"response file not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise ValueError(f"cannot read response file {path}: {e}") from None
    return from_dict(doc)


def response(spec: str | Response | dict) -> Response:
    """Parse a response spec: ``linear``, ``exp``, ``exp:K``, ``gamma:2.2``, ``srgb``,
    a path to a response JSON file, a JSON document, or a ``Response`` (returned as is)."""
    if isinstance(spec, Response):
        return spec
    if isinstance(spec, dict):
        return from_dict(spec)
    if not isinstance(spec, str):
        raise TypeError(f"response must be a name, a JSON path or a Response, got {spec!r}")
    name, _, arg = spec.partition(":")
    if name in ("linear", "srgb") and not arg:
        return _BY_KIND[name]()
    if name in ("exp", "gamma"):
        what, key = ("k", "k") if name == "exp" else ("exponent", "gamma")
        lo, hi = RANGES[key]
        letter = "K" if name == "exp" else "G"
        expected = f"{name}:{letter} with {letter} a number in [{lo:g}, {hi:g}]"
        if not arg:
            if name == "exp":
                return Exp()
            raise ValueError(f"response spec {spec!r}: gamma response needs an exponent, "
                             f"expected {expected}, e.g. gamma:2.2")
        try:
            value = float(arg)
        except ValueError:
            raise ValueError(f"response spec {spec!r}: {name} {what} must be a number, "
                             f"expected {expected}") from None
        try:
            return Exp(value) if name == "exp" else Gamma(value)
        except ValueError as e:
            raise ValueError(f"response spec {spec!r}: {e}") from None
    if spec.endswith(".json") or os.path.sep in spec or os.path.exists(spec):
        return load_response(spec)
    raise ValueError(f"unknown response {spec!r}; use linear, exp, exp:K, gamma:G, srgb "
                     "or a response JSON file")


CHANNEL_SET_KIND = "per-channel"


def channel_set_to_dict(responses: Sequence[Response]) -> dict:
    """A JSON document holding one response per channel (written by ``clblur calibrate``)."""
    return {"format": "clblur-response", "version": FORMAT_VERSION, "kind": CHANNEL_SET_KIND,
            "channels": [r.to_dict() for r in responses]}


def save_channel_set(path: str | os.PathLike, responses: Sequence[Response]) -> None:
    """Write per-channel responses as one JSON file (atomically)."""
    from clblur.io import atomic_write_text

    atomic_write_text(Path(path), json.dumps(channel_set_to_dict(responses), indent=2) + "\n")


def _channel_set(spec) -> list[Response] | None:
    """The responses of a per-channel document (dict or JSON path), else None."""
    doc = spec
    if isinstance(spec, (str, os.PathLike)) and str(spec).endswith(".json") \
            and Path(spec).is_file():
        try:
            doc = json.loads(Path(spec).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
            raise ValueError(f"cannot read response file {spec}: {e}") from None
    if not (isinstance(doc, dict) and doc.get("kind") == CHANNEL_SET_KIND):
        return None
    channels = doc.get("channels")
    if not isinstance(channels, list) or not channels:
        raise ValueError("per-channel response document needs a non-empty 'channels' list")
    return [from_dict(d) for d in channels]


def per_channel(spec, channels: int) -> list[Response]:
    """One response per channel: a single spec is shared, a sequence must match ``channels``;
    a per-channel document (``kind: per-channel``, e.g. from ``clblur calibrate``) acts as the
    sequence it holds."""
    if not isinstance(spec, (list, tuple, Response)):
        found = _channel_set(spec)
        if found is not None:
            spec = found
    if isinstance(spec, (list, tuple)):
        if len(spec) != channels:
            raise ValueError(f"got {len(spec)} per-channel responses for an image with "
                             f"{channels} channel(s)")
        return [for_device(response(s)) for s in spec]
    r = for_device(response(spec))
    return [r] * channels
