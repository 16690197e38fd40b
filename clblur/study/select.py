"""Diagnose and extend: nested tests of each effect on held-out pixels, forward selection
with exchanges.

Cross-fitting lives in ``clblur.study.crossfit``, the test statistics in
``clblur.study.significance``; this module decides and reports.

Conventions
-----------
* Target pixels are cut into square blocks; blocks alternate between two folds like a
  checkerboard.  A model is fitted (maximum likelihood, ``variants.pixel_nll``) on one fold and
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
  ``misregistration`` must also predict better than its own shift mirrored, which smooths
  the source's noise as much (:func:`_against_mirror`).
* Significance: ``p < alpha / m`` (Bonferroni over the ``m`` effects tested in a round), so
  null data give no finding at all with probability >= 1 - alpha; a finding also needs a
  held-out gain of at least ``MIN_GAIN`` nats per pixel value (an effect size, which only
  makes the decision stricter).
* Forward selection: of the significant effects, the one with the largest held-out gain
  joins the model (unless one with fewer parameters predicts not significantly worse:
  then the simplest of those, ``_joining``), the rest are re-tested against the enlarged
  model, until none is significant.  Systematic effects are tested with the noise model
  free in both fits (a nuisance); ``noise`` itself is tested only when no systematic
  effect is significant.  A winner's fit with its effect at null is also a start for the
  current model; where it fits a fold better, the winners are tested again from there
  (``_better_base``), so no winner gains what only its own search found.
  Findings are ranked by the order they joined, then by statistic.
* Exchange: when none joins, a joined effect is replaced by a rival (significant in the
  round it joined) whose model predicts the held-out blocks significantly better in its
  place, or that has fewer parameters and predicts not significantly worse
  (``_best_swap``); forward selection then goes on.  Greedy selection alone keeps the
  first of two near-equal explanations even when later effects favour the other.
* Removal: when no exchange is left, a joined effect whose rival joined on top of it is
  tested for removal by the same test, and the weakest that adds nothing leaves
  (``_redundant``): the exchange reached the other way round.  After either, the effects
  that were contained in the one that left are candidates again (``_testable_again``).
* What is left: the final model is tested against per-code offsets that name no cause
  (``clblur.study.leftover``), so a cause outside the vocabulary is reported as structure
  left rather than passed over (``Selection.leftover``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from clblur.blas import one_blas_thread
from clblur.study.crossfit import (
    CONDITIONAL,
    WARP_RIDGE,
    Folds,
    applicable,
    assign_blocks,
    average_params,
    fit,
    fit_all,
    free_params,
    heldout_scores,
    physical_bounds,
)
from clblur.study.domain import code_shares, mixing_domain
from clblur.study.effects import (
    EFFECTS,
    FAMILY_LIMITS,
    effect_keys,
    explain,
    is_per_image,
    param_range,
    readable_estimate,
)
from clblur.study.leftover import leftover
from clblur.study.model import WARP_KEYS, Group, null_params, time_ok
from clblur.study.significance import t_test, weighted_test
from clblur.study.variants import pack, pixel_nll

__all__ = ["Finding", "Selection", "select", "intervals", "MIN_GAIN", "assign_blocks", "on_edge",
           "applicable", "physical_bounds", "fit", "t_test", "weighted_test"]


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
    edge: list[str] = field(default_factory=list)  # parameters its fit left on a bound

    def explain(self, significant: bool, gain: float, **how) -> None:
        """Write the finding's sentence (``effects.explain``; ``how``: its ``too_small``,
        ``replaced`` or ``replaced_by``), with the edge note (``_edge_note``) however often
        the verdict is rewritten."""
        self.explanation = (explain(self.effect, self.estimate, significant, gain, **how)
                            + _edge_note(self.edge, significant))


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
    leftover: dict | None = None  # what the extended model leaves (``study.leftover``)
    domain: dict | None = None  # the domain the final curve averages in (``study.domain``)




def select(groups: list[Group], alpha: float = 0.05, min_gain: float = MIN_GAIN,
           progress=None, split: int = 0) -> Selection:
    """Run the whole diagnosis (see the module docstring) on the blocks' fold ``split``
    (``assign_blocks``; 0, the checkerboard, unless the study repeats the split).

    BLAS runs on one thread meanwhile (``clblur.blas``: OpenBLAS's threads, woken by
    L-BFGS-B's small products, spin on the core the other fold's fit needs).
    """
    nblocks = assign_blocks(groups, split=split)
    with one_blas_thread(), Folds(groups, nblocks) as folds:
        return _select(groups, folds, nblocks, alpha, min_gain, progress)


def _select(groups: list[Group], folds: Folds, nblocks: int, alpha: float, min_gain: float,
            progress) -> Selection:
    channels = groups[0].channels
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

    earlier: dict[str, list[dict]] = {}
    replaced: dict[str, tuple] = {}  # effect -> (the effect it replaced, the exchange's gain)
    replaced_by: dict[str, str] = {}  # the inverse

    def test(model: frozenset, effect: str, start: list[dict]):
        if progress is not None:
            progress.set_postfix_str(f"round {rnd}: {effect}")
        p_base = folds.fit(model, start, channels)
        only = (frozenset({effect}) | (model & {"noise"})) if effect in CONDITIONAL else None
        # the effect's fit of the previous round is a second start: it already searched the
        # effect's own parameters (the response shape's basins), which the new model moves little
        p_e = folds.fit(model | {effect}, p_base, channels, only, earlier.get(effect))
        earlier[effect] = p_e
        if progress is not None:
            progress.update(1)
        return score(effect, p_base, p_e)

    def score(effect: str, p_base: list[dict], p_e: list[dict]):
        """The held-out test of ``p_e`` (the model with ``effect``) against ``p_base``,
        recorded as the effect's finding of this round."""
        if effect == "noise":
            d = folds.block_nll(p_base) - folds.block_nll(p_e)
            d = d[used]
            d = d[np.abs(d) > 1e-9]  # blocks the effect cannot reach carry no evidence
            t, pv = t_test(d)
        else:
            # an effect that spreads the reads: its gain beyond the denoising it buys
            less = (folds.block_source_gain(p_base, p_e) if effect in _SPREADING else None)
            d, t, pv = _weighted_gain(folds, p_base, p_e, used, less)
            if effect == "misregistration":
                d, t, pv = _against_mirror(folds, p_e, (d, t, pv), used)
        gain = float(d.sum()) / max(nvalid, 1)
        est = readable_estimate(effect, average_params(p_e), channels)
        f = findings[effect] = Finding(effect, False, t, pv, est, "", gain, rnd,
                                       edge=on_edge(effect, p_e, channels, folds.bounds))
        f.explain(False, gain, replaced_by=replaced_by.get(effect))
        return effect, pv, gain, p_e

    cur_params = folds.fit(current, [null, null], channels)
    # the other winners of the round each effect joined, with their test in that round
    # (statistic, p, gain, round): an exchange reports the rival's own evidence
    rivals: dict[str, dict[str, tuple]] = {}
    visited = {current}
    contained: set[str] = set()  # left out because another joined with their parameters
    while True:
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
            base_model = current | nuisance
            if _better_base(folds, base_model, winners, channels):
                # a winner's fit showed the current model a better basin: every winner is
                # measured again from there, so what it gains is its own
                p_base = folds.fit(base_model, cur_params, channels)
                tested = [score(e, p_base, p_e) if any(e == w[0] for w in winners)
                          else (e, pv, gain, p_e) for e, pv, gain, p_e in tested]
                winners = [r for r in tested if r[1] < level and r[2] >= min_gain]
                if "noise" not in base_model:
                    cur_params = p_base
            winners_all = list(winners)
            if not winners and "noise" in candidates:
                winners = [r for r in [test(current, "noise", cur_params)]
                           if r[1] < level and r[2] >= min_gain]
            for e, pv, gain, _ in tested:
                if pv < level and gain < min_gain:
                    findings[e].explain(False, gain, too_small=True,
                                        replaced_by=replaced_by.get(e))
            winners = _sufficient(winners, folds, level, used)
            if not winners:
                break
            e, pv, gain, _ = _joining(winners, folds, level, used)
            rivals[e] = {c: (findings[c].statistic, findings[c].p_value, findings[c].nll_gain,
                             rnd) for c, *_ in winners_all
                         if c not in (e, "noise") and not _nested(c, e, channels)}
            findings[e].significant = True
            findings[e].explain(True, gain)
            order.append(e)
            current = current | {e}
            cur_params = folds.fit(current, cur_params, channels)
            candidates.remove(e)
            # an effect whose parameters all joined with another (response_imax's rho, inside
            # response_shape) has nothing left to add
            have = set(free_params(current, channels))
            for c in [c for c in candidates if set(EFFECTS[c].params(channels)) <= have]:
                candidates.remove(c)
                contained.add(c)
                findings[c].explanation = (f"{c}: {EFFECTS[c].what}. Contained in {e}, which "
                                           "joined the model with its parameters.")
        # an exchange: a rival of a joined effect (significant in the round it joined) that
        # predicts the held-out blocks significantly better in its place, or as well with
        # fewer parameters
        swap = _best_swap(folds, current, order, rivals, candidates, cur_params, visited,
                          alpha, min_gain, used, earlier)
        if swap is not None:
            out, into, p_change, gain = swap
            f = findings[into]
            f.significant = True
            f.statistic, f.p_value, f.nll_gain, f.round = rivals[out][into]
        else:
            # no exchange left: a joined effect that the rival which joined on top of it makes
            # redundant leaves; the same outcome as an exchange, reached the other way round
            drop = _redundant(folds, current, order, rivals, candidates, cur_params, visited,
                              alpha, min_gain, used)
            if drop is None:
                break
            out, into, p_change, keep = drop
            gain = -keep  # the held-out change of leaving it out
        exchange = into not in current
        current = (current - {out}) | {into}
        visited.add(current)
        # the change was decided with the noise free; refit from there, quieted if the model
        # has no noise effect
        quiet = {n: null[n] for n in EFFECTS["noise"].params(channels)}
        start = p_change if "noise" in current else [{**q, **quiet} for q in p_change]
        cur_params = folds.fit(current, start, channels)
        if exchange:
            order[order.index(out)] = into
            candidates.remove(into)
            candidates.append(out)  # it may still join, on top of its replacement
        else:
            order.remove(out)  # shown to add nothing to a model that keeps its rival
        candidates += _testable_again(contained, current, candidates, channels)
        replaced[into] = (out, gain)
        replaced_by[out] = into
        findings[out].significant = False
        findings[out].explain(False, findings[out].nll_gain, replaced_by=into)
    _note_toe(findings, current, folds.bounds)
    ranked = [findings[e] for e in order] + sorted(
        (f for e, f in findings.items() if e not in order), key=lambda f: -f.statistic)
    base_p = folds.fit(frozenset(), [null, null], channels)
    full = fit_all(pack(groups), free_params(current, channels), cur_params,
                   sum(int(g.valid.sum()) for g in groups), folds.bounds)
    for f in ranked:
        if f.significant:
            f.estimate = readable_estimate(f.effect, full, channels)
            f.edge = on_edge(f.effect, [full], channels, folds.bounds)
            f.explain(True, f.nll_gain, replaced=replaced.get(f.effect))
            f.interval = intervals(groups, full, f.effect, channels, folds.bounds)
    b_rmse, b_nll, b_pred = heldout_scores(groups, base_p)
    x_rmse, x_nll, x_pred = heldout_scores(groups, cur_params)
    left = leftover(folds, cur_params, used, groups, alpha, min_gain)
    _note_misfit(ranked, left)
    domain = mixing_domain(full, channels, code_shares(groups, channels))
    return Selection(order, ranked, full, b_rmse, x_rmse, b_nll, x_nll, b_pred, x_pred, skip,
                     left, domain)


