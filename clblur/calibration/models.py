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

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import isotonic_regression, least_squares
from scipy.sparse.linalg import spsolve

from clblur.responses import (
    Emor,
    EmorBasis,
    Exp,
    ExpOffset,
    GammaOffset,
    MonotoneSpline,
    Polynomial,
    Response,
    Table,
    default_knots,
)

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
        return Exp(1.0).forward(x)

    def inverse(self, v, theta):
        return Exp(1.0).inverse(v)

    def export(self, theta):
        return Exp(1.0)  # k is set on the paper's normalised axis by clblur.calibration.fit


class ExpOffsetFamily(ForwardFamily):
    """Eq. 3 above a black level ``b``: ``v = b + (1 - b)(1 - exp(-x))``."""

    name = "exp-offset"
    theta0, lower, upper = (0.02,), (0.0,), (0.5,)

    def curve(self, theta) -> ExpOffset:
        return ExpOffset(black=float(theta[0]), k=1.0)

    def forward(self, x, theta):
        return self.curve(theta).forward(x)

    def inverse(self, v, theta):
        return self.curve(theta).inverse(v)

    def named(self, theta):
        return {"black_level": float(theta[0])}

    def export(self, theta):
        return _export(self.curve(theta), self.name, self.named(theta))


class GammaOffsetFamily(ForwardFamily):
    """A power law above a black level: ``v = b + (1 - b) min(x, 1) ** (1 / gamma)``."""

    name = "gamma-offset"
    theta0, lower, upper = (0.02, 2.2), (0.0, 0.2), (0.5, 10.0)

    def curve(self, theta) -> GammaOffset:
        return GammaOffset(black=float(theta[0]), gamma=float(theta[1]))

    def forward(self, x, theta):
        return self.curve(theta).forward(x)

    def inverse(self, v, theta):
        return self.curve(theta).inverse(v)

    def named(self, theta):
        return {"black_level": float(theta[0]), "gamma": float(theta[1])}

    def export(self, theta):
        return _export(self.curve(theta), self.name, self.named(theta))


def _export(curve: Response, family: str, params: dict) -> Table:
    """A fitted family as the dense ``Table`` the kernels run (exposure top scaled to 1)."""
    t = curve.as_table(TABLE_SIZE)
    return _table(t.exposure, t.value, family, params)


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
        g = Polynomial(tuple(coef)).inverse(v)
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
    curve = Polynomial(tuple(coef))
    ga, gb = curve.inverse(va), curve.inverse(vb)
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


class _EmorCurve(ForwardFamily):
    name = "emor"

    def __init__(self, basis: EmorBasis, components: int, emor_dir=None):
        self.basis, self.m, self.emor_dir = basis, components, emor_dir
        self.theta0 = (0.0,) * components
        self.lower, self.upper = (-np.inf,) * components, (np.inf,) * components

    def curve(self, theta) -> Emor:
        return Emor(tuple(theta), emor_dir=self.emor_dir)

    def forward(self, x, theta):
        # unconstrained during the fit (the least-squares steps need a smooth model)
        return np.interp(x, self.basis.grid, self.curve(theta).raw_curve())

    def inverse(self, v, theta):
        return self.curve(theta).inverse(v)

    def named(self, theta):
        return {"components": self.m, "coefficients": [float(t) for t in theta]}

    def export(self, theta):
        c = self.curve(theta)
        return _table(self.basis.grid, c.forward(self.basis.grid), self.name, self.named(theta))


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
        curve = _EmorCurve(EmorBasis.load(emor_dir), int(components),
                           None if emor_dir is None else str(emor_dir))
        theta, _, log_tau = _joint_forward_fit(curve, samples, tau, full_scale, refine_times)
        return FamilyFit(curve.export(theta), curve.named(theta),
                         int(components) + _n_time_params(tau, refine_times), np.exp(log_tau))


# Pixel values the cross-exposure fit uses, in codes of an 8-bit scale: everything not clipped
# at either end (the same range the evaluation scores).
PAIR_LOW_CODE, PAIR_HIGH_CODE = 2.5, 252.5


