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
* Scored values: pixel-channels valid (``low < v < high``) in both images and *flat*: their
  3 x 3 neighbourhood spans at most ``flat_tolerance`` of full scale in both images, so a
  sub-pixel misregistration between the exposures (scanned film frames, hand-held shots)
  cannot masquerade as response error.  ``flat_tolerance=None`` scores every pixel.
* ``low`` defaults to 0.1: below it a pixel sits at or near the black level, where one code
  value stands for a large exposure range (an under-exposed value, rejected like a clipped
  one).  RMSE in code values of the series' dtype, pooled over pairs and channels.
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from clblur.calibration.fitting import ResponseFit, fit, transfer
from clblur.calibration.sampling import VALID_HIGH, Sampling
from clblur.calibration.series import ExposureSeries

FLAT_TOLERANCE = 0.03
EVAL_LOW = 0.1
DIRECTIONS = ("darker", "brighter")


def _local_range(image: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Max minus min over each pixel's 3 x 3 neighbourhood (code values), at ``coords``."""
    import cv2

    kernel = np.ones((3, 3), np.uint8)
    img = image.astype(np.float32)
    spread = cv2.dilate(img, kernel) - cv2.erode(img, kernel)
    return spread.reshape(-1, image.shape[2])[coords]


def _refit_without(series: ExposureSeries, f: ResponseFit, j: int) -> ResponseFit:
    keep = [i for i in range(len(series.images)) if i != j]
    s = f.sampling
    sampling = Sampling([c.drop_exposure(j) for c in s.per_channel], s.footprint, s.patch,
                        s.low, s.high)
    return fit(series.subset(keep), f.model, sampling=sampling, **f.options)


def evaluate(series: ExposureSeries, fit_result: ResponseFit, gaps=(1, 4), *,
             refit: bool = True, tolerance: float = 0.25, max_pixels: int | None = None,
             low: float = EVAL_LOW, high: float = VALID_HIGH,
             flat_tolerance: float | None = FLAT_TOLERANCE, seed: int = 0,
             progress: bool = False) -> dict:
    """Held-out RMSE (code values) for each gap in stops, plus the fit's AIC/BIC.

    ``max_pixels`` scores a random subset of the held-out pixels (faster; the same subset for
    every pair).  Returns ``{"model", "shared", "rmse": {gap: rmse}, "rmse_per_channel":
    {gap: [...]}, "rmse_darker": {gap: rmse}, "rmse_brighter": {gap: rmse}, "n_values":
    {gap: n}, "n_pairs": {gap: n}, "log_likelihood", "n_params", "aic", "bic", "rmse_fit"}``;
    a gap with no pair gets RMSE NaN.
    """
    gaps = tuple(float(g) for g in gaps)
    if not gaps or any(g <= 0 for g in gaps):
        raise ValueError(f"gaps must be positive numbers of stops, got {gaps}")
    if not 0.0 <= low < high <= 1.0:
        raise ValueError(f"valid range needs 0 <= low < high <= 1, got {low}, {high}")
    stops = np.log2(series.relative_exposures())
    n, ch = len(series.images), series.channels
    coords = np.flatnonzero(~fit_result.sampling.footprint.ravel())
    if max_pixels is not None and coords.size > max_pixels:
        coords = np.sort(np.random.default_rng(seed).choice(coords, max_pixels, replace=False))
    values = [im.reshape(-1, ch)[coords].astype(np.float64) / series.full_scale
              for im in series.images]
    usable = []
    for im, v in zip(series.images, values, strict=True):
        ok = (v > low) & (v < high)
        if flat_tolerance is not None:
            ok &= _local_range(im, coords) <= flat_tolerance * series.full_scale
        usable.append(ok)
    sse = {(g, d): np.zeros(ch) for g in gaps for d in DIRECTIONS}
    cnt = {(g, d): np.zeros(ch, dtype=np.int64) for g in gaps for d in DIRECTIONS}
    pairs = dict.fromkeys(gaps, 0)
    sources = {j: [(i, g) for i in range(n) for g in gaps
                   if i != j and abs(abs(stops[i] - stops[j]) - g) <= tolerance]
               for j in range(n)}
    targets = [j for j in range(n) if sources[j]]
    for j in tqdm(targets, desc=f"evaluate {fit_result.model}", disable=not progress,
                  leave=False):
        model = _refit_without(series, fit_result, j) if refit else fit_result
        for i, g in sources[j]:
            ok = usable[i] & usable[j]
            pairs[g] += 1
            ratio = 2.0 ** (stops[j] - stops[i])
            key = (g, "darker" if ratio < 1 else "brighter")
            for c in range(ch):
                m = ok[:, c]
                pred = transfer(model.responses[c], values[i][m, c], ratio)
                err = (pred - values[j][m, c]) * series.full_scale
                sse[key][c] += float(np.sum(err**2))
                cnt[key][c] += int(m.sum())

    def rmse(s, k):
        return float(np.sqrt(s / k)) if k else float("nan")

    out = {"model": fit_result.model, "shared": fit_result.shared, "rmse": {},
           "rmse_per_channel": {}, "rmse_darker": {}, "rmse_brighter": {}, "n_values": {},
           "n_pairs": {}}
    for g in gaps:
        key = int(g) if g.is_integer() else g
        s_all = sse[g, "darker"] + sse[g, "brighter"]
        c_all = cnt[g, "darker"] + cnt[g, "brighter"]
        out["rmse"][key] = rmse(s_all.sum(), c_all.sum())
        out["rmse_per_channel"][key] = [rmse(a, b) for a, b in zip(s_all, c_all, strict=True)]
        for d in DIRECTIONS:
            out[f"rmse_{d}"][key] = rmse(sse[g, d].sum(), cnt[g, d].sum())
        out["n_values"][key] = int(c_all.sum())
        out["n_pairs"][key] = pairs[g]
    out.update({"log_likelihood": fit_result.log_likelihood, "n_params": fit_result.n_params,
                "aic": fit_result.aic, "bic": fit_result.bic, "rmse_fit": fit_result.rmse_fit})
    return out
