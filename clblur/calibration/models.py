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
* ``exp``, ``exp-offset`` and ``gamma-offset`` are fitted in the *forward* direction: least
  squares on code values, the quantity the evaluation measures.  ``polynomial`` (Mitsunaga &
  Nayar), ``nonparametric`` (Debevec & Malik) and ``emor`` (Grossberg & Nayar) are fitted in the
  inverse direction as their authors specify, then made monotone.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.optimize import isotonic_regression, least_squares
from scipy.sparse.linalg import lsqr, spsolve

from clblur.responses import Exp, Response, Table

TABLE_SIZE = 1024


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


def _not_supported(family: str, refine_times: bool) -> None:
    if refine_times:
        raise ValueError(f"refine_times is not supported by the {family} model; use exp, "
                         "exp-offset, gamma-offset or polynomial")


class ForwardFamily:
    """A closed-form curve ``v = F(x; theta)`` fitted jointly with per-sample radiances.

    Exposure convention: ``x = E_p * tau_i`` with the curve's own unit (``k = 1`` for the
    exponentials, full scale at ``x = 1`` for the power law).
    """

    name = ""
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
        return FamilyFit(self.export(theta), self.named(theta), len(self.theta0),
                         np.exp(log_tau))


def _joint_forward_fit(family: ForwardFamily, samples, tau, full_scale, refine_times):
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
    free_tau = np.flatnonzero(np.arange(n_e) != int(np.argmax(tau))) if refine_times \
        else np.empty(0, int)
    n_t = free_tau.size

    def unpack(p):
        lt = log_tau0.copy()
        lt[free_tau] = p[m + n_s:]
        return p[:m], p[m:m + n_s], lt

    def residuals(p):
        theta, log_e, lt = unpack(p)
        return (family.forward(np.exp(log_e[pi] + lt[ii]), theta) - target) * full_scale

    rows = np.arange(target.size)
    pattern = [sp.csr_matrix(np.ones((target.size, m))) if m else None,
               sp.csr_matrix((np.ones(target.size), (rows, pi)), shape=(target.size, n_s))]
    if n_t:
        col = np.full(n_e, -1)
        col[free_tau] = np.arange(n_t)
        hit = col[ii] >= 0
        pattern.append(sp.csr_matrix((np.ones(hit.sum()), (rows[hit], col[ii][hit])),
                                     shape=(target.size, n_t)))
    sparsity = sp.hstack([p for p in pattern if p is not None]).tocsr()
    p0 = np.concatenate([theta0, log_e0, log_tau0[free_tau]])
    lower = np.concatenate([family.lower, np.full(n_s + n_t, -np.inf)])
    upper = np.concatenate([family.upper, np.full(n_s + n_t, np.inf)])
    sol = least_squares(residuals, p0, jac_sparsity=sparsity, bounds=(lower, upper),
                        method="trf", tr_solver="lsmr", x_scale="jac", max_nfev=200)
    return unpack(sol.x)


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

    Minimises ``sum (g(v_q) - R_q g(v_q+1))**2`` over neighbouring exposures; with
    ``refine_times`` the ratios ``R_q`` are re-estimated from the curve and the fit repeated.
    Exposure convention: full scale at exposure 1.
    """

    name = "polynomial"

    def fit(self, samples, tau, *, full_scale, refine_times=False, order: int = 6,
            iterations: int = 30, **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the polynomial model: {sorted(opts)}")
        if not isinstance(order, (int, np.integer)) or not 1 <= order <= 12:
            raise ValueError(f"polynomial order must be an integer in 1..12, got {order!r}")
        sorted_idx, pairs = _consecutive_pairs(samples, tau)
        ratios = tau[sorted_idx[:-1]] / tau[sorted_idx[1:]]
        if sum(a.size for a, _ in pairs) <= order:
            raise ValueError("too few samples valid in neighbouring exposures for the "
                             f"polynomial model of order {order}")
        powers = np.arange(order + 1)
        coef = None
        for _ in range(iterations if refine_times else 1):
            rows, rhs = [], []
            for (va, vb), r in zip(pairs, ratios, strict=True):
                d = va[:, None] ** powers - r * vb[:, None] ** powers
                rows.append(d[:, :-1] - d[:, -1:])
                rhs.append(-d[:, -1])
            c, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
            coef = np.append(c, 1.0 - c.sum())
            if not refine_times:
                break
            new = np.array([_ratio(coef, va, vb, r) for (va, vb), r
                            in zip(pairs, ratios, strict=True)])
            done = np.max(np.abs(np.log(new / ratios))) < 1e-6
            ratios = new
            if done:
                break
        tau_fit = np.empty_like(tau)
        tau_fit[sorted_idx] = np.concatenate([np.cumprod(ratios[::-1])[::-1], [1.0]])
        v = np.linspace(0.0, 1.0, TABLE_SIZE)
        g = np.polyval(coef[::-1], v)
        params = {"order": int(order), "coefficients": coef.tolist()}
        if refine_times:
            params["exposure_ratios"] = ratios.tolist()
        return FamilyFit(_table(g, v, self.name, params), params,
                         order + (ratios.size if refine_times else 0), tau_fit)


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
    non-decreasing sequences (isotonic regression).  Exposure convention: full scale at 1.
    """

    name = "nonparametric"

    def fit(self, samples, tau, *, full_scale, refine_times=False, smoothness: float = 30.0,
            levels: int | None = None, **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the nonparametric model: {sorted(opts)}")
        _not_supported(self.name, refine_times)
        if not smoothness > 0:
            raise ValueError(f"smoothness must be positive, got {smoothness!r}")
        if levels is not None:
            n_lev = int(levels)
        else:  # one level per code value for uint8, 1024 bins for deeper or float images
            n_lev = min(int(full_scale) + 1, 1024) if full_scale > 1 else 256
        if n_lev < 16:
            raise ValueError(f"levels must be at least 16, got {levels!r}")
        v, ok = samples.values, samples.valid
        n_s = v.shape[0]
        pi, ii = np.nonzero(ok)
        pos = v[pi, ii] * (n_lev - 1)
        z0 = np.clip(np.floor(pos).astype(int), 0, n_lev - 2)
        a = pos - z0
        w = _hat(v[pi, ii])
        n_obs = pi.size
        r = np.arange(n_obs)
        data = sp.csr_matrix(
            (np.concatenate([w * (1 - a), w * a, -w]),
             (np.concatenate([r, r, r]), np.concatenate([z0, z0 + 1, n_lev + pi]))),
            shape=(n_obs, n_lev + n_s))
        zc = np.arange(1, n_lev - 1)
        # second differences shrink with the level spacing squared; keep lam per uint8 step
        ws = smoothness * _hat(zc / (n_lev - 1)) * ((n_lev - 1) / 255.0) ** 2
        rs = np.arange(zc.size)
        smooth = sp.csr_matrix(
            (np.concatenate([ws, -2 * ws, ws]),
             (np.concatenate([rs, rs, rs]), np.concatenate([zc - 1, zc, zc + 1]))),
            shape=(zc.size, n_lev + n_s))
        anchor = sp.csr_matrix(([1.0], ([0], [n_lev // 2])), shape=(1, n_lev + n_s))
        mat = sp.vstack([data, smooth, anchor]).tocsr()
        rhs = np.concatenate([w * np.log(tau[ii]), np.zeros(zc.size + 1)])
        sol = spsolve((mat.T @ mat).tocsc(), mat.T @ rhs)
        log_g = sol[:n_lev]
        counts = np.bincount(np.clip(np.rint(pos).astype(int), 0, n_lev - 1),
                             minlength=n_lev).astype(float)
        log_g = isotonic_regression(log_g, weights=counts + 1.0).x
        value = np.arange(n_lev) / (n_lev - 1)
        params = {"smoothness": float(smoothness), "levels": n_lev}
        return FamilyFit(_table(np.exp(log_g - log_g[-1]), value, self.name, params), params,
                         n_lev - 1, tau.copy())


@dataclass(frozen=True)
class EmorBasis:
    """Grossberg & Nayar's inverse EMoR: ``g(B) = g0(B) + sum_m c_m hinv_m(B)`` on grid B."""

    grid: np.ndarray
    mean: np.ndarray
    components: np.ndarray  # (25, 1024)

    @classmethod
    def load(cls, folder: str | os.PathLike | None = None) -> EmorBasis:
        from clblur.data import data_dir

        if folder is None:
            root = data_dir()
            if root is None:
                raise ValueError("EMoR basis not found: pass emor_dir= (--emor-dir) or set "
                                 "CLBLUR_DATA to a folder holding crf/invemor.txt")
            folder = root / "crf"
        path = Path(folder) / "invemor.txt"
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
            grid, mean = np.array(blocks["B"]), np.array(blocks["g0"])
            comps = np.array([blocks[f"hinv({m})"] for m in range(1, 26)])
        except KeyError as e:
            raise ValueError(f"{path}: missing block {e.args[0]!r}") from None
        if grid.size != mean.size or comps.shape[1] != grid.size:
            raise ValueError(f"{path}: blocks of different lengths")
        return cls(grid, mean, comps)


class EmorFamily:
    """Grossberg & Nayar's EMoR: mean inverse curve plus ``components`` principal components.

    Linear least squares for the coefficients and the radiances on
    ``g(v_pi) = E_p tau_i``, each row divided by the current ``g(v_pi)`` (relative error,
    re-weighted twice) and hat-weighted.  Exposure convention: ``g(1) = 1``.
    """

    name = "emor"

    def fit(self, samples, tau, *, full_scale, refine_times=False, components: int = 5,
            emor_dir=None, **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the emor model: {sorted(opts)}")
        _not_supported(self.name, refine_times)
        if not isinstance(components, (int, np.integer)) or not 1 <= components <= 25:
            raise ValueError(f"EMoR components must be an integer in 1..25, got {components!r}")
        basis = EmorBasis.load(emor_dir)
        v, ok = samples.values, samples.valid
        n_s = v.shape[0]
        pi, ii = np.nonzero(ok)
        vv = v[pi, ii]
        g0 = np.interp(vv, basis.grid, basis.mean)
        h = np.stack([np.interp(vv, basis.grid, c) for c in basis.components[:components]], 1)
        coef = np.zeros(components)
        r = np.arange(pi.size)
        for _ in range(3):
            scale = _hat(vv) / np.maximum(g0 + h @ coef, 1e-3)
            dense = sp.csr_matrix(h * scale[:, None])
            rad = sp.csr_matrix((-tau[ii] * scale, (r, pi)), shape=(pi.size, n_s))
            mat = sp.hstack([dense, rad]).tocsr()
            sol = lsqr(mat, -g0 * scale, atol=1e-12, btol=1e-12, iter_lim=20000)[0]
            coef = sol[:components]
        g = basis.mean + coef @ basis.components[:components]
        params = {"components": int(components), "coefficients": coef.tolist()}
        return FamilyFit(_table(g, basis.grid, self.name, params), params, components,
                         tau.copy())


FAMILIES = {f.name: f for f in (ExpFamily(), ExpOffsetFamily(), GammaOffsetFamily(),
                                PolynomialFamily(), NonparametricFamily(), EmorFamily())}
MODELS = tuple(FAMILIES)
