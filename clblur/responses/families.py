"""Response families fitted by ``clblur.calibration`` and ``clblur.study``.

``ExpOffset`` (Eq. 3 above a black level), ``GammaOffset``, ``ExpShape`` (Eq. 3 generalised:
black level, power, curvature and a free smooth warp, nested so that its null parameters give
Eq. 3 exactly), ``Polynomial`` (Mitsunaga & Nayar 1999) and ``MonotoneSpline`` (a free monotone
piecewise-linear curve, itself a ``Table``).  Families without a kernel code run on the device
as their dense ``Table`` (``clblur.responses.for_device``).

Conventions
-----------
Exposure ``x >= 0`` in arbitrary units (full scale at ``x = 1`` where a family normalises);
values ``v`` normalised to [0, 1].
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError
from clblur.responses.base import (
    Parametric,
    Response,
    _in_range,
    _positive_finite,
    _strictly_increasing,
)
from clblur.responses.kernel_curves import Table

__all__ = ["ExpOffset", "GammaOffset", "ExpShape", "Polynomial", "MonotoneSpline", "default_knots",
           "warp_basis", "warp_basis_slopes"]


# Value grid on which families without a closed-form forward are inverted numerically.
_GRID = np.linspace(0.0, 1.0, 4097)
_NODES = 2048  # ExpShape's warped forward: Hermite nodes uniform in ln x
# a Newton step of the nodes below this (in ln w) leaves them converged to rounding
_NEWTON_DONE = 1e-13


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

    def __hash__(self) -> int:
        # the instances are frozen: the hash (of the JSON form) is taken once.  Why: a study
        # keys its code tables by the curve (clblur.study.model._code_tables), and hashing
        # it anew on every prediction was 1 - 2 % of a study's time (cProfile)
        cached = self.__dict__.get("_hash")
        if cached is None:
            cached = super().__hash__()
            object.__setattr__(self, "_hash", cached)
        return cached

    def __getstate__(self) -> dict:
        # a str's hash differs between processes (PYTHONHASHSEED): the hash is not pickled
        return {k: v for k, v in self.__dict__.items() if k != "_hash"}


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


@functools.lru_cache(maxsize=256)
def _warp_polynomial(c: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``sum_m c_m (P_m(t) - 1)`` as power-series coefficients in ``t`` (highest first, for
    Horner's rule), and those of its derivative in ``w = (t + 1) / 2``."""
    legendre = np.polynomial.legendre
    power = legendre.leg2poly(np.concatenate([[0.0], c]))
    power[0] -= sum(c)
    return power[::-1].copy(), (2.0 * np.polynomial.polynomial.polyder(power))[::-1].copy()