class SplineFamily:
    """A free monotone curve fitted on the cross-exposure prediction error directly.

    The objective is Mitsunaga & Nayar's (1999) ratio idea taken to code values: for every
    fitting pixel valid in exposures ``i`` and ``j`` (at most ``max_gap`` stops apart, both
    orders), predict code ``j`` from code ``i`` through the curve,
    ``v_j = I(I^-1(v_i) tau_j / tau_i)``, and minimise the squared error in code values.
    The curve is a ``clblur.responses.MonotoneSpline`` (``knots`` segments, denser towards
    black, exposure 0 at value 0), so the toe is modelled: codes at and below the black level
    get near-zero exposure increments, and the dark noise floor is what the curve predicts
    for a very dark source.  A small second-difference penalty (``smoothness``, on the log
    increments) keeps stretches without data smooth.

    Samples are single random pixels (``Sampling.pixels``), edges included, so the fit sees
    the values it is scored on; the scored pixels are disjoint from them.  Pairs are pooled
    by (source value, exposure ratio): the squared error of a pool is its count times the
    error of its mean target plus a constant, so the fit costs the same for any number of
    pixels.  Exposure convention: full scale at exposure 1.  Shutter times are taken as
    given (``refine_times`` does not apply).
    """

    name = "spline"
    default_low = PAIR_LOW_CODE / 255.0
    uses_pixels = True

    def fit(self, samples, tau, *, full_scale, refine_times=False, knots: int = 64,
            smoothness: float = 0.3, max_gap: float = 4.5, **opts) -> FamilyFit:
        if opts:
            raise TypeError(f"unknown option(s) for the spline model: {sorted(opts)}")
        if not isinstance(knots, (int, np.integer)) or not 4 <= knots <= 256:
            raise ValueError(f"spline knots must be an integer in 4..256, got {knots!r}")
        if not smoothness >= 0:
            raise ValueError(f"smoothness must be >= 0, got {smoothness!r}")
        src, mean, ratio, count = pooled_pairs(samples.values, samples.valid, tau, max_gap,
                                               full_scale)
        if src.size < knots:
            raise ValueError("too few pixel pairs valid in two exposures for the spline model "
                             f"({src.size} pools for {knots} knots)")
        u = default_knots(int(knots))
        theta = fit_cross_exposure(u, src, mean, ratio, np.sqrt(count) * full_scale,
                                   smoothness)
        curve = MonotoneSpline(u, theta)
        params = {"knots": int(knots), "smoothness": float(smoothness),
                  "pairs": int(count.sum()), "black_level": curve_black_level(curve)}
        curve.meta.update({"params": params})
        return FamilyFit(curve, params, int(knots) - 1, tau)


def curve_black_level(curve: Response, fraction: float = 1e-3) -> float:
    """The toe: the highest value whose exposure is below ``fraction`` of mid-scale's."""
    v = np.linspace(0.0, 1.0, 1021)
    x = np.asarray(curve.inverse(v))
    below = v[x <= fraction * float(curve.inverse(np.array([0.5]))[0])]
    return float(below[-1]) if below.size else 0.0


