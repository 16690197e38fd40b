"""Response families fitted to calibration samples, one class per family.

Conventions
-----------
* Each family fits one response curve to a ``SampleSet`` (rows: samples, columns: exposures)
  given the nominal relative exposures ``tau`` (longest = 1).  The unknowns are the curve and
  one radiance per sample; the radiance scale and the exposure unit are the same degree of
  freedom, so every family fixes it by a convention stated on the class.
* The result is a ``FamilyFit``: a ``clblur.responses.Response`` (``Exp`` for the paper's
  family; a ``Table`` with ``meta = {"family", "params"}`` for the others, so ``clblur blur
  --response FILE`` runs them on the same kernel path), the family's parameters, the number of
  curve parameters and the exposures used (re-estimated when ``refine_times`` is set).
* ``exp``, ``exp-offset``, ``gamma-offset`` and ``emor`` are fitted in the *forward*
  direction: least squares on code values, the quantity the evaluation measures.
  ``polynomial`` (Mitsunaga & Nayar) and ``nonparametric`` (Debevec & Malik) are fitted in the
  inverse direction as their authors specify, then made monotone.
* ``refine_times`` (uncertain shutter times) re-estimates one exposure per image, tied to the
  nominal value by a Gaussian prior (``TIME_SIGMA`` in log units) with the mean and the
  overall trend of ``ln tau`` held at their nominal values (see ``time_deviation_basis``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.optimize import isotonic_regression, least_squares
from scipy.sparse.linalg import spsolve

from clblur.responses import Exp, Response, Table

TABLE_SIZE = 1024
# Default low end of the fitted values.  The offset families model the black level, so they
# see values down to just above code 0.  The free curves do not model it; near the black level
# (13..25 DN on the Memorial stack, and not constant from image to image) they would bend to
# follow its drift, so they are fitted from 10 % of full scale up (measured: held-out 4-stop
# RMSE 9.6 -> 5.6 DN for nonparametric on Memorial, docs/studies/memorial-calibration.md).
FLOOR_LOW = 0.02
CURVE_LOW = 0.1
# Uncertain shutter times: prior standard deviation of ln(tau) around the nominal value, and
# the residual size (log exposure for the inverse fits) a one-sigma time error is worth.
TIME_SIGMA = 0.1
TIME_PRIOR_SCALE = 0.02


@dataclass(frozen=True)
class FamilyFit:
    response: Response
    params: dict
    n_shape_params: int
    tau: np.ndarray  # relative exposures the curve was fitted with


def _strictly_increasing(y: np.ndarray) -> np.ndarray:
    """Monotone non-decreasing samples -> strictly increasing (tiny ramp, far below 1 DN)."""
    y = np.maximum.accumulate(y)
    span = max(float(y[-1] - y[0]), 1e-12)
    return y + np.linspace(0.0, 1e-7 * span, y.size)


def _table(exposure: np.ndarray, value: np.ndarray, family: str, params: dict) -> Table:
    """A Table with exposure scaled so the top sample is 1 (the scale is arbitrary).

    ``value`` must already be strictly increasing (it is always a grid here)."""
    x = _strictly_increasing(np.maximum(exposure, 0.0))
    return Table(x / x[-1], value,
                 meta={"family": family, "params": params})


def time_deviation_basis(log_tau: np.ndarray) -> np.ndarray:
    """Orthonormal columns spanning the exposure deviations that can be learnt.

    A common offset of ``ln tau`` is the radiance scale and a common stretch is the curve's
    exponent (``g -> g**a`` with ``tau -> tau**a`` fits equally well, down to the all-equal,
    flat-curve solution), so neither can come from the data: refined exposures are
    ``ln tau = ln tau_nominal + B z`` with ``B`` orthogonal to both (n x (n - 2)).
    """
    n = log_tau.size
    if n < 3:
        raise ValueError("refine_times needs at least 3 exposures")
    fixed = np.stack([np.ones(n), log_tau - log_tau.mean()], axis=1)
    q, _ = np.linalg.qr(fixed, mode="complete")
    return q[:, 2:]


def _n_time_params(tau: np.ndarray, refine_times: bool) -> int:
    return tau.size - 2 if refine_times else 0


def _refined_tau(tau: np.ndarray, basis: np.ndarray, z: np.ndarray) -> np.ndarray:
    t = tau * np.exp(basis @ z)
    return t / t.max()


class ForwardFamily:
    """A closed-form curve ``v = F(x; theta)`` fitted jointly with per-sample radiances.

    Exposure convention: ``x = E_p * tau_i`` with the curve's own unit (``k = 1`` for the
    exponentials, full scale at ``x = 1`` for the power law).
    """

    name = ""
    default_low = FLOOR_LOW
    theta0: tuple[float, ...] = ()
    lower: tuple[float, ...] = ()
    upper: tuple[float, ...] = ()

    def forward(self, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def inverse(self, v: np.ndarray, theta: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def named(self, theta: np.ndarray) -> dict:
        return {}

    def export(self, theta: np.ndarray) -> Response:
        raise NotImplementedError

    def fit(self, samples, tau: np.ndarray, *, full_scale: float, refine_times: bool = False,
            **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the {self.name} model: {sorted(opts)}")
        theta, log_e, log_tau = _joint_forward_fit(self, samples, tau, full_scale, refine_times)
        return FamilyFit(self.export(theta), self.named(theta),
                         len(self.theta0) + _n_time_params(tau, refine_times), np.exp(log_tau))


def _joint_forward_fit(family: ForwardFamily, samples, tau, full_scale, refine_times,
                       time_sigma: float = TIME_SIGMA):
    """Least squares on code values over (curve parameters, log radiance per sample[, log
    exposure per image]); returns ``(theta, log_e, log_tau)`` with ``max(tau) == 1``."""
    v, ok = samples.values, samples.valid
    n_s, n_e = v.shape
    m = len(family.theta0)
    theta0 = np.asarray(family.theta0, dtype=np.float64)
    log_tau0 = np.log(tau)
    with np.errstate(divide="ignore", invalid="ignore"):
        guess = np.log(np.maximum(family.inverse(np.clip(v, 1e-6, 1 - 1e-6), theta0), 1e-12))
    guess = guess - log_tau0[None, :]
    log_e0 = np.array([np.median(g[o]) for g, o in zip(guess, ok, strict=True)])
    log_e0 = np.where(np.isfinite(log_e0), log_e0, np.log(1e-12))
    pi, ii = np.nonzero(ok)
    target = v[pi, ii]
    basis = time_deviation_basis(log_tau0) if refine_times else np.zeros((n_e, 0))
    n_t = basis.shape[1]
    prior_w = 1.0 / time_sigma  # a one-sigma deviation costs as much as a 1-DN residual

    def unpack(p):
        return p[:m], p[m:m + n_s], log_tau0 + basis @ p[m + n_s:]

    def residuals(p):
        theta, log_e, lt = unpack(p)
        r = (family.forward(np.exp(log_e[pi] + lt[ii]), theta) - target) * full_scale
        return np.concatenate([r, prior_w * p[m + n_s:]]) if n_t else r

    n_res = target.size + n_t
    rows = np.arange(target.size)
    blocks = [sp.csr_matrix((np.ones(target.size), (rows, pi)), shape=(n_res, n_s))]
    if m:
        blocks.insert(0, sp.csr_matrix(np.vstack([np.ones((target.size, m)),
                                                  np.zeros((n_t, m))])))
    if n_t:
        blocks.append(sp.csr_matrix(np.ones((n_res, n_t))))
    sparsity = sp.hstack(blocks).tocsr()
    p0 = np.concatenate([theta0, log_e0, np.zeros(n_t)])
    lower = np.concatenate([family.lower, np.full(n_s + n_t, -np.inf)])
    upper = np.concatenate([family.upper, np.full(n_s + n_t, np.inf)])
    sol = least_squares(residuals, p0, jac_sparsity=sparsity, bounds=(lower, upper),
                        method="trf", tr_solver="lsmr", x_scale="jac", max_nfev=200)
    theta, log_e, log_tau = unpack(sol.x)
    shift = log_tau.max()  # keep the longest exposure at 1; radiances absorb the shift
    return theta, log_e + shift, log_tau - shift


class ExpFamily(ForwardFamily):
    """The paper's Eq. 3, ``v = 1 - exp(-x)``: no shape parameter once k is absorbed in x."""

    name = "exp"

    def forward(self, x, theta):
        return -np.expm1(-x)

    def inverse(self, v, theta):
        return -np.log1p(-v)

    def export(self, theta):
        return Exp(1.0)  # k is set on the paper's normalised axis by clblur.calibration.fit


