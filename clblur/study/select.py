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
from clblur.study.model import Group, null_params, pixel_nll, predict, time_ok

# Least held-out gain (nats per pixel value) that counts as a finding: with hundreds of
# thousands of values, deviations far below any visible effect (a gain of 1.0001) are
# "significant"; this asks for a difference worth modelling as well.
MIN_GAIN = 0.002


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
    return out


class _Folds:
    def __init__(self, groups: list[Group], nblocks: int):
        self.nblocks = nblocks
        self.part = [[g.subset(g.fold == f) for g in groups] for f in (0, 1)]
        self.nvalid = [sum(int(g.valid.sum()) for g in part) for part in self.part]
        self.cache: dict[frozenset, list[dict]] = {}

    def fit(self, effects: frozenset, start: list[dict], channels: int) -> list[dict]:
        if effects not in self.cache:
            free = [n for e in sorted(effects) for n in EFFECTS[e].params(channels)]
            self.cache[effects] = [fit(self.part[f], free, start[f], self.nvalid[f])
                                   for f in (0, 1)]
        return self.cache[effects]

    def block_fit_gain(self, base: list[dict], ext: list[dict]) -> np.ndarray:
        """Held-out drop of squared residuals per block, weighted by the base model's
        variance: how much better ``ext`` predicts the mean, noise model held fixed."""
        out = np.zeros(self.nblocks)
        for f in (0, 1):
            for g in self.part[f]:
                pb, var = predict(g, base[1 - f])
                pe, _ = predict(g, ext[1 - f])
                gain = ((g.target - pb) ** 2 - (g.target - pe) ** 2) / var
                out += np.bincount(g.block, weights=np.where(g.valid, gain, 0.0).sum(axis=1),
                                   minlength=self.nblocks)
        return 0.5 * out  # in nats, like the likelihood: -log L has r^2 / (2 var)

    def block_nll(self, params: list[dict]) -> np.ndarray:
        """Held-out NLL per block: fold f scored with the parameters fitted on the other."""
        out = np.zeros(self.nblocks)
        for f in (0, 1):
            for g in self.part[f]:
                out += np.bincount(g.block, weights=pixel_nll(g, params[1 - f]),
                                   minlength=self.nblocks)
        return out


def fit(groups: list[Group], free: list[str], start: dict, nvalid: int) -> dict:
    """Maximum-likelihood fit of the ``free`` parameters from ``start``."""
    names = list(dict.fromkeys(free))
    if not names:
        return dict(start)
    lo = np.array([PARAMS[n][1] for n in names])
    hi = np.array([PARAMS[n][2] for n in names])
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
        else:
            d = folds.block_fit_gain(p_base, p_e)
        d = d[used]
        d = d[np.abs(d) > 1e-9]  # blocks the effect cannot reach carry no evidence
        t, pv = t_test(d)
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
               _average(cur_params), sum(int(g.valid.sum()) for g in groups))
    for f in ranked:
        if f.significant:
            f.estimate = readable_estimate(f.effect, full, channels)
            f.explanation = explain(f.effect, f.estimate, True, f.nll_gain)
    b_rmse, b_nll, b_pred = _heldout(groups, base_p)
    x_rmse, x_nll, x_pred = _heldout(groups, cur_params)
    return Selection(order, ranked, full, b_rmse, x_rmse, b_nll, x_nll, b_pred, x_pred, skip)


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
            sub = g.subset(rows)
            pr, var = predict(sub, params[1 - f])
            pred[rows] = pr
            r = np.where(sub.valid, sub.target - pr, 0.0)
            se += float((r * r).sum())
            nll += float(pixel_nll(sub, params[1 - f]).sum())
            count += int(sub.valid.sum())
        preds.append(pred)
    return math.sqrt(se / max(count, 1)), nll / max(count, 1), preds