# codes: a black level can hide below the darkest codes the data show when they lie this far
# up or more (``_note_toe``)
TOE_CODES = 3.0
# effects that absorb part of a black level the shape's toe hides (``_note_toe``): a code
# offset and a common exposure factor bend the cross-exposure relation near black alike
STAND_INS = frozenset({"quantisation", "exposure_gain"})


def _note_toe(findings: dict[str, Finding], current: frozenset,
              bounds: dict[str, tuple[float, float]]) -> None:
    """Add to a black level left out beside a joined response shape that the data cannot
    tell the two apart below their darkest codes.

    The free shape bends its toe so that the darkest codes seen map near zero light, and so
    absorbs much of a pedestal that lies below them: on exposure series of a gamma-2.2
    camera 10 codes above black, whose darkest codes lay near 30, the pedestal beat the
    absorbing shape by 0.0003 - 0.0006 nats per value, far below the least gain
    (``docs/studies/method.md``, Detection limits).  A report that names only the shape
    there should say so; the darkest codes are the black level's bound
    (``physical_bounds``, the darkest patches of a series)."""
    black = findings.get("black_level")
    levels = [hi for name, (_, hi) in bounds.items() if name.startswith("black")]
    if (black is None or black.significant or "black_level" in current
            or "response_shape" not in current or not levels):
        return
    dark = 255.0 * min(levels)
    if dark >= TOE_CODES:
        black.explanation += (
            f" The darkest patches of the data lie near {dark:.0f} codes (the most a black "
            "level may be; single noisy pixels go lower): a black level under that trades "
            "with the toe of the response shape, which can absorb it over the codes seen, so "
            "these data may not tell the two apart (frames whose patches reach near black "
            "do).")
        proxies = sorted(current & STAND_INS)
        if proxies:
            black.explanation += (
                f" {' and '.join(proxies)}, joined here, can stand in for such a black level "
                "(a filmic camera 16 codes above black read as a +1-code quantisation offset "
                "and an exposure gain of 0.97): read them with that in mind.")


