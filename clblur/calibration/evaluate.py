"""Held-out evaluation: predict one exposure from another through the fitted response.

Conventions
-----------
* For a target image ``j`` and a source ``i`` whose photometric exposure differs by ``gap``
  stops (within ``tolerance`` stops), the prediction is ``I(I^-1(f_i) x_j / x_i)``.  Both
  directions are scored: predicting the *darker* image compresses the source's noise, while
  predicting the *brighter* one amplifies it by the ratio of the curve's slopes (large in the
  toe of a film curve), so the two are also reported separately.
* Leave-one-exposure-out: with ``refit=True`` (default) the model is refitted without image
  ``j`` (same samples, same options) before predicting it, so the target never informed the
  curve.  Pixels inside any sampled patch are never scored (held-out pixels only).
* Scored values (headline): *every* pixel-channel whose source is valid, i.e. codes 3..252 of
  255 (``low < v < high`` with the defaults, ``high`` scaled by the series' ``white_level``
  where its camera clips below full scale; neither clipped at the top nor at code 0..2 in
  the dark), random pixels, edges and textures included, at a source value where the
  target is seldom clipped: at most ``censored`` (1 %) of its targets lie outside the valid
  range, by a monotone fit of that share against the source value, per pair and channel
  (``clblur.calibration.censoring``).  A target's own value is not what decides whether it
  is scored: where it sometimes clips, keeping only the targets that did not selects on
  their noise, and a fitted curve that bends to that selection then outscored the true
  curve (the JPEG copies of Memorial, ``docs/studies/validation.md``).  The few clipped
  targets left inside the range are not scored.  A secondary column keeps only *flat*
  pixels: their 3 x 3 neighbourhood spans at most ``flat_tolerance`` of full scale in both
  images (8 DN in uint8), where a sub-pixel misregistration between the exposures cannot
  masquerade as response error.  RMSE in code values of the series' dtype, pooled over
  pairs and channels.
* A gap with no pair of exposures that far apart gets RMSE NaN and a reason in ``missing``.
"""

from __future__ import annotations

import hashlib

import numpy as np
from tqdm import tqdm

from clblur.calibration.censoring import CENSORED, uncensored
from clblur.calibration.fitting import ResponseFit, fit, transfer
from clblur.calibration.models import FAMILIES
from clblur.calibration.series import ExposureSeries
from clblur.errors import InputError

__all__ = ["CENSORED", "DEFAULT_GAPS", "DIRECTIONS", "EVAL_HIGH", "EVAL_LOW", "FLAT_TOLERANCE",
           "GAP_TOLERANCE", "HeldOut", "darker_pairs", "evaluate", "held_out", "local_range",
           "series_gaps"]

DEFAULT_GAPS = (1.0, 4.0)
GAP_TOLERANCE = 0.25  # stops: a pair of exposures counts for a gap this close to it

FLAT_TOLERANCE = 0.03
# Codes 3..252 of 255 are valid: code 0..2 may be a clipped black, 253..255 a clipped white.
EVAL_LOW = 2.5 / 255.0
EVAL_HIGH = 252.5 / 255.0
DIRECTIONS = ("darker", "brighter")


