"""Cross-fitting: block folds, maximum-likelihood fits on one fold, scores on the other.

Target pixels are cut into square blocks that alternate between two folds like a
checkerboard (``assign_blocks``); a model is fitted (``fit``: maximum likelihood,
``clblur.study.variants.pixel_nll``) on one fold and scored on the other, both ways round, so
every block is scored by parameters that never saw it (``clblur.study.select`` tests and
selects on these scores).

Conventions
-----------
Fold ``f`` of a group holds the rows with ``Group.fold == f``; parameters ``params[1 - f]``
(fitted on the other fold) score it.  RMSE is in 8-bit codes, NLL per valid pixel value.
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np
from scipy import optimize

from clblur.study.compact import compact
from clblur.study.effects import (
    EFFECTS,
    PARAMS,
    PER_IMAGE,
    black_names,
    image_keys,
    is_per_image,
    param_range,
)
from clblur.study.gradient import is_analytic, nll_gradient
from clblur.study.model import WARP_KEYS, Group, observed_mean, time_ok
from clblur.study.shape_start import shape_starts
from clblur.study.variants import (
    darkest_codes,
    geometric,
    has_variant,
    pack,
    pixel_nll,
    predict,
    subset,
)

__all__ = ["CONDITIONAL", "assign_blocks", "applicable", "block_terms", "physical_bounds",
           "fit", "fit_all", "penalised_nll",
           "Folds", "free_params",
           "average_params", "heldout_scores", "series_images"]


def fold_part(g: Group, f: int) -> Group:
    """The rows of ``g`` in fold ``f`` (cached: copying every histogram is not free)."""
    cache = g.__dict__.setdefault("_folds", {})
    if f not in cache:
        cache[f] = subset(g, g.fold == f)
    return cache[f]


def assign_blocks(groups: list[Group], blocks_per_group: int = 64, split: int = 0) -> int:
    """Give every target pixel a block id and a fold; returns the number of blocks.

    ``split`` 0 is the checkerboard of blocks.  ``split`` s > 0 draws another split of the
    same blocks: in each group a random half of the blocks that hold its pixels (seeded by
    ``(s, group)``) forms fold 0, so repeated splits are reproducible and balanced.
    """
    offset = 0
    for gi, g in enumerate(groups):
        h, w = g.shape
        side = max(4, int(round(math.sqrt(h * w / blocks_per_group))))
        br, bc = g.rows // side, g.cols // side
        ncols = (w + side - 1) // side
        nblocks = ((h + side - 1) // side) * ncols
        g.block = offset + br * ncols + bc
        if split == 0:
            g.fold = ((br + bc + gi) % 2).astype(np.int8)
        else:
            local = br * ncols + bc
            held = np.unique(local)  # blocks with sampled pixels
            fold = np.zeros(nblocks, np.int8)
            fold[np.random.default_rng([split, gi]).permutation(held)[held.size // 2:]] = 1
            g.fold = fold[local]
        g.__dict__.pop("_folds", None)
        g.__dict__["gid"] = gi  # psf_orientation is chosen per group
        offset += nblocks
    return offset


def applicable(groups: list[Group]) -> dict[str, str]:
    """Effects the data cannot show, with the reason."""
    out = {}
    if not any(g.source_clipped for g in groups):
        out["saturation"] = (
            "an exposure series' clipped source pixels bound their light from below only and "
            "are left out" if any(g.__dict__.get("clipped_left_out") for g in groups)
            else "no source pixel is clipped (code 255)")
    if not any((1, 0) in g.hist for g in groups):
        out["nonuniform_motion"] = "no time order along the motion (PSF, or exposure series)"
    if not any((0, 1) in g.hist for g in groups):
        out["vignetting"] = ("source and target share sensor positions, so a fixed falloff "
                             "cancels in Eq. 8")
    if groups[0].channels < 2:
        out["channel_gain"] = out["channel_shape"] = "single-channel images"
    if not has_variant(groups, "psf_orientation"):
        out["psf_orientation"] = "the motion path is its own 180-degree turn (centred path)"
    if not has_variant(groups, "psf_scale"):
        out["psf_scale"] = "no motion between source and target (stack or series)"
    if not has_variant(groups, "optical_blur"):
        out["optical_blur"] = ("source and target are not separate captures of a blur pair "
                               "(stack or series: the same optics and pipeline)")
    if not has_variant(groups, "misregistration"):
        out["misregistration"] = "groups built without shifted histograms"
    if not series_images(groups):
        out["exposure_times"] = out["white_balance"] = (
            "no exposure series of three images or more (the longest and the shortest "
            "exposure fix the scale and the exponent)")
    elif groups[0].channels < 2:
        out["white_balance"] = "single-channel images"
    return out


def series_images(groups: list[Group]) -> tuple[int, ...]:
    """The images of an exposure series whose own exposure a fit can free (``lt:I``): all
    but the longest and the shortest (``effects``); empty outside a series."""
    return tuple(sorted({i for g in groups for i in g.__dict__.get("inner_images", ())}))


def _expand(free: list[str], groups: list[Group]) -> list[str]:
    """``free`` with ``lt`` (``exposure_times``) read as one ``lt:I`` per inner image, and
    ``lw`` (``white_balance``) as one ``lw:I:c`` per inner image and channel but the first."""
    out = []
    for n in free:
        if n in PER_IMAGE:
            out += image_keys(n, series_images(groups), groups[0].channels)
        else:
            out.append(n)
    return out


def physical_bounds(groups: list[Group]) -> dict[str, tuple[float, float]]:
    """Parameter bounds the data impose: a channel's black level cannot exceed the darkest
    code seen in that channel."""
    dark = np.min([darkest_codes(g) for g in groups], axis=0)
    return {n: (0.0, min(PARAMS[n][2], max(float(d), 0.0) / 255.0))
            for n, d in zip(black_names(dark.size), dark, strict=True)}


# Ridge on the response warp (total nats per unit coefficient squared): where a power law or
# Eq. 3 curvature already fits, the warp and ``gamma`` trade along a nearly flat valley and the
# optimiser stops anywhere in it (a gamma-2.2 stack read as gamma 1.8 plus warp).  A prior of
# scale ~0.2 on each coefficient picks the plain family there and costs an S-shaped camera
# curve, whose warp gains thousands of nats, nothing measurable.
WARP_RIDGE = 10.0
# the forward-difference step (in the fit's unit coordinates) of the parameters whose
# gradient is not in closed form: scipy's default for L-BFGS-B (``eps``)
_DIFFERENCE_STEP = 1e-8
_STOP = {"maxiter": 300, "ftol": 1e-7, "gtol": 1e-5}


# Effects tested conditionally: their extension fits free only the effect's own parameters
# (and the noise nuisance), the current model's held at its fit on the same fold.  They
# change the histogram rows, so their fits cannot run on pooled rows (``clblur.study.compact``)
# and cost 10-50x more per evaluation; with fewer free parameters the test stays nested and
# cross-fitted (the extension can only fit worse than a full refit: conservative).
CONDITIONAL = frozenset({"misregistration", "psf_scale", "optical_blur"})

# Black levels tried, as fractions of their bound, for a start with a pedestal beside a free
# response shape (``_pedestal_start``).
_PEDESTAL_FRACTIONS = (0.2, 0.4, 0.6, 0.8)


def _parallel_folds() -> bool:
    """Whether fold 1 gets a process of its own: with two or more cores for this process."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return ((cores or 1) >= 2 and bool(sys.executable)
            and os.environ.get("CLBLUR_STUDY_PROCESSES", "1") != "0")