class ExpOffsetFamily(ForwardFamily):
    """Eq. 3 above a black level ``b``: ``v = b + (1 - b)(1 - exp(-x))``."""

    name = "exp-offset"
    theta0, lower, upper = (0.02,), (0.0,), (0.5,)

    def forward(self, x, theta):
        b = theta[0]
        return b - (1.0 - b) * np.expm1(-x)

    def inverse(self, v, theta):
        b = theta[0]
        return -np.log1p(-np.clip((v - b) / (1.0 - b), 0.0, 1.0))

    def named(self, theta):
        return {"black_level": float(theta[0])}

    def export(self, theta):
        b = float(theta[0])
        v = np.linspace(b, 1.0 - 1e-6, TABLE_SIZE)
        return _table(self.inverse(v, theta), v, self.name, self.named(theta))


class GammaOffsetFamily(ForwardFamily):
    """A power law above a black level: ``v = b + (1 - b) min(x, 1) ** (1 / gamma)``."""

    name = "gamma-offset"
    theta0, lower, upper = (0.02, 2.2), (0.0, 0.2), (0.5, 10.0)

    def forward(self, x, theta):
        b, g = theta
        return b + (1.0 - b) * np.power(np.clip(x, 0.0, 1.0), 1.0 / g)

    def inverse(self, v, theta):
        b, g = theta
        return np.power(np.clip((v - b) / (1.0 - b), 0.0, 1.0), g)

    def named(self, theta):
        return {"black_level": float(theta[0]), "gamma": float(theta[1])}

    def export(self, theta):
        b = float(theta[0])
        v = np.linspace(b, 1.0, TABLE_SIZE)
        return _table(self.inverse(v, theta), v, self.name, self.named(theta))


