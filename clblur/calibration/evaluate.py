"""Held-out evaluation: predict one exposure from another through the fitted response.

Conventions
-----------
* For a target image ``j`` and a source ``i`` whose photometric exposure differs by ``gap``
  stops (within ``tolerance`` stops), the prediction is ``I(I^-1(f_i) x_j / x_i)``.
* Leave-one-exposure-out: with ``refit=True`` (default) the model is refitted without image
  ``j`` (same samples, same options) before predicting it, so the target never informed the
  curve.  Pixels inside any sampled patch are never scored (held-out pixels only).
* Scored values: pixel-channels valid (``low < v < high``) in both images.  RMSE in code
  values of the series' dtype, pooled over all pairs and channels; per channel too.
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from clblur.calibration.fitting import ResponseFit, fit, transfer
from clblur.calibration.sampling import Sampling
from clblur.calibration.series import ExposureSeries


def _refit_without(series: ExposureSeries, f: ResponseFit, j: int) -> ResponseFit:
    keep = [i for i in range(len(series.images)) if i != j]
    s = f.sampling
    sampling = Sampling([c.drop_exposure(j) for c in s.per_channel], s.footprint, s.patch,
                        s.low, s.high)
    return fit(series.subset(keep), f.model, sampling=sampling, **f.options)


def evaluate(series: ExposureSeries, fit_result: ResponseFit, gaps=(1, 4), *,
             refit: bool = True, tolerance: float = 0.25, max_pixels: int | None = None,
             seed: int = 0, progress: bool = False) -> dict:
    """Held-out RMSE (code values) for each gap in stops, plus the fit's AIC/BIC.

    ``max_pixels`` scores a random subset of the held-out pixels (faster; same for every
    pair).  Returns ``{"model", "shared", "rmse": {gap: rmse}, "rmse_per_channel": {gap:
    [...]}, "n_values": {gap: n}, "n_pairs": {gap: n}, "log_likelihood", "n_params", "aic",
    "bic", "rmse_fit"}``; a gap with no pair gets RMSE NaN.
    """
    gaps = tuple(float(g) for g in gaps)
    if not gaps or any(g <= 0 for g in gaps):
        raise ValueError(f"gaps must be positive numbers of stops, got {gaps}")
    stops = np.log2(series.relative_exposures())
    n, ch = len(series.images), series.channels
    held = ~fit_result.sampling.footprint
    coords = np.flatnonzero(held.ravel())
    if max_pixels is not None and coords.size > max_pixels:
        coords = np.sort(np.random.default_rng(seed).choice(coords, max_pixels, replace=False))
    flat = [im.reshape(-1, ch)[coords].astype(np.float64) / series.full_scale
            for im in series.images]
    low, high = fit_result.sampling.low, fit_result.sampling.high
    sse = {g: np.zeros(ch) for g in gaps}
    cnt = {g: np.zeros(ch, dtype=np.int64) for g in gaps}
    pairs = dict.fromkeys(gaps, 0)
    targets = [j for j in range(n)
               if any(abs(abs(stops[i] - stops[j]) - g) <= tolerance
                      for i in range(n) for g in gaps if i != j)]
    for j in tqdm(targets, desc=f"evaluate {fit_result.model}", disable=not progress,
                  leave=False):
        model = _refit_without(series, fit_result, j) if refit else fit_result
        vj = flat[j]
        ok_j = (vj > low) & (vj < high)
        for i in range(n):
            d = abs(stops[i] - stops[j])
            for g in gaps:
                if i == j or abs(d - g) > tolerance:
                    continue
                vi = flat[i]
                ok = ok_j & (vi > low) & (vi < high)
                pairs[g] += 1
                ratio = 2.0 ** (stops[j] - stops[i])
                for c in range(ch):
                    m = ok[:, c]
                    pred = transfer(model.responses[c], vi[m, c], ratio)
                    err = (pred - vj[m, c]) * series.full_scale
                    sse[g][c] += float(np.sum(err**2))
                    cnt[g][c] += int(m.sum())
    out = {"model": fit_result.model, "shared": fit_result.shared, "rmse": {},
           "rmse_per_channel": {}, "n_values": {}, "n_pairs": {}}
    for g in gaps:
        key = int(g) if g.is_integer() else g
        total = cnt[g].sum()
        out["rmse"][key] = float(np.sqrt(sse[g].sum() / total)) if total else float("nan")
        out["rmse_per_channel"][key] = [float(np.sqrt(s / k)) if k else float("nan")
                                        for s, k in zip(sse[g], cnt[g], strict=True)]
        out["n_values"][key] = int(total)
        out["n_pairs"][key] = pairs[g]
    out.update({"log_likelihood": fit_result.log_likelihood, "n_params": fit_result.n_params,
                "aic": fit_result.aic, "bic": fit_result.bic, "rmse_fit": fit_result.rmse_fit})
    return out