class Folds:
    """The two folds of a set of groups, with the fits on each cached by effect set.

    Parameters
    ----------
    groups : list of Group
        Groups whose ``fold`` and ``block`` were set by ``assign_blocks``.
    nblocks : int
        Number of blocks (``assign_blocks``'s return value).

    Conventions
    -----------
    ``fit`` returns ``[params fitted on fold 0, params fitted on fold 1]``; the ``block_*``
    scores evaluate fold ``f`` with the parameters of fold ``1 - f``.

    The two folds' fits run side by side where this process has two cores: fold 1's in a
    child process that holds that fold from the first fit to ``close``
    (``clblur.study.fold_worker``; ``Folds`` is a context manager).  The fits are the
    sequential ones, bit for bit; ``CLBLUR_STUDY_PROCESSES=0`` keeps both in this process.
    """

    def __init__(self, groups: list[Group], nblocks: int):
        self.nblocks = nblocks
        # packed: the fits and block scores only sum over rows (``variants.pack``)
        self.part = [pack([fold_part(g, f) for g in groups]) for f in (0, 1)]
        self.nvalid = [sum(int(g.valid.sum()) for g in part) for part in self.part]
        self.cache: dict[frozenset, list[dict]] = {}
        self.bounds = physical_bounds(groups)
        self._worker = None  # clblur.study.fold_worker.FoldWorker, at the first fit

    def __enter__(self) -> Folds:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End fold 1's worker process, if one was started."""
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def fit(self, effects: frozenset, start: list[dict], channels: int,
            only: frozenset | None = None, warm: list[dict] | None = None,
            shape_search: bool = False) -> list[dict]:
        """Parameters fitted on each fold with ``effects`` free (cached per effect set).

        ``only``: free just these effects' parameters, the rest held at ``start`` (a
        conditional fit, see ``CONDITIONAL``).  ``warm``: per fold, a second start (the same
        extension fitted in an earlier round), which replaces the search over fixed starts.
        ``shape_search``: search the response shape's starts whatever ``start`` is.
        """
        key = (effects, only)
        if key not in self.cache:
            free = free_params(only if only is not None else effects, channels)
            warm = [None, None] if warm is None else warm
            if self._worker is None and _parallel_folds():
                # imported here: the child runs that module as a script, and a module the
                # package imported already would be run a second time
                from clblur.study.fold_worker import FoldWorker

                self._worker = FoldWorker(self.part[1], self.nvalid[1], self.bounds)
            if self._worker is not None:
                self._worker.submit(free, start[1], warm[1], shape_search)
            first = fit(self.part[0], free, start[0], self.nvalid[0], self.bounds, warm[0],
                        shape_search)
            second = (self._worker.result() if self._worker is not None else
                      fit(self.part[1], free, start[1], self.nvalid[1], self.bounds, warm[1],
                          shape_search))
            self.cache[key] = [first, second]
        return self.cache[key]

    def improve(self, effects: frozenset, starts: list[dict], channels: int) -> bool:
        """Descend from ``starts`` (one per fold) with ``effects`` free and keep, per fold,
        the result where it fits that fold better than the cached fit of ``effects``.

        A test's extension contains the model it extends: its fit with the effect at its
        null value is a start for the model itself, and can lie in a better basin than the
        model's own search reached (a free response shape beside a black level).  Measured
        against the poorer fit, the extension's gain would be the optimiser's, not the
        effect's.  Returns whether either fold's fit improved.
        """
        current = self.fit(effects, starts, channels)
        free = free_params(effects, channels)
        if self._worker is not None:
            self._worker.submit(free, starts[1], None, False, False)
        first = fit(self.part[0], free, starts[0], self.nvalid[0], self.bounds, search=False)
        second = (self._worker.result() if self._worker is not None else
                  fit(self.part[1], free, starts[1], self.nvalid[1], self.bounds,
                      search=False))
        better = [penalised_nll(part, new) < penalised_nll(part, old)
                  for part, new, old in zip(self.part, (first, second), current, strict=True)]
        if any(better):
            self.cache[(effects, None)] = [new if b else old for b, new, old
                                          in zip(better, (first, second), current, strict=True)]
        return any(better)

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
        out = np.zeros((3, self.nblocks))
        for f in (0, 1):
            for g in self.part[f]:
                pb, var = predict(g, base[1 - f])
                pe, var_e = predict(g, ext[1 - f])
                # kept values are compared with their mean given that they were kept
                pb, pe = observed_mean(g, pb, var), observed_mean(g, pe, var_e)
                out += block_terms(g, pb, pe, var, self.nblocks)
        return out[0], out[1], out[2]

    def block_source_gain(self, base: list[dict], ext: list[dict]) -> np.ndarray:
        """Per block: the part of ``block_score``'s gain ``D_b`` that ``ext`` is expected to
        win from the source's noise alone, ``sum_p (s_S - s_E) / (2 var)`` (``s``: the
        variance each model's prediction carries from its source pixels' noise and
        rounding, ``model.predict``'s source share).

        Why: where ``ext`` reads more source pixels per target pixel (a blur of the
        prediction), its prediction carries less of the source's noise, and it predicts a
        noisy pair better even where the target holds no such blur; that much of its gain
        names no cause.  Under the base model the expected ``D_b`` of a needless blur is
        this term less the blur's bias, and with a real blur this term plus the bias."""
        out = np.zeros(self.nblocks)
        for f in (0, 1):
            for g in self.part[f]:
                _, var, share_b = predict(g, base[1 - f], source_share=True)
                _, var_e, share_e = predict(g, ext[1 - f], source_share=True)
                less = np.where(g.valid, (share_b * var - share_e * var_e) / (2.0 * var), 0.0)
                out += np.bincount(g.block, less.sum(axis=1), minlength=self.nblocks)
        return out

    def block_nll(self, params: list[dict]) -> np.ndarray:
        """Held-out NLL per block: fold f scored with the parameters fitted on the other."""
        out = np.zeros(self.nblocks)
        for f in (0, 1):
            for g in self.part[f]:
                out += np.bincount(g.block, weights=pixel_nll(g, params[1 - f]),
                                   minlength=self.nblocks)
        return out