def local_range(image: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Max minus min over each pixel's 3 x 3 neighbourhood (code values), at ``coords``."""
    import cv2

    kernel = np.ones((3, 3), np.uint8)
    img = image.astype(np.float32)
    spread = cv2.dilate(img, kernel) - cv2.erode(img, kernel)
    return spread.reshape(-1, image.shape[2])[coords]


class HeldOut:
    """The held-out pixels of a series and the values scored in each pair and channel.

    They depend on the data and the sampling's footprint alone, not on the curve, so every
    model fitted on one sampling shares them (``evaluate``'s ``cache``) rather than making
    them again, a few passes over 10 M values a pair on a 10 MP bracket.  The held-out pixels
    are kept as codes (a byte each for 8-bit series) and made values per pair and channel:
    as float64 values of every pixel of every image they took 8 times the series.  A pair's
    scored values are kept as bits, 1.3 MB a channel of a 10 MP pair.
    """

    def __init__(self, series: ExposureSeries, footprint: np.ndarray, max_pixels: int | None,
                 seed: int, low: float, high: float, flat_tolerance: float | None,
                 censored: float):
        self.series = series  # held, so that the id in a cache's key names only this series
        self.full_scale, self.low, self.high, self.censored = (series.full_scale, low, high,
                                                               censored)
        ch = series.channels
        # held out: what no fit has seen, and what showed one static scene (series.moving)
        coords = np.flatnonzero(~(footprint | series.moving).ravel())
        if max_pixels is not None and coords.size > max_pixels:
            coords = np.sort(np.random.default_rng(seed).choice(coords, max_pixels,
                                                                replace=False))
        self.coords, self.size = coords, coords.size  # flat indices into the image
        self.codes = [im.reshape(-1, ch)[coords] for im in series.images]
        self.valid, self.intact = [], []
        for i, k in enumerate(self.codes):  # one image's float values at a time
            v = k.astype(np.float64) / series.full_scale
            self.valid.append((v > low) & (v < high))
            spoiled = series.coded_near_clip(i)  # a JPEG's clipped region as the codec left it
            self.intact.append(np.ones(coords.size, dtype=bool) if spoiled is None
                               else ~spoiled.reshape(-1)[coords])
        self.flat = None if flat_tolerance is None else [
            local_range(im, coords) <= flat_tolerance * series.full_scale
            for im in series.images]
        self._scored: dict[tuple[int, int, int], np.ndarray] = {}

    def values(self, i: int, m: np.ndarray, c: int) -> np.ndarray:
        """Image ``i``'s channel ``c`` at the held-out pixels ``m`` (a mask), normalised."""
        return self.codes[i][m, c].astype(np.float64) / self.full_scale

    def scored(self, i: int, j: int, c: int) -> np.ndarray:
        """A mask over the held-out pixels: the values of channel ``c`` scored when image
        ``j`` is predicted from image ``i`` (the source valid, both images intact, the
        target seldom clipped at that source value: ``censoring.uncensored``)."""
        packed = self._scored.get((i, j, c))
        if packed is not None:
            return np.unpackbits(packed, count=self.size).view(bool)
        m = self.valid[i][:, c] & self.intact[i] & self.intact[j]
        m[m] = uncensored(self.codes[i][m, c], self.values(j, m, c), self.low, self.high,
                          self.censored)
        self._scored[i, j, c] = np.packbits(m)
        return m


def _refit_without(series: ExposureSeries, f: ResponseFit, j: int) -> ResponseFit:
    keep = [i for i in range(len(series.images)) if i != j]
    # What a family chose from the data (the spline's smoothness, by cross-validation on the
    # sampled pixels, never the scored ones) is kept: choosing it again for every left-out
    # exposure cost Memorial's 16-image evaluation 5 times its time.  The curve itself is
    # refitted without the target, as before.
    names = getattr(FAMILIES[f.model], "chosen_from_data", ())
    kept = [{k: p[k] for k in names if k in p} for p in f.params["per_channel"]]
    return fit(series.subset(keep), f.model, sampling=f.sampling.drop_exposure(j),
               group_options=kept if names else None,
               **f.options)


def series_gaps(series: ExposureSeries, wanted=DEFAULT_GAPS,
                tolerance: float = GAP_TOLERANCE) -> tuple[float, ...]:
    """The gaps to score a series at: each wanted gap, or the nearest one the series has.

    A bracket two stops apart has no 1-stop pair, and a default of 1 and 4 stops would leave
    half of its table empty (and rank models on one gap).  Each wanted gap the series has
    (within ``tolerance``) is kept; one it lacks becomes the nearest gap between two of its
    exposures (the smaller on a tie), rounded to 0.01 stop; duplicates are dropped, the
    order kept.

    Args:
        series: the exposure series.
        wanted: the gaps asked for, in stops.
        tolerance: how far (stops) a pair's gap may be from a wanted gap to count for it.

    Returns:
        The gaps to score, in stops.
    """
    stops = np.log2(series.relative_exposures())
    present = np.unique(np.round(np.abs(stops[:, None] - stops[None, :])[
        np.triu_indices(stops.size, 1)], 2))
    present = present[present > 0]
    out: list[float] = []
    for g in (float(x) for x in wanted):
        if present.size and not np.any(np.abs(present - g) <= tolerance):
            g = float(present[np.argmin(np.abs(present - g))])
        if g not in out:
            out.append(g)
    return tuple(out)


def held_out(series: ExposureSeries, fit_result: ResponseFit, *, max_pixels: int | None,
             seed: int, low: float = EVAL_LOW, high: float | None = None,
             flat_tolerance: float | None = FLAT_TOLERANCE, censored: float = CENSORED,
             cache: dict | None = None) -> HeldOut:
    """The held-out values of ``series`` for fits on ``fit_result``'s sampling, made once
    per ``cache`` (a dict shared by the models fitted on one sampling; None: made here);
    ``high`` None: ``EVAL_HIGH`` times the series' ``white_level``, as ``evaluate``."""
    if high is None:  # a camera that clips below full scale: its clipped codes are not light
        high = EVAL_HIGH * series.white_level
    footprint = fit_result.sampling.footprint
    cache_key = (id(series), hashlib.blake2b(np.packbits(footprint).tobytes()).hexdigest(),
                 footprint.shape, max_pixels, seed, low, high, flat_tolerance, censored)
    held = None if cache is None else cache.get(cache_key)
    if held is None:
        held = HeldOut(series, footprint, max_pixels, seed, low, high, flat_tolerance,
                       censored)
        if cache is not None:
            cache[cache_key] = held
    return held


def darker_pairs(series: ExposureSeries, gaps, tolerance: float = GAP_TOLERANCE
                 ) -> list[tuple[int, int]]:
    """(source, target) of every pair ``gaps`` stops apart (within ``tolerance``) whose
    target is the darker image, as ``evaluate`` scores them."""
    stops = np.log2(series.relative_exposures())
    n = stops.size
    return [(i, j) for j in range(n) for i in range(n)
            if stops[i] > stops[j] and any(abs(stops[i] - stops[j] - float(g)) <= tolerance
                                           for g in gaps)]


def evaluate(series: ExposureSeries, fit_result: ResponseFit, gaps=DEFAULT_GAPS, *,
             refit: bool = True, tolerance: float = GAP_TOLERANCE, max_pixels: int | None = None,
             low: float = EVAL_LOW, high: float | None = None,
             flat_tolerance: float | None = FLAT_TOLERANCE, censored: float = CENSORED,
             seed: int = 0, progress: bool = False, cache: dict | None = None) -> dict:
    """Held-out RMSE (code values) for each gap in stops, plus the fit's AIC/BIC.

    ``max_pixels`` scores a random subset of the held-out pixels (faster; the same subset for
    every pair). ``cache``: a dict shared by the evaluations of models fitted on one series and
    sampling (``calibrate`` passes one), so that the held-out pixels and each pair's scored
    values are made once; None makes them for this call. Returns ``{"model", "shared", "rmse":
    {gap: rmse}, "rmse_per_channel": {gap: [...]}, "rmse_darker": {gap: rmse}, "rmse_brighter":
    {gap: rmse}, "n_values": {gap: n}, "n_pairs": {gap: n}, "refit" (False when ``refit`` is
    False or the series has only 2 images), "valid" ([low, high] of full scale a scored value
    lies in), "censored" (the share of clipped targets a scored source value may have),
    "flat_tolerance", "flat": {"rmse", "rmse_darker", "rmse_brighter", "n_values"} (flat pixels
    only; absent when ``flat_tolerance`` is None), "missing": {gap: reason}, "log_likelihood",
    "n_params", "aic", "bic", "rmse_fit"}``; a gap with no pair gets RMSE NaN and its reason in
    ``missing``.
    """
    if high is None:
        high = EVAL_HIGH * series.white_level  # as held_out, checked before any work
    gaps = tuple(float(g) for g in gaps)
    if not gaps or any(g <= 0 for g in gaps):
        raise InputError(f"gaps must be positive numbers of stops, got {gaps}")
    if not 0.0 <= low < high <= 1.0:
        raise InputError(f"valid range needs 0 <= low < high <= 1, got {low}, {high}")
    if not 0.0 <= censored < 1.0:
        raise InputError(f"censored (the share of clipped targets a scored source value may "
                         f"have) must be in [0, 1), got {censored}")
    stops = np.log2(series.relative_exposures())
    n, ch = len(series.images), series.channels
    # Leaving an exposure out of a 2-image series leaves nothing to fit: score the full fit
    # (slightly optimistic) and say so in the result rather than fail.
    refit = refit and n > 2
    held = held_out(series, fit_result, max_pixels=max_pixels, seed=seed, low=low, high=high,
                    flat_tolerance=flat_tolerance, censored=censored, cache=cache)
    flat = held.flat
    kinds = ("all",) if flat is None else ("all", "flat")
    sse = {(g, d, k): np.zeros(ch) for g in gaps for d in DIRECTIONS for k in kinds}
    cnt = {(g, d, k): np.zeros(ch, dtype=np.int64) for g in gaps for d in DIRECTIONS
           for k in kinds}
    pairs = dict.fromkeys(gaps, 0)
    sources = {j: [(i, g) for i in range(n) for g in gaps
                   if i != j and abs(abs(stops[i] - stops[j]) - g) <= tolerance]
               for j in range(n)}
    targets = [j for j in range(n) if sources[j]]
    for j in tqdm(targets, desc=f"evaluate {fit_result.model}", disable=not progress,
                  leave=False):
        model = _refit_without(series, fit_result, j) if refit else fit_result
        for i, g in sources[j]:
            pairs[g] += 1
            ratio = 2.0 ** (stops[j] - stops[i])
            direction = "darker" if ratio < 1 else "brighter"
            both_flat = None if flat is None else flat[i] & flat[j]
            for c in range(ch):
                m = held.scored(i, j, c)
                pred = transfer(model.responses[c], held.values(i, m, c), ratio)
                err2 = ((pred - held.values(j, m, c)) * series.full_scale) ** 2
                sse[g, direction, "all"][c] += float(np.sum(err2))
                cnt[g, direction, "all"][c] += err2.size
                if both_flat is not None:
                    fm = both_flat[:, c][m]
                    sse[g, direction, "flat"][c] += float(np.sum(err2[fm]))
                    cnt[g, direction, "flat"][c] += int(fm.sum())

    def rmse(s, k):
        return float(np.sqrt(s / k)) if k else float("nan")

    out = {"model": fit_result.model, "shared": fit_result.shared, "refit": refit,
           "valid": [low, high], "censored": censored, "flat_tolerance": flat_tolerance,
           "rmse": {}, "rmse_per_channel": {}, "rmse_darker": {}, "rmse_brighter": {},
           "n_values": {}, "n_pairs": {}, "missing": {}}
    if flat is not None:
        out["flat"] = {"rmse": {}, "rmse_darker": {}, "rmse_brighter": {}, "n_values": {}}
    present = sorted({round(abs(a - b), 2) for a in stops for b in stops if a > b})
    for g in gaps:
        key = int(g) if g.is_integer() else g
        for kind in kinds:
            dest = out if kind == "all" else out["flat"]
            s_all = sse[g, "darker", kind] + sse[g, "brighter", kind]
            c_all = cnt[g, "darker", kind] + cnt[g, "brighter", kind]
            dest["rmse"][key] = rmse(s_all.sum(), c_all.sum())
            if kind == "all":
                out["rmse_per_channel"][key] = [rmse(a, b) for a, b
                                                in zip(s_all, c_all, strict=True)]
            for d in DIRECTIONS:
                dest[f"rmse_{d}"][key] = rmse(sse[g, d, kind].sum(), cnt[g, d, kind].sum())
            dest["n_values"][key] = int(c_all.sum())
        out["n_pairs"][key] = pairs[g]
        if not pairs[g]:
            shown = ", ".join(f"{p:g}" for p in present[:12]) + (" ..." if len(present) > 12
                                                                 else "")
            out["missing"][key] = (f"no two exposures are {g:g} stops apart (within "
                                   f"{tolerance:g} stop); the gaps in this series are {shown}")
        elif not out["n_values"][key]:
            out["missing"][key] = (f"no held-out pixel of any pair {g:g} stops apart is valid "
                                   f"(codes 3..252) at a source value where the target is "
                                   f"seldom clipped")
    out.update({"log_likelihood": fit_result.log_likelihood, "n_params": fit_result.n_params,
                "aic": fit_result.aic, "bic": fit_result.bic, "rmse_fit": fit_result.rmse_fit})
    return out