# effects that can take up what the response family cannot follow (``_note_misfit``): a black
# level bends the toe, a code offset shifts every code.  On ten random 8-component EMoR
# cameras with neither (``docs/studies/validation.md``, ten cameras), levels of 5 - 20 codes
# were named on 8 and offsets of 0.7 - 1 code on 6, always beside a significant leftover by
# code
MISFIT_STAND_INS = ("black_level", "quantisation")


def _note_misfit(ranked: list[Finding], left: dict | None) -> None:
    """Add to a named black level or code offset that the model leaves structure by code.

    Where the response family cannot follow the camera's curve (a toe steeper than its
    middle, say), part of the misfit goes to these two effects, and the data cannot tell
    that part from a real level or offset.  The leftover's ``by_code`` alternative (per-code
    offsets on top of the model) is the symptom; it is reported either way, so this note only
    puts it beside the effects it puts in doubt."""
    code = (left or {}).get("by_code") or {}
    if not code.get("significant"):
        return
    for f in ranked:
        if f.significant and f.effect in MISFIT_STAND_INS:
            f.explanation += (
                " The model leaves structure by code here (the leftover): the response family "
                "does not follow this curve everywhere, and a "
                + ("black level" if f.effect == "black_level" else "code offset")
                + " can stand in for part of that misfit (a toe steeper than the curve's "
                "middle reads as one), so read its size with that in mind.")