def block_terms(g: Group, pb: np.ndarray, pe: np.ndarray, var: np.ndarray,
                nblocks: int) -> np.ndarray:
    """``(D_b, U_b, A_b)`` of ``Folds.block_score`` (3 x ``nblocks``) of ``g``'s held-out
    values, from the base and the extended prediction ``pb``, ``pe`` and the base variance
    ``var`` (values that are not valid count for nothing)."""
    delta = np.where(g.valid, pe - pb, 0.0)
    y = g.target
    return np.stack([
        np.bincount(g.block, (delta * (y - 0.5 * (pb + pe)) / var).sum(axis=1),
                    minlength=nblocks),
        np.bincount(g.block, (delta * (y - pe) / var).sum(axis=1), minlength=nblocks),
        np.bincount(g.block, (delta * delta / var).sum(axis=1), minlength=nblocks)])


def fit(groups: list[Group], free: list[str], start: dict, nvalid: int,
        bounds: dict[str, tuple[float, float]] | None = None,
        warm: dict | None = None, shape_search: bool = False, search: bool = True) -> dict:
    """Maximum-likelihood fit of the ``free`` parameters from ``start`` (and ``warm``, an
    earlier fit of the same parameters, if given).  The response shape's starts (the
    cross-exposure curve or the power-law corners) are searched when ``start`` is the
    paper's Eq. 3, or always with ``shape_search``; ``search=False``: one descent from
    ``start``, no other start.

    ``flip`` (``psf_orientation``) is discrete and separate per group: it is chosen by the
    group's likelihood given the other parameters, alternating with the continuous fit.
    """
    if "flip" not in free:
        return _fit_continuous(groups, free, start, nvalid, bounds, warm, shape_search, search)
    rest = [n for n in free if n != "flip"]
    p = dict(start)
    for _ in range(3):
        chosen = _choose_flips(groups, p)
        if all(p.get(k) == v for k, v in chosen.items()) and _ > 0:
            break
        p.update(chosen)
        p = _fit_continuous(groups, rest, p, nvalid, bounds, search=search)
    return p