def _horner(coefficients: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.full_like(t, coefficients[0])
    for a in coefficients[1:]:
        out *= t
        out += a
    return out


def _warp_series(w: np.ndarray, c: Sequence[float], slope: bool = False
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """``c @ warp_basis(w, len(c))`` and, with ``slope``, its derivative in ``w``, for ``w``
    in [0, 1] (no clipping).

    Why not ``warp_basis``: the response shape's forward evaluates this thousands of times
    per fit, and a basis built term by term (one ``legval`` each, then a product) cost more
    than the rest of the curve.  The Legendre sum is converted once per coefficient set to
    a polynomial in ``t = 2 w - 1`` (at most degree 4 here, well conditioned on [-1, 1])
    and evaluated by Horner's rule: the same sum to rounding, a third of the operations.
    """
    value_c, slope_c = _warp_polynomial(tuple(float(a) for a in c))
    t = 2.0 * np.asarray(w, dtype=np.float64) - 1.0
    return _horner(value_c, t), (_horner(slope_c, t) if slope else None)


def warp_basis(w: np.ndarray, n: int) -> np.ndarray:
    """``n`` smooth functions of ``w`` in [0, 1] that vanish at ``w = 1`` (n x len(w)).

    Shifted Legendre polynomials minus their value at 1: a constant would only rescale the
    exposure unit (which cancels in every prediction), so it is left out.
    """
    return warp_basis_slopes(np.clip(np.asarray(w, dtype=np.float64), 0.0, 1.0), n)[0]


def warp_basis_slopes(w: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`warp_basis` (no clipping) with its first and second derivatives in ``w``,
    three n x w.shape arrays.

    Bonnet's recurrence in ``t = 2 w - 1``: ``(m + 1) P_{m+1} = (2m + 1) t P_m - m P_{m-1}``,
    and differentiated, ``P'_{m+1} = P'_{m-1} + (2m + 1) P_m`` (the same for ``P''`` from
    ``P'``).  Why not ``legval`` and ``legder`` per function: the likelihood's gradient asks
    for these at every evaluation, and the per-call overhead of those was a fifth of a small
    study's time."""
    t = 2.0 * np.asarray(w, dtype=np.float64) - 1.0
    p = [np.ones_like(t), t]
    d1 = [np.zeros_like(t), np.ones_like(t)]
    d2 = [np.zeros_like(t), np.zeros_like(t)]
    for m in range(1, n):
        p.append(((2 * m + 1) * t * p[m] - m * p[m - 1]) / (m + 1))
        d1.append(d1[m - 1] + (2 * m + 1) * p[m])
        d2.append(d2[m - 1] + (2 * m + 1) * d1[m])
    if not n:
        empty = np.zeros((0,) + t.shape)
        return empty, empty, empty
    return (np.stack(p[1:n + 1]) - 1.0, 2.0 * np.stack(d1[1:n + 1]),
            4.0 * np.stack(d2[1:n + 1]))


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
            raise InputError(f"exp-shape warp coefficients must be finite, got {warp}")
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
            base = base * np.exp(_warp_series(np.clip(w, 0.0, 1.0), warp)[0])
        return base

    @staticmethod
    def log_shape_inverse(w, gamma: float, rho: float) -> np.ndarray:
        """``ln`` of ``shape_inverse`` without warp, ``gamma ln(-ln(1 - rho w) / rho)``, on
        ``w`` in (0, 1): the form ``clblur.study`` fits by least squares (the warp adds
        ``c @ warp_basis(w)`` to it)."""
        return gamma * np.log(-np.log1p(-rho * w) / rho)

    def inverse(self, v):
        v = np.asarray(v, dtype=np.float64)
        w = np.clip((v - self.black) / (1.0 - self.black), 0.0, 1.0)
        x = self.shape_inverse(w, self.gamma, self.rho, self.warp)
        if not self.warp:
            return x
        # a strongly bent warp may turn back: keep the running maximum along the value axis
        flat = x.ravel()
        w = w.ravel()
        if flat.size < 2 or (w[1:] >= w[:-1]).all():
            # values already in order (a grid, a code table, one value): no sort needed
            np.maximum.accumulate(np.nan_to_num(flat, nan=0.0, copy=False), out=flat)
            return flat.reshape(x.shape)
        order = np.argsort(w, kind="stable")
        flat[order] = np.maximum.accumulate(np.nan_to_num(flat[order], nan=0.0))
        return flat.reshape(x.shape)

    def forward(self, x):
        if self.warp:
            return self.forward_slope(x)[0]
        x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
        w = -np.expm1(-self.rho * np.power(x, 1.0 / self.gamma)) / self.rho
        return self.black + (1.0 - self.black) * np.minimum(w, 1.0)

    def forward_slope(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Value and its slope ``dv/dx`` at exposures ``x`` (analytic without warp; with it, a
        sampled guess refined by Newton steps, ``_warped_forward_slope``)."""
        x = np.maximum(np.asarray(x, dtype=np.float64), 1e-12)
        scale = 1.0 - self.black
        if not self.warp:
            root = np.power(x, 1.0 / self.gamma)
            w = -np.expm1(-self.rho * root) / self.rho
            slope = np.exp(-self.rho * root) * root / (self.gamma * x)
            over = w > 1.0
            return (self.black + scale * np.where(over, 1.0, w),
                    scale * np.where(over, 0.0, slope))
        v, slope = self._warped_forward_slope(x.ravel())
        return v.reshape(x.shape), slope.reshape(x.shape)

    def _warped_forward_slope(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The warped forward: cubic Hermite interpolation in ``ln x`` between nodes where
        value and slope are exact (``_log_nodes``), so value and slope are continuous in
        ``x`` and smooth in the parameters (a fit's finite differences and line searches
        stall on a piecewise-linear forward), at a few operations per pixel.  Below the
        first node and above the last the sampled forward and its segment slope are kept.
        """
        lo, step, w_n, m_n, gx = self._log_nodes()
        scale = 1.0 - self.black
        lx = np.log(x)
        u = (lx - lo) / step
        inside = (u >= 0.0) & (u <= w_n.size - 1)
        k = np.clip(u.astype(np.intp), 0, w_n.size - 2)
        t = np.clip(u - k, 0.0, 1.0)
        t2 = t * t
        t3 = t2 * t
        w0, w1, m0, m1 = w_n[k], w_n[k + 1], step * m_n[k], step * m_n[k + 1]
        w = ((2 * t3 - 3 * t2 + 1) * w0 + (t3 - 2 * t2 + t) * m0 + (3 * t2 - 2 * t3) * w1
             + (t3 - t2) * m1)
        dw_du = (6 * t2 - 6 * t) * (w0 - w1) + (3 * t2 - 4 * t + 1) * m0 + (3 * t2 - 2 * t) * m1
        slope_w = dw_du / (step * x)  # dw/dx = dw/du du/dlnx dlnx/dx
        # one Newton step on the log inverse: where the curve is nearly flat in ln x (a
        # shoulder about to turn back) the interpolant's error is squared away
        ins = np.flatnonzero(inside & (w > 1e-9) & (w < 1.0 - 1e-9))
        log_inv, d_log = self._log_inverse_and_slope(w[ins])
        ok = d_log > 0
        ins = ins[ok]
        w[ins] = np.clip(w[ins] - (log_inv[ok] - lx[ins]) / d_log[ok], 1e-12, 1.0 - 1e-12)
        slope_w[ins] = 1.0 / (x[ins] * d_log[ok])
        rest = np.flatnonzero(~inside)
        if rest.size:  # the sampled forward and its segment slope
            xr = x[rest]
            seg = np.clip(np.searchsorted(gx, xr, side="right") - 1, 0, gx.size - 2)
            w[rest] = (np.interp(xr, gx, _GRID) - self.black) / scale
            slope_w[rest] = np.where(xr < gx[-1], (_GRID[seg + 1] - _GRID[seg])
                                     / (gx[seg + 1] - gx[seg]), 0.0) / scale
        over = x >= gx[-1]
        return (self.black + scale * np.where(over, 1.0, w),
                scale * np.where(over, 0.0, slope_w))

    def _log_nodes(self) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
        """Nodes uniform in ``ln x`` (cached): start, step, the value above the black level
        and its slope ``dw / d ln x`` at each, and the sampled grid's exposures.

        Node values are the sampled forward refined by Newton steps on the log inverse;
        where the warp turns the curve back or Newton does not settle, the sampled value and
        a difference slope are kept, so the interpolant stays continuous.
        """
        cache = self.__dict__.get("_nodes")
        if cache is None:
            gx = self._grid_exposure()
            # from a hundredth of a code above the black level (the grid's first exposures
            # are 0 there) to the last finite grid exposure
            first = self.inverse(np.array([self.black + 4e-5 * (1.0 - self.black)]))[0]
            lo, hi = np.log(max(first, gx[1])), np.log(gx[-2])
            lx = np.linspace(lo, hi, _NODES)
            step = float(lx[1] - lx[0])
            scale = 1.0 - self.black
            w = (np.interp(np.exp(lx), gx, _GRID) - self.black) / scale
            sampled = w.copy()
            # Newton in ln w, where ln x is nearly linear (a power law's toe is exactly so),
            # at most six steps; it converges quadratically from the sampled guess, so it
            # stops once no node moves by more than _NEWTON_DONE (a fit builds a curve for
            # nearly every likelihood it evaluates: the steps were most of a study's time)
            z = np.log(np.clip(w, 1e-9, 1.0 - 1e-9))
            for _ in range(6):
                wz = np.exp(z)
                log_inv, d_log = self._log_inverse_and_slope(wz)
                d_z = d_log * wz
                ok = d_z > 0
                move = np.where(ok, (log_inv - lx) / np.where(ok, d_z, 1.0), 0.0)
                z = np.minimum(z - move, np.log(1.0 - 1e-12))
                if not np.abs(move).max() > _NEWTON_DONE:  # NaN steps: keep stepping
                    break
            wk = np.exp(z)
            log_inv, d_log = self._log_inverse_and_slope(wk)
            fine = (d_log > 0) & (np.abs(log_inv - lx) < 1e-9) & (wk > 1e-9)
            w = np.where(fine, wk, sampled)
            slope = np.where(fine, 1.0 / np.where(fine, d_log, 1.0), np.gradient(w, step))
            cache = (float(lo), step, w, slope, gx)
            object.__setattr__(self, "_nodes", cache)
        return cache

    def _log_inverse_and_slope(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``ln x(w)`` and ``d ln x / d w`` of the shape above the black level."""
        rho, gamma = self.rho, self.gamma
        inner = -np.log1p(-rho * w)
        log_inv = gamma * np.log(inner / rho)
        d_log = gamma * rho / ((1.0 - rho * w) * inner)
        if self.warp:
            warp, d_warp = _warp_series(w, self.warp, slope=True)
            log_inv, d_log = log_inv + warp, d_log + d_warp
        return log_inv, d_log

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
            raise InputError("polynomial response needs 2..13 finite coefficients "
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
            raise InputError(f"monotone spline needs K + 1 >= 3 knots and K log increments, got "
                             f"{u.size} and {th.size}")
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(th))):
            raise InputError("monotone spline parameters must be finite")
        if u[0] != 0.0 or u[-1] != 1.0 or np.any(np.diff(u) <= 0):
            raise InputError("monotone spline knots must increase strictly from 0 to 1")
        total = float(np.log(np.sum(np.exp(th - th.max()))) + th.max())
        if abs(total) > 1e-12:  # x_K = 1 (the exposure unit); a saved curve already has it
            th = th - total
        x = self.knot_exposures(th)
        self.knots, self.log_increments = u, th
        info = {"family": self.family, "knots": u.tolist(), "log_increments": th.tolist()}
        super().__init__(_strictly_increasing(x / x[-1]), u, meta={**info, **(meta or {})})

    param_names = property(lambda self: tuple(f"t{m}" for m in range(self.log_increments.size)))

    @staticmethod
    def knot_exposures(log_increments: np.ndarray) -> np.ndarray:
        """Unnormalised exposures at the knots, ``x_k = sum_{m <= k} exp(theta_m)``, ``x_0 = 0``.

        The one place the spline's parametrisation is written; ``clblur.calibration`` fits
        ``log_increments`` through it and ``clblur.study`` reads fitted curves through it.
        """
        return np.concatenate([[0.0], np.cumsum(np.exp(log_increments))])

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