def on_edge(effect: str, fits: list[dict], channels: int,
            bounds: dict[str, tuple[float, float]] | None = None) -> list[str]:
    """The parameters of ``effect`` that a fit in ``fits`` left on a bound of their range
    other than their null value (``effects.PARAMS``, or ``bounds``: a black level's darkest
    code).  A null on its bound (no black level, no extra noise, ``rho = 1``) is no
    symptom, nor is a bound that is a limit of the family (``effects.FAMILY_LIMITS``: ``rho``
    at its least, the power law); a factor driven to the end of its range is: the data did
    not stop it."""
    bounds = bounds or {}
    out = set()
    for q in fits:
        for n in effect_keys(effect, channels, q):
            if n not in q or n.startswith("flip:"):
                continue
            null, lo, hi = param_range(n)
            lo, hi = bounds.get(n, (lo, hi))
            tol = 1e-4 * (hi - lo)
            v = q[n]
            at = [b for b in (lo, hi) if abs(v - b) <= tol and b != null]
            if at and FAMILY_LIMITS.get(n) not in at:
                out.add(n)
    return sorted(out)


def _edge_note(edge: list[str], significant: bool = False) -> str:
    """A sentence for a finding whose fit ran to the edge of a parameter's range
    (``on_edge``): its estimate is where the optimiser stopped, not a measurement.
    Memorial's free exposure times, not significant, bowed to the bound of two frames while
    the curve's warp gave way (docs/studies/validation.md).  For a finding that joined the
    model the bound is what the fit could not pass (the range's end, or what the data allow:
    a black level at the darkest code they show), so its estimate is that limit."""
    if not edge:
        return ""
    where = f" Its fit ran to the edge of the range of {', '.join(edge)}:"
    if significant:
        return where + " the estimate there is that limit, not a measurement of the effect."
    return where + (" the data do not pin this effect down there, and the estimate is no "
                    "measurement of it.")


def _testable_again(contained: set[str], current: frozenset, candidates: list[str],
                    channels: int) -> list[str]:
    """The effects once left out as contained in a joined one (response_imax in
    response_shape) whose parameters are no longer all in the model: after an exchange or a
    drop took that effect out, they can add something again."""
    have = set(free_params(current, channels))
    return [c for c in sorted(contained) if c not in current and c not in candidates
            and not set(EFFECTS[c].params(channels)) <= have]


def _nested(a: str, b: str, channels: int) -> bool:
    """Whether one effect's parameters contain the other's (response_imax in response_shape)."""
    pa, pb = set(EFFECTS[a].params(channels)), set(EFFECTS[b].params(channels))
    return pa <= pb or pb <= pa


# effects a swap never moves: the conditional fits hold the rest of the model fixed, and the
# discrete flips have no null start to replace
_NO_SWAP = CONDITIONAL | {"psf_orientation", "noise"}


def _better_base(folds: Folds, model: frozenset, winners: list[tuple], channels: int) -> bool:
    """Whether a winner's fit, its effect at the null value, gives ``model`` (the current
    model with the round's nuisance) a better fit than its own search found on either fold
    (``Folds.improve``, which then keeps it).

    A test's extension searches starts of its own (the response shape's, a pedestal), so
    its fit can find a basin of the shared parameters that the current model's fit missed.
    Measured against the poorer fit, the extension gains what the optimiser found: a
    linear camera 7.65 codes above black, once its black level had joined, passed
    ``channel_shape`` with exponents within 0.3 % of each other and 0.010 nats per value.
    """
    improved = False
    for effect, *_, p_e in winners:
        if effect not in _NO_SWAP:
            improved |= folds.improve(model, _at_null(p_e, effect, channels), channels)
    return improved