def fit_all(groups: list[Group], free: list[str], fold_params: list[dict], nvalid: int,
            bounds: dict[str, tuple[float, float]] | None = None) -> dict:
    """The parameters fitted on all pixels (the reported estimate), started from each fold's
    fit and from their mean, whichever ends with the best penalised likelihood.

    The mean alone is not enough: where the two folds settled in different basins of the
    response shape (a power law against Eq. 3 with a warp), their mean lies in neither.
    """
    starts = [average_params(fold_params), *fold_params]
    return min((fit(groups, free, s, nvalid, bounds) for s in starts),
               key=lambda p: penalised_nll(groups, p))


def penalised_nll(groups: list[Group], p: dict) -> float:
    """The objective every fit minimises: total NLL plus the warp's ridge."""
    return sum(float(pixel_nll(g, p).sum()) for g in groups) + _ridge(p)


def _ridge(p: dict) -> float:
    return WARP_RIDGE * sum(p.get(k, 0.0) ** 2 for k in WARP_KEYS)


def free_params(effects, channels: int) -> list[str]:
    """The parameters ``effects`` free, each once (effects may share one: ``rho``)."""
    return list(dict.fromkeys(n for e in sorted(effects) for n in EFFECTS[e].params(channels)))


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
                    bounds: dict[str, tuple[float, float]] | None = None,
                    warm: dict | None = None, shape_search: bool = False,
                    search: bool = True) -> dict:
    names = list(dict.fromkeys(_expand(free, groups)))
    if not names:
        return dict(start)
    # an image's exposure that an earlier fit left out starts at its nominal value
    start = {**{n: param_range(n)[0] for n in names if n not in start}, **start}
    bounds = bounds or {}
    lo = np.array([bounds.get(n, param_range(n)[1:])[0] for n in names])
    hi = np.array([bounds.get(n, param_range(n)[1:])[1] for n in names])
    hi = np.maximum(hi, lo + 1e-9)
    # pixels that predict alike, pooled: the same likelihood, far fewer rows (series); with
    # a geometric variant in play its rows must be identical too, which rarely pays
    position = "vig" in names or start.get("vig", 0.0) != 0.0
    timed = (any(is_per_image(n) for n in names)
             or any(v for k, v in start.items() if is_per_image(k)))
    groups = [compact(g, position, geometric(names, start), timed) for g in groups]

    def objective(z, s0):
        return _objective(groups, names, lo, hi, nvalid, z, s0)

    def objective_and_gradient(z, s0):
        return _objective_and_gradient(groups, names, lo, hi, nvalid, z, s0)

    def run(z0, s0):
        return optimize.minimize(objective_and_gradient, z0, args=(s0,), jac=True,
                                 method="L-BFGS-B", bounds=[(0, 1)] * len(z0), options=_STOP)

    first = dict(start)
    if warm is not None:  # the better of the two points is the start
        warm = {**start, **{n: warm[n] for n in names if n in warm}}
        if objective(_unit(warm, names, lo, hi), warm) < objective(_unit(first, names, lo, hi),
                                                                   first):
            first = warm
    starts = [first]
    search = search and first is not warm  # a converged fit of these parameters nearby: one run
    if search and "na" in free and (first["na"] > 1e-6 or first["nb"] > 1e-8
                                    or first.get("nc", 0) > 1e-6):
        # a noise model inflated by a wrong mean flattens the likelihood; restart without it
        starts.append({**first, "na": 0.0, "nb": 0.0, "nc": 0.0})
    eq3 = first["gamma"] == 1.0 and not any(first.get(k) for k in WARP_KEYS)
    if search and "gamma" in free and (eq3 or shape_search):
        # the shape's likelihood has local minima: also start from the curve a quick
        # cross-exposure calibration on the same pixels gives (``shape_start``), or, where
        # the data have no such pixels, from the power-law corners (linear, display gamma)
        # (the corners start noise-free, so they stand in for the noise-free restart)
        plain = {**starts[-1], **dict.fromkeys(WARP_KEYS, 0.0)}
        corners = shape_starts(groups, plain) or [
            {**plain, "gamma": g, "rho": 0.05} for g in (1.0, 2.2)]
        starts = [first, *corners]
    blacks = [n for n in names if n.startswith("black")]
    if search and "gamma" in names and blacks and not any(first[n] for n in blacks):
        pedestal = _pedestal_start(groups, first, blacks, names, lo, hi, objective)
        if pedestal is not None:
            starts.append(pedestal)
    # every start runs to convergence: screening them by a few iterations picked the wrong
    # basin of a truncated gamma-2.2 stack (test_truncated_long_exposure_is_quantisation_
    # not_gain), where the start that converges best is not ahead after ten
    res, s0 = min(((run(_unit(s0, names, lo, hi), s0), s0) for s0 in starts),
                  key=lambda r: r[0].fun)
    best = dict(s0)
    best.update(zip(names, lo + (hi - lo) * res.x, strict=True))
    return best


