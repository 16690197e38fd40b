"""The free monotone spline fitted on cross-exposure prediction error.

``SplineFamily`` (the ``spline`` model) and the function it and ``clblur.study`` share,
``fit_cross_exposure``: a ``clblur.responses.MonotoneSpline`` whose log increments minimise the
code-value error of predicting one exposure from another (Mitsunaga & Nayar's 1999 ratio idea
taken to code values), solved by a small Levenberg-Marquardt loop.

Conventions
-----------
Values normalised to [0, 1]; ``ratio`` is the exposure ratio target / source.  A source value
clipped at either end (outside ``PAIR_LOW_CODE``..``PAIR_HIGH_CODE`` of an 8-bit scale) is not
used; a clipped target is counted as censored (``pooled_pairs``).
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

__all__ = ["SplineFamily", "choose_smoothness", "curve_black_level", "pooled_pairs",
           "fit_cross_exposure", "PAIR_LOW_CODE", "PAIR_HIGH_CODE", "SMOOTHNESS_GRID",
           "TRIM_LIMIT"]


# Pixel values the cross-exposure fit uses, in codes of an 8-bit scale: everything not clipped
# at either end (the same range the evaluation scores).
PAIR_LOW_CODE, PAIR_HIGH_CODE = 2.5, 252.5

# The spline's smoothness weights tried by cross-validation, a factor 3 apart, from the fixed
# weight used before.  At the top the curve lies close to a power law (the penalty's stiff
# limit, ``_power_law_curvature``); the one-standard-error rule takes it on a few series
# (Canon's red, a linear 16-bit camera, a gamma-2.2 one), and stiffer weights tried on
# generated JPEG brackets (to 1.4e6) rose in held-out error on all but one channel, which
# they took further from the truth.
SMOOTHNESS_GRID = tuple(0.3 * 3.0**k for k in range(12))
# Used where a series is too small to cross-validate (fewer spatial tiles than folds, or a
# training fold with fewer pools than knots).
DEFAULT_SMOOTHNESS = 0.3
CV_FOLDS = 5
# The largest share of a pool's targets that may be clipped (``pooled_pairs``).  Trimmed
# further, a pool's mean is that of its middle few codes: with integer targets it snaps to
# them, 0.25 - 0.5 codes off at 43 - 50 % clipped on a test with 1.5 codes of noise; at 25 %
# the middle half is left, within 0.1 code there.
TRIM_LIMIT = 0.25


def _full_fit_scale(folds: int) -> float:
    """By how much a weight chosen on (folds - 1) / folds of the pixels grows when it is
    applied to all of them: the data term grows with the pixels, so the penalty grows by the
    square root of that ratio."""
    return float(np.sqrt(folds / (folds - 1)))


FULL_FIT_SCALE = _full_fit_scale(CV_FOLDS)
# The cross-validation's fits stop at a relative cost decrease of 1e-7, not 1e-10: 4 - 5
# times fewer iterations, the same weight chosen (every channel of the JPEG 4:2:0 bracket of
# docs/studies/radiance_brackets.py; held-out RMSE within 0.004 codes)
CV_RTOL = 1e-7


class SplineFamily:
    """A free monotone curve fitted on the cross-exposure prediction error directly.

    The objective is Mitsunaga & Nayar's (1999) ratio idea taken to code values: for every
    fitting pixel valid in exposures ``i`` and ``j`` (at most ``max_gap`` stops apart, both
    orders), predict code ``j`` from code ``i`` through the curve,
    ``v_j = I(I^-1(v_i) tau_j / tau_i)``, and minimise the squared error in code values.
    The curve is a ``clblur.responses.MonotoneSpline`` (``knots`` segments, denser towards
    black, exposure 0 at value 0), so the toe is modelled: codes at and below the black level
    get near-zero exposure increments, and the dark noise floor is what the curve predicts
    for a very dark source.  A second-difference penalty (``smoothness``) keeps stretches
    without data smooth; it is taken on each segment's log slope against log value, so a
    power law costs nothing and the stiff limit is a gamma curve
    (:func:`_power_law_curvature`).  A clipped target counts as censored
    (:func:`pooled_pairs`).

    The smoothness is chosen on held-out pixels (:func:`choose_smoothness`) unless given.
    The data alone cannot pin it: with exposures a whole number of stops apart, a curve
    whose exposure is multiplied by any function periodic in log2 exposure predicts every
    pair exactly as well (Grossberg & Nayar 2003's ambiguity), and a weak penalty let the
    curve wander along it, most where codec error has structure (JPEG copies of a measured
    radiance map: 20 % to a factor of 150 off in exposure, ``docs/studies/validation.md``).

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
    chosen_from_data = ("smoothness",)  # kept by the evaluation's refits

    def fit(self, samples, tau, *, full_scale, refine_times=False, knots: int = 64,
            smoothness: float | None = None, max_gap: float = 4.5,
            clip_high: float | None = None, **opts) -> FamilyFit:
        if opts:
            raise InputTypeError(f"unknown option(s) for the spline model: {sorted(opts)}")
        if not isinstance(knots, (int, np.integer)) or not 4 <= knots <= 256:
            raise InputError(f"spline knots must be an integer in 4..256, got {knots!r}")
        if smoothness is not None and not smoothness >= 0:
            raise InputError(f"smoothness must be >= 0, got {smoothness!r}")
        if clip_high is not None and not 0.0 < clip_high <= 1.0:
            raise InputError(f"clip_high must be in (0, 1], got {clip_high!r}")
        src, mean, ratio, count = pooled_pairs(samples.values, samples.valid, tau, max_gap,
                                               full_scale, clip_high=clip_high)
        if src.size < knots:
            raise InputError("too few pixel pairs valid in two exposures for the spline model "
                             f"({src.size} pools for {knots} knots)")
        u = default_knots(int(knots))
        chosen = None
        if smoothness is None:
            chosen = choose_smoothness(samples, tau, full_scale, int(knots), max_gap,
                                       clip_high=clip_high)
            smoothness = chosen["smoothness"] * chosen["scale"]
        # down from the stiffest weight, as each fold was fitted: a weight chosen by
        # cross-validation (or passed back by a refit) names the curve of that path
        stiffer = [g * FULL_FIT_SCALE for g in SMOOTHNESS_GRID]
        theta = _fit_down(u, src, mean, ratio, np.sqrt(count) * full_scale, smoothness,
                          stiffer)
        curve = MonotoneSpline(u, theta)
        params = {"knots": int(knots), "smoothness": float(smoothness),
                  "pairs": int(count.sum()), "black_level": curve_black_level(curve)}
        if chosen is not None:
            params["smoothness_cv"] = {k: chosen[k] for k in ("rule", "grid", "rmse", "se")}
        curve.meta.update({"params": params})
        return FamilyFit(curve, params, int(knots) - 1, tau)


def _descend(u, src, mean, ratio, weight, weights, last_rtol: float = CV_RTOL):
    """``fit_cross_exposure`` at each of ``weights`` (stiffest first) in turn, each fit
    starting from the one before and the first from the usual starts; yields each fit's log
    increments.  ``last_rtol``: the last fit's stopping tolerance (the others stop at
    ``CV_RTOL``)."""
    theta = None
    for n, g in enumerate(weights):
        theta = fit_cross_exposure(u, src, mean, ratio, weight, g, theta0=theta, pedestal=True,
                                   rtol=last_rtol if n == len(weights) - 1 else CV_RTOL)
        yield theta


def _fit_down(u, src, mean, ratio, weight, smoothness: float, grid) -> np.ndarray:
    """``fit_cross_exposure`` at ``smoothness``, started from the fits at every stiffer
    weight of ``grid`` in turn, the stiffest from the usual starts (the stiff fits have one
    basin, the weak ones several: a weak fit from the usual starts alone left a JPEG
    bracket's green a factor of 10 - 75 off in exposure where this path found a smooth
    curve with a lower held-out error)."""
    stiffer = sorted((g for g in grid if g > smoothness * (1 + 1e-9)), reverse=True)
    *_, theta = _descend(u, src, mean, ratio, weight, [*stiffer, smoothness], last_rtol=1e-10)
    return theta


def choose_smoothness(samples, tau: np.ndarray, full_scale: float, knots: int = 64,
                      max_gap: float = 4.5, folds: int = CV_FOLDS,
                      grid: tuple[float, ...] = SMOOTHNESS_GRID,
                      clip_high: float | None = None) -> dict:
    """The spline's smoothness by spatial ``folds``-fold cross-validation, one-standard-error
    rule.

    The pixels are cut into square tiles (about 50 over the sampled extent, 8 - 64 px a
    side) dealt at random to the folds, so a held-out pixel's codec block and its
    neighbours' misregistration are not in the training pixels.  On each fold the curve is
    fitted down the grid from its stiffest weight (each fit starting from the stiffer one:
    the stiff fits have one basin, the weak ones several) and scored by the pooled RMSE of
    predicting the darker image of each held-out pair, the direction calibration ranks
    models by (``clblur.calibration.compare.selection_score``).  Chosen: the stiffest weight
    whose mean held-out MSE is within one standard error (over the folds) of the lowest
    (Hastie, Tibshirani & Friedman, *Elements of Statistical Learning*, 2nd ed., 7.10): where
    the data cannot tell the curves apart, the smoothest is taken.

    Returns a dict: ``smoothness`` (the grid value chosen), ``scale`` (by which to multiply
    it for a fit on all the pixels: the penalty against a data term ``folds / (folds - 1)``
    times larger), ``rule``, ``grid``, ``rmse`` and ``se`` (per grid value, code values;
    empty where the series is too small to cross-validate and ``DEFAULT_SMOOTHNESS`` is
    returned).
    """
    fallback = {"smoothness": DEFAULT_SMOOTHNESS, "scale": 1.0, "grid": [DEFAULT_SMOOTHNESS],
                "rmse": [], "se": [], "rule": "fixed (too few pixels to cross-validate)"}
    fold = _spatial_folds(samples.rows, samples.cols, folds)
    if fold is None:
        return fallback
    u = default_knots(knots)
    mse = np.full((folds, len(grid)), np.nan)
    for k in range(folds):
        train, test = fold != k, fold == k
        src, mean, ratio, count = pooled_pairs(samples.values[train], samples.valid[train],
                                               tau, max_gap, full_scale, clip_high=clip_high)
        h_src, h_mean, h_ratio, h_count = pooled_pairs(samples.values[test],
                                                       samples.valid[test], tau, max_gap,
                                                       full_scale, clip_high=clip_high)
        darker = h_ratio < 1.0
        if src.size < knots or not darker.any():
            return fallback
        down = range(len(grid) - 1, -1, -1)
        for g, theta in zip(down, _descend(u, src, mean, ratio, np.sqrt(count) * full_scale,
                                           [grid[g] for g in down]), strict=True):
            curve = MonotoneSpline(u, theta)
            with np.errstate(invalid="ignore", over="ignore"):
                pred = curve.forward(curve.inverse(h_src[darker]) * h_ratio[darker])
            # a pool's squared error is its count times its mean's error, plus its spread,
            # which no curve changes
            mse[k, g] = (np.sum(h_count[darker] * (pred - h_mean[darker]) ** 2)
                         / h_count[darker].sum() * full_scale**2)
    mean_mse = mse.mean(axis=0)
    if not np.isfinite(mean_mse).any():  # no weight predicted the held-out pixels at all
        return {**fallback, "rule": "fixed (no weight predicted the held-out pixels)"}
    se = mse.std(axis=0, ddof=1) / np.sqrt(folds)
    best = int(np.nanargmin(mean_mse))
    pick = int(np.flatnonzero(mean_mse <= mean_mse[best] + se[best]).max())
    return {"smoothness": float(grid[pick]), "scale": _full_fit_scale(folds),
            "grid": [float(g) for g in grid], "rmse": np.sqrt(mean_mse).tolist(),
            "se": se.tolist(), "rule": f"{folds}-fold spatial cross-validation, one standard error"}


def _spatial_folds(rows: np.ndarray, cols: np.ndarray, folds: int) -> np.ndarray | None:
    """A fold index per pixel: square tiles dealt at random (a fixed seed) to ``folds``
    folds; None when there are fewer tiles than twice the folds."""
    if rows.size == 0:
        return None
    extent = float(rows.max() + 1) * float(cols.max() + 1)
    tile = int(np.clip(np.sqrt(extent / 50.0), 8, 64))
    across = int(cols.max()) // tile + 1
    key = (rows // tile) * across + cols // tile
    tiles, which = np.unique(key, return_inverse=True)
    if tiles.size < 2 * folds:
        return None
    return (np.random.default_rng(0).permutation(tiles.size) % folds)[which]


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
                 full_scale: float, levels: int = 1024, clip_high: float | None = None):
    """Pool ordered exposure pairs of each sample by (source value, ratio), clipped targets
    counted as censored.

    A pair enters where its source value is valid and unclipped.  Its target either lies
    inside the range too, or is clipped (at or below ``PAIR_LOW_CODE``, at or above
    ``PAIR_HIGH_CODE``): censored, known only to lie beyond that end.  Leaving the clipped
    targets out would keep a pool's brighter (darker) targets where the bottom (top) clips,
    so its mean would sit above (below) what the curve predicts, and the fit would bend to
    that selection on noise at both ends of the range.  Instead each pool is trimmed
    symmetrically: with ``t`` of its targets censored at the worse end, its ``t`` lowest and
    ``t`` highest targets are dropped (the censored ones among them) and the rest averaged.
    For noise symmetric about the curve's prediction that mean is unbiased (the argument of
    Powell's symmetrically trimmed least squares for censored regression, Econometrica 54,
    1986, 1435 - 1460, here on the replicates a pool holds).  A pool with more than
    ``TRIM_LIMIT`` of its targets censored is left out.  A target invalid for another reason
    (a JPEG's coded clipped region, ``ExposureSeries.coded_near_clip``, with a value inside
    the range) is left out.

    ``clip_high``: for a camera that clips below full scale (``ExposureSeries.white_level``),
    the normalised value from which a target is clipped high, in place of ``PAIR_HIGH_CODE``:
    its pile is censored like full scale, and a source must lie below it.

    ``values``/``valid``: (P, n) normalised values and validity (see ``SampleSet``).  Returns
    ``(source value, mean target value, ratio tau_j / tau_i, count)`` per pool, ``count``
    the targets averaged.  Source values are exact codes for 8-bit data and binned to
    ``levels`` otherwise.
    """
    n = values.shape[1]
    lo, hi = PAIR_LOW_CODE / 255.0, PAIR_HIGH_CODE / 255.0
    if clip_high is not None:
        hi = min(hi, clip_high)
    inside = (values > lo) & (values < hi)
    source_ok = valid & inside
    # a target counts where it is valid and inside the range, or clipped at either end (a
    # value of 0 or full scale is invalid for being clipped: censored, not unknown)
    target_ok = (valid & inside) | (values <= lo) | (values >= hi)
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
        both = source_ok[:, i] & target_ok[:, j]
        q = np.clip(np.rint(values[both, i] * (bins - 1)), 0, bins - 1).astype(np.int64)
        keys.append(q + bins * int(r_index))
        targets.append(values[both, j])
    key = np.concatenate(keys)
    tgt = np.concatenate(targets)
    order = np.lexsort((tgt, key))  # by pool, and within a pool by target value
    key, tgt = key[order], tgt[order]
    uniq, start, total = np.unique(key, return_index=True, return_counts=True)
    pool = np.repeat(np.arange(uniq.size), total)
    below = np.bincount(pool, tgt <= lo, uniq.size)
    above = np.bincount(pool, tgt >= hi, uniq.size)
    trim = np.maximum(below, above).astype(np.int64)
    # a pool censored more often than TRIM_LIMIT is left out (trimmed whole)
    trim = np.where(trim > TRIM_LIMIT * total, total, trim)
    rank = np.arange(key.size) - start[pool]
    # the censored targets sort to their pool's ends, so they are among those trimmed
    kept = (rank >= trim[pool]) & (rank < (total - trim)[pool])
    count = np.bincount(pool[kept], minlength=uniq.size)
    mean = np.bincount(pool[kept], weights=tgt[kept], minlength=uniq.size)
    use = count > 0
    src = (uniq[use] % bins) / (bins - 1)
    ratio = np.asarray(ratios)[uniq[use] // bins]
    return src, mean[use] / count[use], ratio, count[use].astype(np.float64)


def fit_cross_exposure(u: np.ndarray, src: np.ndarray, target: np.ndarray, ratio: np.ndarray,
                       weight: np.ndarray, smoothness: float,
                       theta0: np.ndarray | None = None, pedestal: bool = False,
                       rtol: float = 1e-10) -> np.ndarray:
    """Log increments of the ``MonotoneSpline`` on knots ``u`` minimising
    ``sum weight^2 (I(I^-1(src) ratio) - target)^2`` plus ``smoothness^2`` times the squared
    curvature of :func:`_power_law_curvature` (analytic Jacobian, trust region).

    Starts from ``theta0``, else from the best of three power laws and, with ``pedestal``,
    a straight line above the black level the pairs imply (:func:`_pedestal`); the sum of
    the increments is pinned softly (the exposure unit is free).  ``rtol``: the relative
    decrease of the cost below which the iterations stop.
    """
    k = u.size - 1
    h = np.diff(u)
    a = np.clip(np.searchsorted(u, src, side="right") - 1, 0, k - 1)
    w = (src - u[a]) / h[a]
    m = np.arange(1, k + 1)
    d_src = (m[None, :] <= a[:, None]) + w[:, None] * (m[None, :] == a[:, None] + 1)
    diff2, bend = _power_law_curvature(u)

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
        return np.concatenate([weight * (v - target), smoothness * (diff2 @ th - bend),
                               [total]])

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
            theta = _levenberg_marquardt(residuals, jacobian, start, rtol=rtol)
            r = residuals(theta)
            cost = float(r @ r)
            if cost < best_cost:
                best, best_cost = theta, cost
    return best


def _power_law_curvature(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The spline's smoothness penalty, ``rows @ theta - offset``: second differences of the
    log slope of each segment against the log of its centre value, so a power law (a gamma
    curve, ``x = v ** g``) costs nothing.

    ``theta`` are the log increments on knots ``u``; a segment's log slope is ``theta_m - log
    h_m``.  A power law's log slope is linear in log value (exactly in the limit of short
    segments; on the first rows, whose segments start at or near 0, the penalty of
    ``x = v ** g`` on 64 knots is 0.011 for g = 2.2 and 0.28 for g = 0.4, against 1.35 and
    0.19 on the log increments against the knot index), so where the data do not reach, a
    stiff spline continues as a gamma curve.  Each row is the change of the divided first
    difference times the geometric mean of the two spacings, which for even spacing is the
    plain second difference: the weights keep the scale they had.
    """
    k = u.size - 1
    h = np.diff(u)
    s = np.log(0.5 * (u[:-1] + u[1:]))
    ds = np.diff(s)
    rows = np.zeros((max(k - 2, 0), k))
    r = np.arange(k - 2)
    scale = np.sqrt(ds[:-1] * ds[1:])
    rows[r, r] = scale / ds[:-1]
    rows[r, r + 2] = scale / ds[1:]
    rows[r, r + 1] = -(rows[r, r] + rows[r, r + 2])
    return rows, rows @ np.log(h)


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