def _current_fit(folds: Folds, current: frozenset, candidates: list[str],
                 cur_params: list[dict]) -> tuple[frozenset, list[dict]]:
    """The noise nuisance (when it is a candidate) and the current model's fit with it:
    what an exchange or a removal is measured against, and where its fits start."""
    nuisance = frozenset({"noise"}) if "noise" in candidates else frozenset()
    return nuisance, folds.fit(current | nuisance, cur_params, folds.part[0][0].channels)


def _at_null(fits: list[dict], effect: str, channels: int) -> list[dict]:
    """Each fold's parameters with ``effect``'s at their null values (the effect taken out,
    the rest kept as a start).  An image's own parameters (``lt:I``, ``lw:I:c``) are left
    out, which reads as nominal: a model without the effect holds none, and a start that
    kept them made a fold's fit that ``Folds.improve`` keeps hold keys its other fold's
    fit lacked (a study stopped on the white balance's keys, 2026-12-07)."""
    out = []
    for q in fits:
        keys = effect_keys(effect, channels, q)
        out.append({**{k: v for k, v in q.items() if not (k in keys and is_per_image(k))},
                    **{n: param_range(n)[0] for n in keys if not is_per_image(n)}})
    return out


def _best_swap(folds: Folds, current: frozenset, order: list[str],
               rivals: dict[str, dict[str, tuple]], candidates: list[str],
               cur_params: list[dict],
               visited: set, alpha: float, min_gain: float, used: np.ndarray,
               earlier: dict[str, list[dict]]) -> tuple | None:
    """The best exchange of a joined effect for one of its rivals, or ``None``.

    Forward selection commits to the larger held-out gain even when two effects explain
    the same deviation almost equally well at that round (a gain of 1.005 and a -0.5 code
    offset, both seen through the paper's wrong response; a free response shape and an
    offset on top of a gain); the effects that join later can then favour the other, or
    show that the two are interchangeable.  So, once no effect joins, each joined effect
    ``e`` is tried against each rival ``c`` (significant in the round ``e`` joined): the
    model with ``c`` in place of ``e`` is fitted from the rival's own earlier fit (and the
    response shape's starts) and compared with the current one on the held-out blocks, by
    the block-robust test of an addition (``_weighted_gain``), at ``alpha`` over the number
    of exchanges tried, with the same least gain.  The exchange is made

    * when ``c`` predicts significantly better (an *improvement*), or
    * when ``c`` has fewer parameters and ``e`` does not predict significantly better
      (a *simplification*: of two interchangeable explanations the simpler one, as
      ``_sufficient`` prefers ``response_imax`` to ``response_shape``), or
    * when ``c`` has as many parameters and predicts better, though not significantly or
      by less than the least gain (a *tie*: of two interchangeable explanations of one size
      the better predictor, not the one that happened to join first; which one joins first
      can turn on rounding: a truncated frame stack names a gain of 0.995 or the -0.5 code
      offset depending on the CPU's BLAS kernels, and the offset predicts better by 0.004
      nats per value once the response shape has joined).

    Improvements go first (the largest gain), then simplifications (the fewest parameters),
    then ties (the largest gain).
    Returns ``(out, into, params, gain)``: ``gain`` is the held-out gain of ``c``'s model
    over ``e``'s.  A model once left is never entered again,
    so the search ends.
    """
    channels = folds.part[0][0].channels
    pairs = [(e, c) for e in order if e not in _NO_SWAP for c in rivals.get(e, ())
             if c in candidates and c not in _NO_SWAP and c in earlier
             and (current - {e}) | {c} not in visited]
    if not pairs:
        return None
    level = alpha / len(pairs)
    nuisance, base = _current_fit(folds, current, candidates, cur_params)
    nvalid = max(sum(folds.nvalid), 1)
    improve, simplify, tie = [], [], []
    for e, c in pairs:
        model = (current - {e}) | {c} | nuisance
        start = [{**q, **{n: earlier[c][f][n] for n in effect_keys(c, channels, earlier[c][f])}}
                 for f, q in enumerate(_at_null(base, e, channels))]
        p = folds.fit(model, start, channels, shape_search="response_shape" in model)
        d, _, pv = _weighted_gain(folds, base, p, used)
        gain = float(d.sum()) / nvalid
        if pv < level and gain >= min_gain:
            improve.append((e, c, p, gain))
            continue
        size, size_e = len(EFFECTS[c].params(channels)), len(EFFECTS[e].params(channels))
        if size < size_e:
            d_back, _, pv_back = _weighted_gain(folds, p, base, used)
            if not (pv_back < level and float(d_back.sum()) / nvalid >= min_gain):
                simplify.append((size, (e, c, p, gain)))
        elif size == size_e and gain > 0.0:
            tie.append((e, c, p, gain))
    if improve:
        return max(improve, key=lambda r: r[3])
    if simplify:
        return min(simplify, key=lambda r: r[0])[1]
    if tie:
        return max(tie, key=lambda r: r[3])
    return None