def _objective(groups: list[Group], names: list[str], lo: np.ndarray, hi: np.ndarray,
               nvalid: int, z: np.ndarray, s0: dict) -> float:
    """The penalised NLL per value at unit coordinates ``z`` of ``names`` (in their
    ``[lo, hi]``), the other parameters at ``s0``; 1e3 where the time weights turn negative."""
    p = _point(names, lo, hi, z, s0)
    if not time_ok(p):
        return 1e3
    return penalised_nll(groups, p) / max(nvalid, 1)


def _point(names: list[str], lo: np.ndarray, hi: np.ndarray, z: np.ndarray, s0: dict) -> dict:
    """The parameters at unit coordinates ``z`` of ``names``, the others at ``s0``."""
    p = dict(s0)
    p.update(zip(names, lo + (hi - lo) * z, strict=True))
    return p


def _objective_and_gradient(groups: list[Group], names: list[str], lo: np.ndarray,
                            hi: np.ndarray, nvalid: int, z: np.ndarray, s0: dict
                            ) -> tuple[float, np.ndarray]:
    """``_objective`` and its gradient in ``z``: in closed form where a parameter acts on
    the values' exposures, responses or variances (``clblur.study.gradient``), by forward
    differences for the geometric variants."""
    p = _point(names, lo, hi, z, s0)
    grad = np.zeros_like(z)
    if not time_ok(p):
        return 1e3, grad
    closed = [i for i, n in enumerate(names) if is_analytic(n)]
    parts = [nll_gradient(g, p, [names[i] for i in closed]) for g in groups]
    # summed as penalised_nll sums, so a difference step compares like with like
    f = (sum(float(nll.sum()) for nll, _ in parts) + _ridge(p)) / max(nvalid, 1)
    if closed:
        by_value = sum(g for _, g in parts) + np.array(
            [2.0 * WARP_RIDGE * p[names[i]] if names[i] in WARP_KEYS else 0.0
             for i in closed])
        grad[closed] = by_value * (hi - lo)[closed] / max(nvalid, 1)
    for i, n in enumerate(names):
        if not is_analytic(n):
            # scipy's own forward step for L-BFGS-B, turned back at the upper bound
            step = _DIFFERENCE_STEP if z[i] + _DIFFERENCE_STEP <= 1.0 else -_DIFFERENCE_STEP
            moved = z.copy()
            moved[i] += step
            grad[i] = (_objective(groups, names, lo, hi, nvalid, moved, s0) - f) / (
                moved[i] - z[i])
    return f, grad


