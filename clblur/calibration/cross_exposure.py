"""The free monotone spline fitted on cross-exposure prediction error.

``SplineFamily`` (the ``spline`` model) and the function it and ``clblur.study`` share,
``fit_cross_exposure``: a ``clblur.responses.MonotoneSpline`` whose log increments minimise the
code-value error of predicting one exposure from another (Mitsunaga & Nayar's 1999 ratio idea
taken to code values), solved by a small Levenberg-Marquardt loop.

Conventions
-----------
Values normalised to [0, 1]; ``ratio`` is the exposure ratio target / source; pixels clipped
at either end (outside ``PAIR_LOW_CODE``..``PAIR_HIGH_CODE`` of an 8-bit scale) are not used.
"""

from __future__ import annotations

import numpy as np

from clblur.calibration.forward_families import FamilyFit
from clblur.errors import InputError, InputTypeError
from clblur.responses import (
    Gamma,
    MonotoneSpline,
    Response,
    default_knots,
)

__all__ = ["SplineFamily", "curve_black_level", "pooled_pairs", "fit_cross_exposure",
           "PAIR_LOW_CODE", "PAIR_HIGH_CODE"]


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
    refines_times = False  # the times are taken as given (``fit`` ignores refine_times)

    def fit(self, samples, tau, *, full_scale, refine_times=False, knots: int = 64,
            smoothness: float = 0.3, max_gap: float = 4.5, **opts) -> FamilyFit:
        if opts:
            raise InputTypeError(f"unknown option(s) for the spline model: {sorted(opts)}")
        if not isinstance(knots, (int, np.integer)) or not 4 <= knots <= 256:
            raise InputError(f"spline knots must be an integer in 4..256, got {knots!r}")
        if not smoothness >= 0:
            raise InputError(f"smoothness must be >= 0, got {smoothness!r}")
        src, mean, ratio, count = pooled_pairs(samples.values, samples.valid, tau, max_gap,
                                               full_scale)
        if src.size < knots:
            raise InputError("too few pixel pairs valid in two exposures for the spline model "
                             f"({src.size} pools for {knots} knots)")
        u = default_knots(int(knots))
        theta = fit_cross_exposure(u, src, mean, ratio, np.sqrt(count) * full_scale,
                                   smoothness, pedestal=True)
        curve = MonotoneSpline(u, theta)
        params = {"knots": int(knots), "smoothness": float(smoothness),
                  "pairs": int(count.sum()), "black_level": curve_black_level(curve)}
        curve.meta.update({"params": params})
        return FamilyFit(curve, params, int(knots) - 1, tau)


def curve_black_level(curve: Response, fraction: float = 1e-3) -> float:
    """The toe: the highest value whose exposure is below ``fraction`` of mid-scale's.

    Found on a grid of 1021 values, then by bisection to 1e-7 of full scale: the grid alone
    is 64 codes of a 16-bit camera.
    """
    v = np.linspace(0.0, 1.0, 1021)
    x = np.asarray(curve.inverse(v))
    limit = fraction * float(curve.inverse(np.array([0.5]))[0])
    below = np.flatnonzero(x <= limit)
    if not below.size:
        return 0.0
    lo = float(v[below[-1]])
    if below[-1] + 1 == v.size:
        return lo
    hi = float(v[below[-1] + 1])  # the inverse is monotone: the level lies in [lo, hi)
    while hi - lo > 1e-7:
        mid = 0.5 * (lo + hi)
        if float(np.asarray(curve.inverse(np.array([mid])))[0]) <= limit:
            lo = mid
        else:
            hi = mid
    return lo


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
                       theta0: np.ndarray | None = None, pedestal: bool = False) -> np.ndarray:
    """Log increments of the ``MonotoneSpline`` on knots ``u`` minimising
    ``sum weight^2 (I(I^-1(src) ratio) - target)^2`` (analytic Jacobian, trust region).

    Starts from ``theta0``, else from the best of three power laws and, with ``pedestal``,
    a straight line above the black level the pairs imply (:func:`_pedestal`); the sum of
    the increments is pinned softly (the exposure unit is free).
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
        x = MonotoneSpline.knot_exposures(th)
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
        # The objective has degenerate local minima (a curve nearly flat below its last knot
        # predicts every target inside one segment); a display gamma, a straight line and a
        # steep power law start in different basins, and the lowest cost wins.  So does a
        # straight line above a black level read off the pairs themselves: a linear sensor
        # with a pedestal (raw data, 12 % of full scale) lies in a basin none of the three
        # reach, where the spline was left 10 - 29 codes off
        curves = [Gamma(g).inverse(u) for g in (2.2, 1.0, 4.0)]
        black = _pedestal(src, target, ratio) if pedestal else 0.0
        if black > 0.0:
            curves.append(np.maximum(u - black, 0.0))
        starts = [np.log(np.maximum(np.diff(c), 1e-6)) for c in curves]
    else:
        starts = [np.asarray(theta0, dtype=np.float64)]
    best, best_cost = None, np.inf
    # trial steps may overflow exp(); their non-finite cost rejects them
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for start in starts:
            theta = _levenberg_marquardt(residuals, jacobian, start)
            r = residuals(theta)
            cost = float(r @ r)
            if cost < best_cost:
                best, best_cost = theta, cost
    return best


def _pedestal(src: np.ndarray, target: np.ndarray, ratio: np.ndarray) -> float:
    """The black level ``b`` of a linear camera that the pooled pairs imply.  Such a camera
    maps each source value on a line ``target = s src + (1 - s) b`` (``s`` the exposure
    ratio): per ratio a line fitted by least squares, its fixed point ``b``, the median over
    the ratios; 0 where that is no level a file could hold (below 0 or above half scale)."""
    levels = []
    for r in np.unique(ratio):
        pick = ratio == r
        if abs(r - 1.0) < 1e-9 or pick.sum() < 3:
            continue
        slope, intercept = np.polyfit(src[pick], target[pick], 1)
        if abs(1.0 - slope) > 1e-6:
            levels.append(intercept / (1.0 - slope))
    b = float(np.median(levels)) if levels else 0.0
    return b if 0.0 < b < 0.5 else 0.0


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