def _redundant(folds: Folds, current: frozenset, order: list[str],
               rivals: dict[str, dict[str, tuple]], candidates: list[str],
               cur_params: list[dict], visited: set, alpha: float, min_gain: float,
               used: np.ndarray) -> tuple | None:
    """A joined effect that a rival which joined after it makes redundant, or ``None``.

    The exchange (``_best_swap``) replaces a joined effect by a rival still outside the
    model.  When the rival joined on top of it instead (which order the two take can turn
    on rounding: a truncated frame stack seen through the paper's response names a gain of
    0.995 first on one machine, and the offset joins after the response shape on another),
    the exchange has nothing to swap in.  So each joined effect ``e`` with a rival in the
    model is tested for removal: the model without ``e`` is fitted (from the current fit,
    ``e``'s parameters at null, and the response shape's starts) and ``e`` is tested as an
    addition to it
    (``_weighted_gain``, at ``alpha`` over the number of effects tried, the same least
    gain).  Of those that add nothing significant, the one with the smallest gain is
    dropped.  Returns ``(dropped, its rival in the model, params without it, gain of
    keeping it)``.  A model once left is never entered again."""
    channels = folds.part[0][0].channels
    # the rival in the model is the one that joined last: it joined on top of ``e``
    tried = [(e, max((c for c in rivals[e] if c in current), key=order.index)) for e in order
             if e not in _NO_SWAP and any(c in current for c in rivals.get(e, ()))
             and current - {e} not in visited]
    if not tried:
        return None
    level = alpha / len(tried)
    nuisance, base = _current_fit(folds, current, candidates, cur_params)
    nvalid = max(sum(folds.nvalid), 1)
    weakest = None
    for e, rival in tried:
        # searched as an exchange's fit is: without e the response shape's optimum can lie
        # in another basin than the one the start (the current fit) sits in
        model = (current - {e}) | nuisance
        p = folds.fit(model, _at_null(base, e, channels), channels,
                      shape_search="response_shape" in model)
        d, _, pv = _weighted_gain(folds, p, base, used)
        gain = float(d.sum()) / nvalid
        if (pv >= level or gain < min_gain) and (weakest is None or gain < weakest[3]):
            weakest = (e, rival, p, gain)
    return weakest