def pooled_pairs(values: np.ndarray, valid: np.ndarray, tau: np.ndarray, max_gap: float,
                 full_scale: float, levels: int = 1024):
    """Pool ordered exposure pairs of each sample by (source value, ratio).

    ``values``/``valid``: (P, n) normalised values and validity (see ``SampleSet``).  Returns
    ``(source value, mean target value, ratio tau_j / tau_i, count)`` per pool.  Source values
    are exact codes for 8-bit data and binned to ``levels`` otherwise.
    """
    n = values.shape[1]
    lo, hi = PAIR_LOW_CODE / 255.0, PAIR_HIGH_CODE / 255.0
    ok = valid & (values > lo) & (values < hi)
    bins = int(full_scale) + 1 if full_scale <= 255 else levels
    keys, targets = [], []
    pairs = [(i, j) for i in range(n) for j in range(n)
             if i != j and abs(np.log2(tau[j] / tau[i])) <= max_gap]
    if not pairs:
        return (np.zeros(0),) * 4
    # pairs with the same ratio (a bracket in whole stops) share pools: the residual depends
    # on the source value and the ratio only
    log_ratio = np.round([np.log2(tau[j] / tau[i]) for i, j in pairs], 6)
    ratios, which = np.unique(log_ratio, return_inverse=True)
    ratios = 2.0 ** ratios
    for r_index, (i, j) in zip(which, pairs, strict=True):
        both = ok[:, i] & ok[:, j]
        q = np.clip(np.rint(values[both, i] * (bins - 1)), 0, bins - 1).astype(np.int64)
        keys.append(q + bins * int(r_index))
        targets.append(values[both, j])
    key = np.concatenate(keys)
    tgt = np.concatenate(targets)
    uniq, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    mean = np.bincount(inv, weights=tgt) / count
    src = (uniq % bins) / (bins - 1)
    ratio = np.asarray(ratios)[uniq // bins]
    return src, mean, ratio, count.astype(np.float64)


def fit_cross_exposure(u: np.ndarray, src: np.ndarray, target: np.ndarray, ratio: np.ndarray,
                       weight: np.ndarray, smoothness: float,
                       theta0: np.ndarray | None = None) -> np.ndarray:
    """Log increments of the ``MonotoneSpline`` on knots ``u`` minimising
    ``sum weight^2 (I(I^-1(src) ratio) - target)^2`` (analytic Jacobian, trust region).

    Starts from a gamma-2.2 curve unless ``theta0`` is given; the sum of the increments is
    pinned softly (the exposure unit is free).
    """
    k = u.size - 1
    h = np.diff(u)
    a = np.clip(np.searchsorted(u, src, side="right") - 1, 0, k - 1)
    w = (src - u[a]) / h[a]
    m = np.arange(1, k + 1)
    d_src = (m[None, :] <= a[:, None]) + w[:, None] * (m[None, :] == a[:, None] + 1)
    diff2 = np.zeros((max(k - 2, 0), k))
    r = np.arange(k - 2)
    diff2[r, r], diff2[r, r + 1], diff2[r, r + 2] = 1.0, -2.0, 1.0

    def predict(th):
        x = np.concatenate([[0.0], np.cumsum(np.exp(th))])
        xi = x[a] + w * (x[a + 1] - x[a])
        z = ratio * xi
        b = np.clip(np.searchsorted(x, z, side="right") - 1, 0, k - 1)
        dx = np.maximum(x[b + 1] - x[b], 1e-300)
        t = np.clip((z - x[b]) / dx, 0.0, 1.0)
        return x, z, b, dx, u[b] + h[b] * t

    def residuals(th):
        v = predict(th)[-1]
        total = np.log(np.sum(np.exp(th)))
        return np.concatenate([weight * (v - target), smoothness * (diff2 @ th), [total]])

    def jacobian(th):
        x, z, b, dx, _ = predict(th)
        inside = z < x[-1]
        slope = np.where(inside, h[b] / dx, 0.0)
        jac = (slope * ratio)[:, None] * d_src
        left = np.where(inside, h[b] * (z - x[b + 1]) / dx**2, 0.0)
        right = np.where(inside, -h[b] * (z - x[b]) / dx**2, 0.0)
        jac += left[:, None] * (m[None, :] <= b[:, None])
        jac += right[:, None] * (m[None, :] <= b[:, None] + 1)
        e = np.exp(th)
        jac *= e[None, :] * weight[:, None]
        return np.vstack([jac, smoothness * diff2, (e / e.sum())[None, :]])

    if theta0 is None:
        x0 = u ** 2.2
        theta0 = np.log(np.maximum(np.diff(x0), 1e-6))
    # trial steps may overflow exp(); their non-finite cost rejects them
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _levenberg_marquardt(residuals, jacobian, np.asarray(theta0, dtype=np.float64))


def _levenberg_marquardt(residuals, jacobian, theta: np.ndarray, iterations: int = 200,
                         rtol: float = 1e-10) -> np.ndarray:
    """Damped Gauss-Newton on the normal equations (few parameters, many residuals: a
    K x K solve per step instead of an SVD of the whole Jacobian)."""
    r = residuals(theta)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        jac = jacobian(theta)
        a = jac.T @ jac
        g = jac.T @ r
        improved = False
        for _ in range(30):
            step = np.linalg.solve(a + lam * (np.diag(np.diag(a)) + 1e-12 * np.eye(a.shape[0])),
                                   -g)
            trial = theta + step
            r_new = residuals(trial)
            c_new = float(r_new @ r_new)
            if np.isfinite(c_new) and c_new < cost:
                improved = True
                break
            lam *= 4.0
        if not improved:
            break
        done = cost - c_new <= rtol * cost
        theta, r, cost, lam = trial, r_new, c_new, max(lam / 3.0, 1e-9)
        if done:
            break
    return theta


FAMILIES = {f.name: f for f in (ExpFamily(), ExpOffsetFamily(), GammaOffsetFamily(),
                                PolynomialFamily(), NonparametricFamily(), EmorFamily(),
                                SplineFamily())}
MODELS = tuple(FAMILIES)
