"""Diagnose and extend: nested tests of each effect on held-out pixels, forward selection.

Conventions
-----------
* Target pixels are cut into square blocks; blocks alternate between two folds like a
  checkerboard.  A model is fitted (maximum likelihood, ``model.pixel_nll``) on one fold and
  scored on the other, both ways round, so every block is scored by parameters that never saw
  it (cross-fitting).
* Test of effect ``e`` given the current model ``S``: ``d_b`` = held-out improvement of
  block ``b`` from ``S`` to ``S + e``: for ``noise`` the drop of the negative log-likelihood;
  for the systematic effects (which change the prediction) half the drop of the squared
  residuals weighted by the variance of ``S``, so a mere re-shaping of the variance cannot
  pass for a better prediction.  The statistic is the one-sided t statistic of the mean
  of ``d_b`` over blocks (blocks are nearly independent even when pixels inside one are not);
  the p-value is Student's t with ``B - 1`` degrees of freedom.  Blocks where the extension
  leaves every prediction unchanged (e.g. no clipped source pixel on any path, for
  ``saturation``) are left out: they carry no evidence either way.  Extra parameters fitted to
  noise lose held-out likelihood on average, so under the null the test is conservative.
* Significance: ``p < alpha / m`` (Bonferroni over the ``m`` effects tested in a round), so
  null data give no finding at all with probability >= 1 - alpha; a finding also needs a
  held-out gain of at least ``MIN_GAIN`` nats per pixel value (an effect size, which only
  makes the decision stricter).
* Forward selection: of the significant effects, the one with the largest held-out gain
  joins the model, the rest are re-tested against the enlarged model, until none is
  significant.  Systematic effects are tested with the noise model free in both fits (a
  nuisance); ``noise`` itself is tested only when no systematic effect is significant.
  Findings are ranked by the order they joined, then by statistic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from clblur.study.effects import EFFECTS, PARAMS, explain, readable_estimate
from clblur.study.model import Group, null_params, time_ok
from clblur.study.variants import darkest_code, has_variant, pixel_nll, predict, subset

# Least held-out gain (nats per pixel value) that counts as a finding: with hundreds of
# thousands of values, deviations far below any visible effect (a gain of 1.0001) are
# "significant"; this asks for a difference worth modelling as well.  0.01: 8-bit rounding
# errors are a deterministic function of the value, not independent noise, and on real
# frames whose long exposure the paper's model itself built (GoPro, rounded) they let a
# gain of 1.0005 (0.003 codes of RMSE, 0.0097 nats) pass a threshold of 0.002.
MIN_GAIN = 0.01


@dataclass
class Finding:
    effect: str
    significant: bool
    statistic: float
    p_value: float
    estimate: dict
    explanation: str
    nll_gain: float  # held-out nats per pixel
    round: int
    interval: dict | None = None  # 95 % confidence interval per estimate, when significant


@dataclass
class Selection:
    effects: list[str]  # in the order they joined
    findings: list[Finding]
    params: dict[str, float]  # fitted on all pixels
    baseline_rmse: float
    extended_rmse: float
    baseline_nll: float  # held-out nats per valid pixel value
    extended_nll: float
    baseline_pred: list[np.ndarray] = field(default_factory=list)  # cross-fitted, per group
    extended_pred: list[np.ndarray] = field(default_factory=list)
    not_testable: dict[str, str] = field(default_factory=dict)


def assign_blocks(groups: list[Group], blocks_per_group: int = 64) -> int:
    """Give every target pixel a block id and a fold; returns the number of blocks."""
    offset = 0
    for gi, g in enumerate(groups):
        h, w = g.shape
        side = max(4, int(round(math.sqrt(h * w / blocks_per_group))))
        br, bc = g.rows // side, g.cols // side
        ncols = (w + side - 1) // side
        g.block = offset + br * ncols + bc
        g.fold = ((br + bc + gi) % 2).astype(np.int8)
        g.__dict__["gid"] = gi  # psf_orientation is chosen per group
        offset += ((h + side - 1) // side) * ncols
    return offset


def applicable(groups: list[Group]) -> dict[str, str]:
    """Effects the data cannot show, with the reason."""
    out = {}
    if not any(g.source_clipped for g in groups):
        out["saturation"] = "no source pixel is clipped (code 255)"
    if not any((1, 0) in g.hist for g in groups):
        out["nonuniform_motion"] = "no time order along the motion (PSF, or exposure series)"
    if not any((0, 1) in g.hist for g in groups):
        out["vignetting"] = ("source and target share sensor positions, so a fixed falloff "
                             "cancels in Eq. 8")
    if groups[0].channels < 2:
        out["channel_gain"] = "single-channel images"
    if not has_variant(groups, "psf_orientation"):
        out["psf_orientation"] = "the motion path is its own 180-degree turn (centred path)"
    if not has_variant(groups, "psf_scale"):
        out["psf_scale"] = "no motion between source and target (stack or series)"
    if not has_variant(groups, "misregistration"):
        out["misregistration"] = "groups built without shifted histograms"
    return out


def physical_bounds(groups: list[Group]) -> dict[str, tuple[float, float]]:
    """Parameter bounds the data impose: a black level cannot exceed the darkest code seen."""
    dark = min(darkest_code(g) for g in groups)
    return {"black": (0.0, min(PARAMS["black"][2], max(dark, 0) / 255.0))}


class _Folds:
    def __init__(self, groups: list[Group], nblocks: int):
        self.nblocks = nblocks
        self.part = [[subset(g, g.fold == f) for g in groups] for f in (0, 1)]
        self.nvalid = [sum(int(g.valid.sum()) for g in part) for part in self.part]
        self.cache: dict[frozenset, list[dict]] = {}
        self.bounds = physical_bounds(groups)

    def fit(self, effects: frozenset, start: list[dict], channels: int) -> list[dict]:
        if effects not in self.cache:
            free = [n for e in sorted(effects) for n in EFFECTS[e].params(channels)]
            self.cache[effects] = [fit(self.part[f], free, start[f], self.nvalid[f],
                                       self.bounds) for f in (0, 1)]
        return self.cache[effects]

    def block_score(self, base: list[dict], ext: list[dict]) -> tuple[np.ndarray, ...]:
        """Per block: held-out gain ``D_b``, its noise ``U_b`` and expected size ``A_b``.

        ``D_b = sum_p (r_S^2 - r_E^2) / (2 var)`` = ``sum_p delta (y - mid) / var`` with
        ``delta = pred_E - pred_S`` computed from the *other* fold's parameters and the held-
        out pixel's source codes only, so every pixel is weighted by how much the two models
        differ there, and blocks where they agree contribute nothing.  ``U_b = sum_p delta
        (y - pred_E) / var``: the noise of ``D_b`` measured on the extended model's residuals
        (pure noise when ``E`` is right; inflated by ``delta^2`` when ``S`` is right, which
        makes the test conservative under the null).  ``A_b = sum_p delta^2 / var``: the
        block's share of the information, for the degrees of freedom.
        """
        d = np.zeros(self.nblocks)
        u = np.zeros(self.nblocks)
        a = np.zeros(self.nblocks)
        for f in (0, 1):
            for g in self.part[f]:
                pb, var = predict(g, base[1 - f])
                pe, _ = predict(g, ext[1 - f])
                delta = np.where(g.valid, pe - pb, 0.0)
                y = g.target
                d += np.bincount(g.block, (delta * (y - 0.5 * (pb + pe)) / var).sum(axis=1),
                                 minlength=self.nblocks)
                u += np.bincount(g.block, (delta * (y - pe) / var).sum(axis=1),
                                 minlength=self.nblocks)
                a += np.bincount(g.block, (delta * delta / var).sum(axis=1),
                                 minlength=self.nblocks)
        return d, u, a

    def block_nll(self, params: list[dict]) -> np.ndarray:
        """Held-out NLL per block: fold f scored with the parameters fitted on the other."""
        out = np.zeros(self.nblocks)
        for f in (0, 1):
            for g in self.part[f]:
                out += np.bincount(g.block, weights=pixel_nll(g, params[1 - f]),
                                   minlength=self.nblocks)
        return out


def fit(groups: list[Group], free: list[str], start: dict, nvalid: int,
        bounds: dict[str, tuple[float, float]] | None = None) -> dict:
    """Maximum-likelihood fit of the ``free`` parameters from ``start``.

    ``flip`` (``psf_orientation``) is discrete and separate per group: it is chosen by the
    group's likelihood given the other parameters, alternating with the continuous fit.
    """
    if "flip" not in free:
        return _fit_continuous(groups, free, start, nvalid, bounds)
    rest = [n for n in free if n != "flip"]
    p = dict(start)
    for _ in range(3):
        chosen = _choose_flips(groups, p)
        if all(p.get(k) == v for k, v in chosen.items()) and _ > 0:
            break
        p.update(chosen)
        p = _fit_continuous(groups, rest, p, nvalid, bounds)
    return p


def _choose_flips(groups: list[Group], p: dict) -> dict:
    out = {}
    for g in groups:
        if "psf_orientation" not in g.__dict__.get("variants", {}):
            continue
        key = f"flip:{g.__dict__.get('gid', 0)}"
        nll = [float(pixel_nll(g, {**p, key: v}).sum()) for v in (0.0, 1.0)]
        out[key] = float(nll[1] < nll[0])
    return out


def _fit_continuous(groups: list[Group], free: list[str], start: dict, nvalid: int,
                    bounds: dict[str, tuple[float, float]] | None = None) -> dict:
    names = list(dict.fromkeys(free))
    if not names:
        return dict(start)
    bounds = bounds or {}
    lo = np.array([bounds.get(n, PARAMS[n][1:])[0] for n in names])
    hi = np.array([bounds.get(n, PARAMS[n][1:])[1] for n in names])
    hi = np.maximum(hi, lo + 1e-9)
    starts = [dict(start)]
    if "na" in free and (start["na"] > 1e-6 or start["nb"] > 1e-8):
        # a noise model inflated by a wrong mean flattens the likelihood; restart without it
        starts.append({**start, "na": 0.0, "nb": 0.0})
    if "gamma" in free and start["gamma"] == 1.0 and start["rho"] == 1.0:
        # also start from the power-law corner: linear and display gamma
        starts += [{**s, "gamma": g, "rho": 0.05} for s in list(starts) for g in (1.0, 2.2)]
    best, best_val = None, math.inf
    for s0 in starts:
        def objective(z, s0=s0):
            p = dict(s0)
            p.update(zip(names, lo + (hi - lo) * z, strict=True))
            if not time_ok(p):
                return 1e3
            return sum(float(pixel_nll(g, p).sum()) for g in groups) / max(nvalid, 1)

        z0 = np.clip((np.array([s0[n] for n in names]) - lo) / (hi - lo), 0.0, 1.0)
        res = optimize.minimize(objective, z0, method="L-BFGS-B", bounds=[(0, 1)] * len(z0),
                                options={"maxiter": 300, "ftol": 1e-7, "gtol": 1e-5})
        if res.fun < best_val:
            best_val = res.fun
            best = dict(s0)
            best.update(zip(names, lo + (hi - lo) * res.x, strict=True))
    return best


def t_test(d: np.ndarray) -> tuple[float, float]:
    """One-sided t statistic and p-value that the mean of ``d`` is > 0."""
    if d.size < 3:
        return 0.0, 1.0
    sd = float(d.std(ddof=1))
    if sd <= 1e-12 * max(1.0, float(np.abs(d).max())):
        return 0.0, 1.0
    t = float(d.mean()) / (sd / math.sqrt(d.size))
    return t, float(stats.t.sf(t, d.size - 1))


def weighted_test(d: np.ndarray, u: np.ndarray, a: np.ndarray) -> tuple[float, float]:
    """One-sided test that the summed held-out gain ``sum d`` is > 0, block-robust.

    ``T = sum d_b / sqrt(sum u_b^2)`` (a cluster-robust Wald statistic: pixels inside a block
    may be correlated, blocks are nearly independent); Student's t with Satterthwaite's
    degrees of freedom ``(sum a)^2 / sum a^2 - 1``, so a gain carried by a few blocks is
    judged with the few degrees of freedom those blocks give.  See ``_Folds.block_score``.
    """
    if d.size < 2:
        return 0.0, 1.0
    v = float((u * u).sum())
    if v <= 1e-300 or float(a.sum()) <= 0:
        return 0.0, 1.0
    t = float(d.sum()) / math.sqrt(v)
    df = max(1.0, min(d.size - 1.0, float(a.sum()) ** 2 / float((a * a).sum()) - 1.0))
    return t, float(stats.t.sf(t, df))


def select(groups: list[Group], alpha: float = 0.05, min_gain: float = MIN_GAIN,
           progress=None) -> Selection:
    """Run the whole diagnosis (see the module docstring)."""
    nblocks = assign_blocks(groups)
    channels = groups[0].channels
    folds = _Folds(groups, nblocks)
    used = np.zeros(nblocks, bool)
    for part in folds.part:
        for g in part:
            used[g.block[g.valid.any(axis=1)]] = True
    skip = applicable(groups)
    candidates = [e for e in EFFECTS if e not in skip]
    current: frozenset = frozenset()
    null = null_params()
    findings: dict[str, Finding] = {}
    order: list[str] = []
    nvalid = sum(folds.nvalid)
    rnd = 0

    def test(model: frozenset, effect: str, start: list[dict]):
        if progress is not None:
            progress.set_postfix_str(f"round {rnd}: {effect}")
        p_base = folds.fit(model, start, channels)
        p_e = folds.fit(model | {effect}, p_base, channels)
        if effect == "noise":
            d = folds.block_nll(p_base) - folds.block_nll(p_e)
            d = d[used]
            d = d[np.abs(d) > 1e-9]  # blocks the effect cannot reach carry no evidence
            t, pv = t_test(d)
        else:
            d, u, a = folds.block_score(p_base, p_e)
            reach = used & (a > 1e-12)  # blocks the effect cannot reach carry no evidence
            d = d[reach]
            t, pv = weighted_test(d, u[reach], a[reach])
        gain = float(d.sum()) / max(nvalid, 1)
        est = readable_estimate(effect, _average(p_e), channels)
        findings[effect] = Finding(effect, False, t, pv, est, explain(effect, est, False, gain),
                                   gain, rnd)
        if progress is not None:
            progress.update(1)
        return effect, pv, gain, p_e

    cur_params = folds.fit(current, [null, null], channels)
    while candidates:
        rnd += 1
        level = alpha / len(candidates)
        # Systematic effects compete with the noise model free in both fits (a nuisance), so
        # extra variance cannot masquerade as a better mean and vice versa; noise is judged
        # on its own only when no systematic effect is left to add.
        nuisance = frozenset({"noise"}) if "noise" in candidates else frozenset()
        tested = [test(current | nuisance, e, [cur_params[0], cur_params[1]])
                  for e in candidates if e != "noise"]
        winners = [r for r in tested if r[1] < level and r[2] >= min_gain]
        if not winners and "noise" in candidates:
            winners = [r for r in [test(current, "noise", cur_params)]
                       if r[1] < level and r[2] >= min_gain]
        for e, pv, gain, _ in tested:
            if pv < level and gain < min_gain:
                f = findings[e]
                f.explanation = explain(e, f.estimate, False, gain, too_small=True)
        if not winners:
            break
        # strongest = largest held-out likelihood gain among the significant effects
        e, pv, gain, _ = max(winners, key=lambda r: r[2])
        findings[e].significant = True
        findings[e].explanation = explain(e, findings[e].estimate, True, gain)
        order.append(e)
        current = current | {e}
        cur_params = folds.fit(current, cur_params, channels)
        candidates.remove(e)
    ranked = [findings[e] for e in order] + sorted(
        (f for e, f in findings.items() if e not in order), key=lambda f: -f.statistic)
    base_p = folds.fit(frozenset(), [null, null], channels)
    full = fit(groups, [n for e in sorted(current) for n in EFFECTS[e].params(channels)],
               _average(cur_params), sum(int(g.valid.sum()) for g in groups), folds.bounds)
    for f in ranked:
        if f.significant:
            f.estimate = readable_estimate(f.effect, full, channels)
            f.explanation = explain(f.effect, f.estimate, True, f.nll_gain)
            f.interval = intervals(groups, full, f.effect, channels, folds.bounds)
    b_rmse, b_nll, b_pred = _heldout(groups, base_p)
    x_rmse, x_nll, x_pred = _heldout(groups, cur_params)
    return Selection(order, ranked, full, b_rmse, x_rmse, b_nll, x_nll, b_pred, x_pred, skip)


# readable name and transform of each continuous parameter, for the intervals
_READABLE = {"black": ("black_level_codes", lambda v: 255.0 * v), "gamma": ("gamma", None),
             "rho": ("rho", None), "sat": ("factor", None), "gain": ("gain", math.exp),
             "vig": ("c", None), "t1": ("t1", None), "t2": ("t2", None), "na": ("a", None),
             "nb": ("b", None), "qoff": ("offset_codes", None), "sx": ("shift_x", None),
             "sy": ("shift_y", None), "pscale": ("scale", None)}


def intervals(groups: list[Group], p: dict, effect: str, channels: int,
              bounds: dict[str, tuple[float, float]] | None = None) -> dict | None:
    """95 % confidence intervals of an effect's parameters: block-robust sandwich.

    ``cov = H^-1 M H^-1`` with ``H`` the Hessian of the total NLL in the effect's parameters
    (finite differences, the other parameters held at their fit) and ``M = sum_b s_b s_b^T``
    the outer product of per-block scores, so correlated residuals inside a block widen the
    interval.  Intervals are cut to the physically possible range (parameter bounds, e.g.
    a black level no higher than the darkest code seen).  Conditional on the other
    parameters, so somewhat narrow when parameters trade off.  ``None`` for discrete effects.
    """
    names = [n for n in EFFECTS[effect].params(channels) if n in PARAMS]
    if not names or effect == "psf_orientation":
        return None
    bounds = bounds or {}
    lo = np.array([bounds.get(n, PARAMS[n][1:])[0] for n in names])
    hi = np.array([bounds.get(n, PARAMS[n][1:])[1] for n in names])
    x0 = np.array([p[n] for n in names])
    h = 1e-4 * (hi - lo)
    nblocks = int(max(int(g.block.max()) for g in groups)) + 1

    def nll_blocks(x):
        q = {**p, **dict(zip(names, x, strict=True))}
        if not time_ok(q):
            return None
        out = np.zeros(nblocks)
        for g in groups:
            out += np.bincount(g.block, pixel_nll(g, q), minlength=nblocks)
        return out

    k = len(names)
    f0 = nll_blocks(x0)
    plus, minus = [], []
    for i in range(k):
        e = np.zeros(k)
        e[i] = h[i]
        fp, fm = nll_blocks(x0 + e), nll_blocks(x0 - e)
        if fp is None or fm is None or f0 is None:
            return None
        plus.append(fp)
        minus.append(fm)
    score = np.stack([(plus[i] - minus[i]) / (2 * h[i]) for i in range(k)], axis=1)
    hess = np.zeros((k, k))
    for i in range(k):
        hess[i, i] = float((plus[i] - 2 * f0 + minus[i]).sum()) / h[i] ** 2
        for j in range(i):
            e = np.zeros(k)
            e[i], e[j] = h[i], h[j]
            fpp, fmm = nll_blocks(x0 + e), nll_blocks(x0 - e)
            if fpp is None or fmm is None:
                return None
            # f(x+e) + f(x-e) - 2 f0 = H_ii h_i^2 + H_jj h_j^2 + 2 H_ij h_i h_j
            hij = (float((fpp + fmm - 2 * f0).sum()) - hess[i, i] * h[i] ** 2
                   - hess[j, j] * h[j] ** 2) / (2 * h[i] * h[j])
            hess[i, j] = hess[j, i] = hij
    try:
        hinv = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return None
    meat = score.T @ score
    cov = hinv @ meat @ hinv
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0) or np.any(np.diag(hess) <= 0):
        return None
    half = 1.96 * np.sqrt(np.diag(cov))
    out = {}
    for i, n in enumerate(names):
        a, b = max(lo[i], x0[i] - half[i]), min(hi[i], x0[i] + half[i])
        key, fn = _READABLE.get(n, (n, None))
        a, b = (fn(a), fn(b)) if fn else (a, b)
        out[key] = [float(a), float(b)]
    return out


def _average(params: list[dict]) -> dict:
    return {k: 0.5 * (params[0][k] + params[1][k]) for k in params[0]}


def _heldout(groups: list[Group], params: list[dict]):
    """Cross-fitted RMSE (codes), NLL per valid value, and predictions per group."""
    se = nll = 0.0
    count = 0
    preds = []
    for g in groups:
        pred = np.zeros_like(g.target)
        for f in (0, 1):
            rows = g.fold == f
            sub = subset(g, rows)
            pr, var = predict(sub, params[1 - f])
            pred[rows] = pr
            r = np.where(sub.valid, sub.target - pr, 0.0)
            se += float((r * r).sum())
            nll += float(pixel_nll(sub, params[1 - f]).sum())
            count += int(sub.valid.sum())
        preds.append(pred)
    return math.sqrt(se / max(count, 1)), nll / max(count, 1), preds