def _weighted_gain(folds: Folds, base: list[dict], ext: list[dict], used: np.ndarray,
                   less: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Held-out gain per block from ``base`` to ``ext`` (blocks either reaches), with the
    block-robust test's statistic and p-value (``significance.weighted_test``); ``less``:
    per block, a part of the gain that names no cause, taken off (``_SPREADING``)."""
    d, u, a = folds.block_score(base, ext)
    if less is not None:
        d = d - less
    reach = used & (a > 1e-12)  # blocks the effect cannot reach carry no evidence
    return (d[reach], *weighted_test(d[reach], u[reach], a[reach]))


def _against_mirror(folds: Folds, p_e: list[dict], against_base: tuple,
                    used: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The misregistration test against the fitted shift's mirror image as well as the
    model without it: whichever of the two gains is smaller.

    Why: a sub-pixel shift mixes each source pixel with a neighbour, which also averages
    the source's noise.  On a noisy exposure series with no shift at all, any small shift
    then predicts the target better than none (48 x 64, Poisson ``a = 5e-4``: a shift of
    0.1 - 0.2 px "significant" on every seed tried).  The opposite shift averages as much;
    only a real shift predicts better than its mirror image, which a real shift makes worse
    than no shift, so this costs a real one nothing."""
    mirror = [{**q, "sx": -q["sx"], "sy": -q["sy"]} for q in p_e]
    d, t, pv = _weighted_gain(folds, mirror, p_e, used)
    return (d, t, pv) if d.sum() < against_base[0].sum() else against_base


# Effects that change which source pixels a prediction reads, and how many: tested on their
# gain beyond the source noise that reading more of them averages away
# (``Folds.block_source_gain``).  Why: blurring the prediction averages more of a noisy
# source's pixels, which predicts a noisy pair better whether or not the target is blurred
# (48 x 64 pairs, Poisson ``a = 2e-3``, nothing blurred: a variance of 0.3 - 0.4 px^2
# "significant" on 2 of 4 seeds).  What is left is the blur's bias: negative where the
# target holds no blur, positive where it does, so a real blur keeps its evidence.  A longer
# path (``psf_scale``) spreads a PSF's weight over more pixels too, and without the same
# control it took a real blur's place on a noisy pair (with ``misregistration``).
# misregistration has its own control (_against_mirror: its mirror averages as much).
_SPREADING = frozenset({"optical_blur", "psf_scale"})


def _sufficient(winners: list[tuple], folds: Folds, level: float,
                used: np.ndarray) -> list[tuple]:
    """Drop a winner that contains a smaller winner (all of its parameters and more) but does
    not predict the held-out blocks significantly better than it: nested model choice, so
    a linear camera reads as Eq. 3 with a high ``Imax`` (``response_imax``), not as a free
    ``response_shape``.  Winners are ``(effect, p, gain, fitted params)`` from one round,
    whose fits share the current model, so both fits compared here are already cached."""
    channels = folds.part[0][0].channels
    own = {r[0]: set(EFFECTS[r[0]].params(channels)) for r in winners}
    keep = []
    for r in winners:
        better = True
        for s in winners:
            if s is not r and own[s[0]] < own[r[0]]:
                better &= _weighted_gain(folds, s[3], r[3], used)[2] < level
        if better:
            keep.append(r)
    return keep


def _joining(winners: list[tuple], folds: Folds, level: float, used: np.ndarray) -> tuple:
    """The winner that joins the model: the one with the largest held-out gain, unless a
    winner with fewer parameters predicts the held-out blocks not significantly worse
    than it (``_weighted_gain`` of the largest over the smaller, at the round's ``level``:
    the test of ``_sufficient``, for winners that are not nested); then the fewest
    parameters among those, the larger gain breaking a tie.

    Why: when two explanations tie, which gain is the larger turns on rounding.  On
    Memorial's dark frames the black level (3 parameters) gains 60 404 nats in round 1 on
    any machine, the free response shape (6) 61 525 with numpy's AVX-512 kernels and 58 975
    without, as its fit lands in one basin or another; the path, and the verdict, followed.
    The simpler of two indistinguishable explanations is the one to commit to (the rule of
    ``_sufficient`` and of the exchange's simplification); the other stays a rival, so the
    exchange still puts it in place if the model then favours it.  Winners are
    ``(effect, p, gain, fitted params)`` of one round, whose fits share the current model."""
    channels = folds.part[0][0].channels
    top = max(winners, key=lambda r: r[2])

    def size(r: tuple) -> int:
        return len(EFFECTS[r[0]].params(channels))

    close = [top]
    for r in winners:
        if r is not top and size(r) < size(top):
            # significance alone, as in _sufficient: a larger model that predicts
            # significantly better is the explanation, however small the difference (a
            # gamma-1.6 camera: the free shape over Eq. 3 with a high Imax by 0.004 nats)
            if _weighted_gain(folds, r[3], top[3], used)[2] >= level:
                close.append(r)
    return min(close, key=lambda r: (size(r), -r[2]))


# readable name and transform of each continuous parameter, for the intervals
_READABLE = {"black": ("black_level_codes", lambda v: 255.0 * v), "gamma": ("gamma", None),
             "rho": ("rho", None), "sat": ("factor", None), "gain": ("gain", math.exp),
             "vig": ("c", None), "t1": ("t1", None), "t2": ("t2", None), "na": ("a", None),
             "nb": ("b", None), "nc": ("code_variance", None),
             "qoff": ("offset_codes", None), "sx": ("shift_x", None),
             "sy": ("shift_y", None), "pscale": ("scale", None),
             "ovar": ("variance_px2", None)}


def intervals(groups: list[Group], p: dict, effect: str, channels: int,
              bounds: dict[str, tuple[float, float]] | None = None) -> dict | None:
    """95 % confidence intervals of an effect's parameters: block-robust sandwich.

    ``cov = H^-1 M H^-1`` with ``H`` the Hessian of the total NLL in the effect's parameters
    (finite differences, the other parameters held at their fit) and ``M = sum_b s_b s_b^T``
    the outer product of per-block scores, so correlated residuals inside a block widen the
    interval.  Intervals are centred on the estimate and cut to the physically possible
    range (parameter bounds, e.g. a black level no higher than the darkest code seen): an
    estimate on its bound gets ``[bound, estimate + half width]``, the differences taken
    one step inside.  Conditional on the other
    parameters, so somewhat narrow when parameters trade off.  ``None`` for discrete effects.
    The response's effects also give ``gamma``, the effective gamma's interval (the delta
    method, :func:`_effective_gamma_interval`), with the family's exponent as ``exponent``:
    the keys of ``effects.readable_estimate``.
    """
    names = effect_keys(effect, channels, p)
    if not names or effect == "psf_orientation":
        return None
    bounds = bounds or {}
    lo = np.array([bounds.get(n, param_range(n)[1:])[0] for n in names])
    hi = np.array([bounds.get(n, param_range(n)[1:])[1] for n in names])
    h = 1e-4 * (hi - lo)
    # finite differences around a point at least one step inside the bounds (an estimate on
    # a bound, such as rho = 1, would otherwise step out of the family's range)
    x0 = np.clip(np.array([p[n] for n in names]), lo + h, hi - h)
    nblocks = int(max(int(g.block.max()) for g in groups)) + 1
    packed = pack(groups)

    def nll_blocks(x):
        q = {**p, **dict(zip(names, x, strict=True))}
        if not time_ok(q):
            return None
        out = np.zeros(nblocks)
        for g in packed:
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
    # the fits minimise the NLL plus the warp's ridge (crossfit.penalised_nll): its
    # curvature belongs to the estimator's Hessian (the sandwich of a penalised fit), and
    # bounds the directions in which the exponent and the warp trade at equal likelihood
    for i, n in enumerate(names):
        if n in WARP_KEYS:
            hess[i, i] += 2.0 * WARP_RIDGE
    try:
        hinv = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return None
    meat = score.T @ score
    cov = hinv @ meat @ hinv
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0) or np.any(np.diag(hess) <= 0):
        return None
    half = 1.96 * np.sqrt(np.diag(cov))
    # centred on the estimate itself: x0 only keeps the differences inside the bounds, and an
    # estimate on its bound (no black level, no extra noise) gets [bound, estimate + half]
    est = np.clip(np.array([p[n] for n in names]), lo, hi)
    ranges = [(max(lo[i], est[i] - half[i]), min(hi[i], est[i] + half[i])) for i in range(k)]
    if effect == "black_level" and k > 1:
        # one level per channel (effects.readable_estimate): each channel's interval, and
        # the interval of their mean (its variance 1' cov 1 / k^2), cut to the bounds' mean
        mean, mhalf = est.mean(), 1.96 * math.sqrt(max(float(cov.sum()), 0.0)) / k
        out = {"black_level_codes": [255.0 * max(lo.mean(), mean - mhalf),
                                     255.0 * min(hi.mean(), mean + mhalf)],
               "channel_codes": [[255.0 * a, 255.0 * b] for a, b in ranges]}
    elif effect == "exposure_times":  # as readable_estimate: the factor on each image's time
        out = {"exposure_factors": {n[3:]: [math.exp(a), math.exp(b)]
                                    for n, (a, b) in zip(names, ranges, strict=True)}}
    elif effect == "white_balance":  # image I, channel c: its gain against channel 0
        out = {"gain_against_first_channel": {n[3:]: [math.exp(a), math.exp(b)]
                                              for n, (a, b) in zip(names, ranges, strict=True)}}
    else:
        out = {}
        for n, (a, b) in zip(names, ranges, strict=True):
            key, fn = _READABLE.get(n, (n, None))
            a, b = (fn(a), fn(b)) if fn else (a, b)
            out[key] = [float(a), float(b)]
    if effect in ("response_shape", "response_imax"):
        # the estimates' "gamma" is the effective gamma (effects.readable_estimate); the
        # family's own exponent is "exponent" there and here
        if "gamma" in out:
            out["exponent"] = out.pop("gamma")
        out["gamma"] = _effective_gamma_interval(
            {**p, **dict(zip(names, est, strict=True))},
            {**p, **dict(zip(names, x0, strict=True))}, names, h, cov)
    return out


def _effective_gamma_interval(p: dict, inside: dict, names: list[str], h: np.ndarray,
                              cov: np.ndarray) -> list[float]:
    """95 % interval of ``effects.effective_gamma`` around its value at ``p``: the delta
    method on the parameters' covariance ``cov`` (the sandwich of :func:`intervals`), with
    the gradient by central differences of step ``h`` at ``inside`` (``p`` moved at least
    one step inside the bounds).

    Why: the effective gamma is what a user reads (2.2 for a display gamma, 1 for a linear
    camera), while with the free warp the exponent alone trades with the warp and its
    interval says little about the curve."""
    from clblur.study.effects import effective_gamma

    grad = np.zeros(len(names))
    for i, n in enumerate(names):
        up, down = dict(inside), dict(inside)
        up[n] += h[i]
        down[n] -= h[i]
        grad[i] = (effective_gamma(up) - effective_gamma(down)) / (2.0 * h[i])
    centre = effective_gamma(p)
    half = 1.96 * float(np.sqrt(max(grad @ cov @ grad, 0.0)))
    return [centre - half, centre + half]