def _consecutive_pairs(samples, tau):
    """(v_dark, v_bright, ratio index) for every sample valid in two neighbouring exposures."""
    order = np.argsort(tau)
    out = []
    for q in range(order.size - 1):
        a, b = order[q], order[q + 1]
        both = samples.valid[:, a] & samples.valid[:, b]
        out.append((samples.values[both, a], samples.values[both, b]))
    return order, out


class PolynomialFamily:
    """Mitsunaga & Nayar 1999: inverse response ``g(v) = sum_n c_n v**n`` with ``g(1) = 1``.

    ``c_0`` is fixed at 0 (no exposure at code 0): with a free constant the exposure-domain
    error is minimised by flattening the curve wherever the samples are sparse (measured on
    the Memorial stack: non-monotone curves and held-out errors near 100 DN).
    Minimises ``sum (g(v_q) - R_q g(v_q+1))**2`` over neighbouring exposures; with
    ``refine_times`` the ratios ``R_q`` are re-estimated from the curve and the fit repeated.
    Exposure convention: full scale at exposure 1.
    """

    name = "polynomial"
    default_low = CURVE_LOW

    def fit(self, samples, tau, *, full_scale, refine_times=False, order: int = 6,
            iterations: int = 30, **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the polynomial model: {sorted(opts)}")
        if not isinstance(order, (int, np.integer)) or not 1 <= order <= 12:
            raise ValueError(f"polynomial order must be an integer in 1..12, got {order!r}")
        sorted_idx, pairs = _consecutive_pairs(samples, tau)
        ratios = tau[sorted_idx[:-1]] / tau[sorted_idx[1:]]
        nominal = ratios.copy()
        basis = time_deviation_basis(np.log(tau[sorted_idx])) if refine_times else None
        if sum(a.size for a, _ in pairs) <= order:
            raise ValueError("too few samples valid in neighbouring exposures for the "
                             f"polynomial model of order {order}")
        powers = np.arange(1, order + 1)
        coef = None
        for _ in range(iterations if refine_times else 1):
            rows, rhs = [], []
            for (va, vb), r in zip(pairs, ratios, strict=True):
                d = va[:, None] ** powers - r * vb[:, None] ** powers
                rows.append(d[:, :-1] - d[:, -1:])
                rhs.append(-d[:, -1])
            c, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
            coef = np.concatenate([[0.0], c, [1.0 - c.sum()]])
            if not refine_times:
                break
            new = np.array([_ratio(coef, va, vb, r) for (va, vb), r
                            in zip(pairs, ratios, strict=True)])
            new = _project_ratios(new, nominal, basis)
            done = np.max(np.abs(np.log(new / ratios))) < 1e-6
            ratios = new
            if done:
                break
        tau_fit = np.empty_like(tau)
        tau_fit[sorted_idx] = np.exp(_log_tau_from_ratios(ratios))
        v = np.linspace(0.0, 1.0, TABLE_SIZE)
        g = np.polyval(coef[::-1], v)
        params = {"order": int(order), "coefficients": coef.tolist()}
        if refine_times:
            params["exposure_ratios"] = ratios.tolist()
        return FamilyFit(_table(g, v, self.name, params), params,
                         order + (basis.shape[1] if refine_times else 0), tau_fit)


def _log_tau_from_ratios(ratios: np.ndarray) -> np.ndarray:
    """Neighbour ratios (ascending exposures) -> ln tau with the longest at 0."""
    return np.concatenate([np.cumsum(np.log(ratios)[::-1])[::-1], [0.0]])


def _project_ratios(ratios, nominal, basis) -> np.ndarray:
    """Keep only the learnable part of the ratio update (see ``time_deviation_basis``)."""
    dev = _log_tau_from_ratios(ratios) - _log_tau_from_ratios(nominal)
    log_tau = _log_tau_from_ratios(nominal) + basis @ (basis.T @ dev)
    return np.exp(-np.diff(log_tau))


def _ratio(coef, va, vb, fallback):
    ga, gb = np.polyval(coef[::-1], va), np.polyval(coef[::-1], vb)
    ok = (ga > 0) & (gb > 0)
    return float(np.mean(ga[ok] / gb[ok])) if ok.sum() >= 3 else float(fallback)


def _hat(v: np.ndarray) -> np.ndarray:
    """Debevec & Malik's hat weight on normalised values, floored so no row vanishes."""
    return np.maximum(np.minimum(v, 1.0 - v) * 2.0, 0.02)


class NonparametricFamily:
    """Debevec & Malik 1997: ``ln g`` at every code level with a smoothness term, made monotone.

    Solves ``w(v)(ln g(v) - ln E_p - ln tau_i) = 0`` and ``lam w(z) (ln g)''(z) = 0`` jointly
    (``ln g`` interpolated linearly between levels), then projects ``ln g`` onto
    non-decreasing sequences (isotonic regression).  With ``refine_times`` the ``ln tau_i`` are
    unknowns too, tied to the nominal times by a Gaussian prior of ``time_sigma`` (log units;
    the prior also fixes the ``g -> g**a, tau -> tau**a`` ambiguity).  Exposure convention:
    full scale at 1.
    """

    name = "nonparametric"
    default_low = CURVE_LOW

    def fit(self, samples, tau, *, full_scale, refine_times=False, smoothness: float = 30.0,
            levels: int | None = None, time_sigma: float = TIME_SIGMA, **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the nonparametric model: {sorted(opts)}")
        if not smoothness > 0:
            raise ValueError(f"smoothness must be positive, got {smoothness!r}")
        if not time_sigma > 0:
            raise ValueError(f"time_sigma must be positive, got {time_sigma!r}")
        if levels is not None:
            n_lev = int(levels)
        else:  # one level per code value for uint8, 1024 bins for deeper or float images
            n_lev = min(int(full_scale) + 1, 1024) if full_scale > 1 else 256
        if n_lev < 16:
            raise ValueError(f"levels must be at least 16, got {levels!r}")
        v, ok = samples.values, samples.valid
        n_s, n_e = v.shape
        basis = time_deviation_basis(np.log(tau)) if refine_times else np.zeros((n_e, 0))
        n_t = basis.shape[1]
        n_var = n_lev + n_s + n_t
        pi, ii = np.nonzero(ok)
        pos = v[pi, ii] * (n_lev - 1)
        z0 = np.clip(np.floor(pos).astype(int), 0, n_lev - 2)
        a = pos - z0
        w = _hat(v[pi, ii])
        r = np.arange(pi.size)
        cols = [z0, z0 + 1, n_lev + pi]
        vals = [w * (1 - a), w * a, -w]
        data = sp.csr_matrix((np.concatenate(vals), (np.tile(r, len(cols)),
                                                     np.concatenate(cols))),
                             shape=(pi.size, n_var))
        if n_t:  # ln tau_i = nominal + (B z)_i: dense coefficients on the n - 2 unknowns z
            data = data + sp.hstack([sp.csr_matrix((pi.size, n_lev + n_s)),
                                     sp.csr_matrix(-w[:, None] * basis[ii])]).tocsr()
        zc = np.arange(1, n_lev - 1)
        # second differences shrink with the level spacing squared; keep lam per uint8 step
        ws = smoothness * _hat(zc / (n_lev - 1)) * ((n_lev - 1) / 255.0) ** 2
        rs = np.arange(zc.size)
        smooth = sp.csr_matrix(
            (np.concatenate([ws, -2 * ws, ws]),
             (np.concatenate([rs, rs, rs]), np.concatenate([zc - 1, zc, zc + 1]))),
            shape=(zc.size, n_var))
        blocks = [data, smooth, sp.csr_matrix(([1.0], ([0], [n_lev // 2])), shape=(1, n_var))]
        rhs = [w * np.log(tau[ii]), np.zeros(zc.size + 1)]
        if n_t:
            blocks.append(sp.hstack([sp.csr_matrix((n_t, n_lev + n_s)),
                                     TIME_PRIOR_SCALE / time_sigma * sp.identity(n_t)]))
            rhs.append(np.zeros(n_t))
        mat = sp.vstack(blocks).tocsr()
        sol = spsolve((mat.T @ mat).tocsc(), mat.T @ np.concatenate(rhs))
        log_g = sol[:n_lev]
        tau_fit = _refined_tau(tau, basis, sol[n_lev + n_s:])
        counts = np.bincount(np.clip(np.rint(pos).astype(int), 0, n_lev - 1),
                             minlength=n_lev).astype(float)
        log_g = isotonic_regression(log_g, weights=counts + 1.0).x
        value = np.arange(n_lev) / (n_lev - 1)
        params = {"smoothness": float(smoothness), "levels": n_lev}
        if n_t:
            params["relative_exposures"] = tau_fit.tolist()
        return FamilyFit(_table(np.exp(log_g - log_g[-1]), value, self.name, params), params,
                         n_lev - 1 + n_t, tau_fit)


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
        return cls(grid, mean, comps)


class _EmorCurve(ForwardFamily):
    name = "emor"

    def __init__(self, basis: EmorBasis, components: int):
        self.basis, self.m = basis, components
        self.theta0 = (0.0,) * components
        self.lower, self.upper = (-np.inf,) * components, (np.inf,) * components

    def curve(self, theta) -> np.ndarray:
        return self.basis.mean + np.asarray(theta) @ self.basis.components[:self.m]

    def forward(self, x, theta):
        return np.interp(x, self.basis.grid, self.curve(theta))

    def inverse(self, v, theta):
        f = _strictly_increasing(np.clip(self.curve(theta), 0.0, 1.0))
        return np.interp(v, f, self.basis.grid)

    def named(self, theta):
        return {"components": self.m, "coefficients": [float(t) for t in theta]}

    def export(self, theta):
        f = _strictly_increasing(np.clip(self.curve(theta), 0.0, 1.0))
        f = (f - f[0]) / (f[-1] - f[0])  # f(0) = 0, f(1) = 1 as in the basis
        return _table(self.basis.grid, f, self.name, self.named(theta))


class EmorFamily:
    """Grossberg & Nayar's EMoR: mean curve plus ``components`` principal components.

    Fitted in the forward direction like the closed-form families (coefficients and one
    radiance per sample, least squares on code values).  Exposure convention: full scale at
    exposure 1, as in the basis.
    """

    name = "emor"
    default_low = CURVE_LOW

    def fit(self, samples, tau, *, full_scale, refine_times=False, components: int = 5,
            emor_dir=None, **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the emor model: {sorted(opts)}")
        if not isinstance(components, (int, np.integer)) or not 1 <= components <= 25:
            raise ValueError(f"EMoR components must be an integer in 1..25, got {components!r}")
        curve = _EmorCurve(EmorBasis.load(emor_dir), int(components))
        theta, _, log_tau = _joint_forward_fit(curve, samples, tau, full_scale, refine_times)
        return FamilyFit(curve.export(theta), curve.named(theta),
                         int(components) + _n_time_params(tau, refine_times), np.exp(log_tau))


FAMILIES = {f.name: f for f in (ExpFamily(), ExpOffsetFamily(), GammaOffsetFamily(),
                                PolynomialFamily(), NonparametricFamily(), EmorFamily())}
MODELS = tuple(FAMILIES)
