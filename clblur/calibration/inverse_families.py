"""Families fitted in the inverse direction, as their authors specify.

``polynomial`` (Mitsunaga & Nayar 1999: inverse response a polynomial with ``g(1) = 1``,
fitted on exposure ratios of consecutive images) and ``nonparametric`` (Debevec & Malik 1997:
a smooth free inverse on the code grid), both then made monotone and exported as ``Table``.

Conventions
-----------
``tau``: nominal relative exposures, longest = 1; values normalised to [0, 1].
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
from scipy.optimize import isotonic_regression, least_squares
from scipy.sparse.linalg import spsolve

from clblur.calibration.forward_families import (
    CURVE_LOW,
    TABLE_SIZE,
    TIME_PRIOR_SCALE,
    TIME_SIGMA,
    FamilyFit,
    _refined_tau,
    _table,
    time_deviation_basis,
)
from clblur.errors import InputError, InputTypeError
from clblur.responses import (
    Gamma,
    Polynomial,
    Table,
)

__all__ = ["PolynomialFamily", "NonparametricFamily", "TOE_MIN_POINTS", "fit_toe",
           "with_toe"]

# darker observations a toe needs; with fewer, the family's own extrapolation is kept
TOE_MIN_POINTS = 20
# the toe's power: from a quarter (a toe that lingers near the floor, film) to 8; a fitted
# power at either end means the darker observations do not hold it, nor its black level
TOE_EXPONENTS = (0.25, 8.0)


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
    fits_toe = True  # fitting.fit fits the curve below default_low on the darker samples

    def fit(self, samples, tau, *, full_scale, refine_times=False, order: int = 6,
            iterations: int = 30, **opts) -> FamilyFit:
        if opts:
            raise InputTypeError(f"unknown option(s) for the polynomial model: {sorted(opts)}")
        if not isinstance(order, (int, np.integer)) or not 1 <= order <= 12:
            raise InputError(f"polynomial order must be an integer in 1..12, got {order!r}")
        sorted_idx, pairs = _consecutive_pairs(samples, tau)
        ratios = tau[sorted_idx[:-1]] / tau[sorted_idx[1:]]
        nominal = ratios.copy()
        basis = time_deviation_basis(np.log(tau[sorted_idx])) if refine_times else None
        if sum(a.size for a, _ in pairs) <= order:
            raise InputError("too few samples valid in neighbouring exposures for the "
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


def _toe_points(curve: Table, samples, tau: np.ndarray, start: float):
    """(value, exposure) of every observation below ``start`` of a sample the curve reads.

    A sample's radiance is taken from its observations at ``start`` or above (where the
    fitted curve holds; geometric mean of ``g(v) / tau``); its darker observations then
    each give one point of the curve below its fitted range."""
    trusted = samples.valid & (samples.values >= start)
    dark = samples.valid & (samples.values < start)
    rows = trusted.any(axis=1) & dark.any(axis=1)
    log_e = np.log(np.maximum(curve.inverse(samples.values[rows]), 1e-300)) - np.log(tau)
    t = trusted[rows]
    radiance = np.exp(np.sum(np.where(t, log_e, 0.0), axis=1) / t.sum(axis=1))
    d = dark[rows]
    return samples.values[rows][d], (radiance[:, None] * tau[None, :])[d]


def fit_toe(curve: Table, samples, tau: np.ndarray, start: float) -> tuple[Table, dict | None]:
    """A free inverse curve below its fitted range, fitted on the darker observations.

    Neither free family models the black level, so they are fitted from ``start`` up, and
    below it their own formulas extrapolate freely: Debevec & Malik's ``ln g`` goes on as a
    straight line and never reaches zero, a polynomial bends wherever nothing holds it
    (measured on a linear 16-bit bracket with a black level of 1.6 % of full scale: the
    nonparametric curve put 7 % of the fitted exposure at the black level, and predicted a
    4-stop brighter image with an RMSE of 32 570 codes).  The toe is a black level and a power:
    ``v = b + (s - b) (x / x_s)**(1 / p)`` below ``s = start`` (continuous there), ``b`` and
    ``p`` fitted by least squares on code values to every observation below ``start`` of a
    sample that also has observations above it (their radiance read through the curve); the
    power is ``clblur.responses.Gamma``'s.  A linear sensor is ``p = 1`` at its black level;
    a gamma curve without one is ``b = 0``.

    Args:
        curve: the fitted curve, a ``Table`` on a value grid that starts at 0.
        samples: the sample set over the whole valid range (not only the fitted one).
        tau: the exposures the curve was fitted with.
        start: the lowest fitted value.

    Returns:
        The curve with the toe below ``start``, and the toe's ``{"black_level", "exponent",
        "points", "held", "start"}`` (``held``: the power lies inside ``TOE_EXPONENTS``, not at
        an end, where the data would not hold it; ``start``: where the toe takes over, above
        ``start`` where the curve holds no light there, ``_response_from``); the curve
        unchanged and None when fewer than ``TOE_MIN_POINTS`` observations lie below it.
    """
    start = _response_from(curve, start)
    if start is None:
        return curve, None
    v_dark, x_dark = _toe_points(curve, samples, tau, start)
    x_start = float(curve.inverse(start))
    keep = (x_dark > 0) & (x_dark < x_start)
    v_dark, x_dark = v_dark[keep], x_dark[keep]
    if v_dark.size < TOE_MIN_POINTS or not x_start > 0:
        return curve, None
    u = x_dark / x_start

    def residuals(theta):  # the power law of the toe, from b up to the curve at ``start``
        b, p = theta
        return b + (start - b) * Gamma(p).forward(u) - v_dark

    # start from the power through the origin with the curve's own slope at ``start``
    above = float(curve.inverse(min(start + 0.01, 1.0)))
    p0 = float(np.clip((above - x_start) / 0.01 * start / x_start, 0.5, 4.0))
    low, high = TOE_EXPONENTS
    sol = least_squares(residuals, x0=[0.0, p0], bounds=([0.0, low], [0.98 * start, high]))
    b, p = (float(t) for t in sol.x)
    value = curve.value
    below = value < start
    exposure = curve.exposure.copy()
    exposure[below] = x_start * Gamma(p).inverse((value[below] - b) / (start - b))
    toe = {"black_level": b, "exponent": p, "points": int(v_dark.size),
           "held": bool(low * 1.001 < p < high * 0.999), "start": start}
    meta = dict(curve.meta)
    meta["params"] = dict(meta.get("params", {}), toe=toe)
    return _table(exposure, value, meta.get("family", "table"), meta["params"]), toe


# exposure (of full scale's) below which a fitted table holds no light: where the family's
# formula fell to 0 or below and the table was clamped (its ramp is 1e-7)
_NO_LIGHT = 1e-6
# the highest value a toe may take over from a curve that holds no light below it
_TOE_HIGHEST = 0.5


def _response_from(curve: Table, start: float) -> float | None:
    """The lowest value at or above ``start`` where ``curve`` holds light, or None above
    ``_TOE_HIGHEST``.

    A polynomial through the origin fitted from 10 % of full scale up may reach 0 at the
    bottom of its range on a camera with a black level: Memorial's blue channel with the
    frames' moving pixels left out (``clblur.calibration.ghosts``) fell to -0.0003 at 10 %,
    the video-range camera ``cam_d`` to -0.001.  A toe starting there had no exposure to
    rise to, so none was fitted and every darker code read as no light (Memorial, 4 stops
    darker: 6.3 -> 9.0 DN); the toe now starts where the curve holds light."""
    if float(curve.inverse(start)) > _NO_LIGHT:
        return start
    v, x = curve.value, curve.exposure
    lit = np.flatnonzero((v >= start) & (x > _NO_LIGHT))
    if lit.size == 0 or v[lit[0]] > _TOE_HIGHEST:
        return None
    return float(v[lit[0]])


def with_toe(fitted: FamilyFit, samples, start: float) -> FamilyFit:
    """``fitted`` with ``fit_toe`` applied; the toe's two numbers join its parameters."""
    curve, toe = fit_toe(fitted.response, samples, fitted.tau, start)
    if toe is None:
        return fitted
    return dataclasses.replace(fitted, response=curve, params=dict(fitted.params, toe=toe),
                               n_shape_params=fitted.n_shape_params + 2)


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
    fits_toe = True  # fitting.fit fits the curve below default_low on the darker samples

    def fit(self, samples, tau, *, full_scale, refine_times=False, smoothness: float = 30.0,
            levels: int | None = None, time_sigma: float = TIME_SIGMA, **opts) -> FamilyFit:
        if opts:
            raise InputTypeError(f"unknown option(s) for the nonparametric model: {sorted(opts)}")
        if not smoothness > 0:
            raise InputError(f"smoothness must be positive, got {smoothness!r}")
        if not time_sigma > 0:
            raise InputError(f"time_sigma must be positive, got {time_sigma!r}")
        if levels is not None:
            n_lev = int(levels)
        else:  # one level per code value for uint8, 1024 bins for deeper or float images
            n_lev = min(int(full_scale) + 1, 1024) if full_scale > 1 else 256
        if n_lev < 16:
            raise InputError(f"levels must be at least 16, got {levels!r}")
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