def _pedestal_start(groups: list[Group], first: dict, blacks: list[str], names: list[str],
                    lo: np.ndarray, hi: np.ndarray, objective) -> dict | None:
    """A start with a black level for a fit that frees it beside the response shape.

    A free shape absorbs much of a pedestal over the codes the data span: started at no
    black level, the joint fit stays in that basin, although the basin with the pedestal
    predicts better (a linear camera 7.65 codes above black read as a shape of exponent 2.7
    with no black level on two seeds of four).  So the black level is set at fractions of its
    bound (the darkest codes), the shape projected from the cross-exposure curve above it
    (``shape_starts``), and the start whose objective is lowest is returned (``None`` where
    the data have no single-code pixels to project from).  It is one more start: the fit
    keeps whichever converges best.
    """
    top = [hi[names.index(n)] for n in blacks]
    best = None
    for frac in _PEDESTAL_FRACTIONS:
        levels = {n: frac * t for n, t in zip(blacks, top, strict=True)}
        for s0 in shape_starts(groups, {**first, **levels, **dict.fromkeys(WARP_KEYS, 0.0)}):
            value = objective(_unit(s0, names, lo, hi), s0)
            if best is None or value < best[0]:
                best = (value, s0)
    return None if best is None else best[1]


def _unit(p: dict, names: list[str], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``p``'s free parameters scaled to [0, 1] between their bounds (the optimiser's box)."""
    return np.clip((np.array([p[n] for n in names]) - lo) / (hi - lo), 0.0, 1.0)


def average_params(params: list[dict]) -> dict:
    """The mean of the two folds' parameters (the reported estimate).  An image's own
    parameter (``lt:I``, ``lw:I:c``) that one fold's fit does not hold is at its nominal
    value there, as every prediction and fit reads it (``_fit_continuous``)."""
    keys = dict.fromkeys([*params[0], *params[1]])
    return {k: 0.5 * (_held(params[0], k) + _held(params[1], k)) for k in keys}


def _held(p: dict, key: str) -> float:
    if key in p:
        return p[key]
    if is_per_image(key):
        return param_range(key)[0]
    raise KeyError(f"a fold's fit lacks {key!r}")


def heldout_scores(groups: list[Group], params: list[dict]):
    """Cross-fitted RMSE (codes), NLL per valid value, and predictions per group.

    Fold ``f`` of every group is predicted with ``params[1 - f]``.
    """
    se = nll = 0.0
    count = 0
    preds = []
    for g in groups:
        pred = np.zeros_like(g.target)
        for f in (0, 1):
            rows = g.fold == f
            sub = fold_part(g, f)
            pr, var = predict(sub, params[1 - f])
            pred[rows] = pr
            r = np.where(sub.valid, sub.target - pr, 0.0)
            se += float((r * r).sum())
            nll += float(pixel_nll(sub, params[1 - f]).sum())
            count += int(sub.valid.sum())
        preds.append(pred)
    return math.sqrt(se / max(count, 1)), nll / max(count, 1), preds
