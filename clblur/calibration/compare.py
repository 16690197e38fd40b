"""``calibrate``: fit several response families to one series and rank them (the API behind
``clblur calibrate``)."""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from clblur.blas import with_one_blas_thread
from clblur.calibration.evaluate import (
    EVAL_LOW,
    FLAT_TOLERANCE,
    darker_pairs,
    evaluate,
    held_out,
    series_gaps,
)
from clblur.calibration.fitting import ResponseFit, fit
from clblur.calibration.models import MODELS, EmorBasis
from clblur.calibration.sampling import VALID_LOW, sample_series
from clblur.calibration.series import ExposureSeries, check_brightening, load_series
from clblur.calibration.surround import surround_dependence
from clblur.errors import InputError

__all__ = ["Calibration", "available_models", "calibrate", "nan_reasons", "selection_score"]


@dataclass
class Calibration:
    """Every fitted model, its held-out evaluation, and the best one's name."""

    series: ExposureSeries
    fits: dict[str, ResponseFit]
    evaluations: dict[str, dict]
    best: str
    skipped: dict[str, str] = field(default_factory=dict)  # model -> why it could not be fit

    @property
    def responses(self):
        """The best model's responses, one per channel."""
        return self.fits[self.best].responses

    @property
    def surround(self) -> dict | None:
        """Whether the best model's held-out error depends on the surround (local tone
        mapping; ``clblur.calibration.surround``), None where no pair was scored."""
        return self.evaluations[self.best].get("surround")

    def table(self) -> list[dict]:
        """One row per model: held-out RMSE per gap and direction, AIC, BIC."""
        return [{"model": n, **{k: e[k] for k in ("rmse", "rmse_darker", "rmse_brighter",
                                                   "rmse_per_channel", "aic", "bic",
                                                   "n_params", "rmse_fit")}}
                for n, e in self.evaluations.items()]


def available_models(emor_dir=None, warn: bool = True) -> list[str]:
    """All models, without ``emor`` when its basis files cannot be found."""
    try:
        EmorBasis.load(emor_dir)
        return list(MODELS)
    except ValueError as e:
        if warn:
            print(f"clblur calibrate: skipping emor ({e})", file=sys.stderr)
        return [m for m in MODELS if m != "emor"]


@with_one_blas_thread
def calibrate(source: ExposureSeries | str | os.PathLike, models=None, *, times=None,
              shared: bool = False, refine_times: bool = False, n_samples: int = 1000,
              patch: int = 3, seed: int = 0, fit_low: float | None = None,
              emor_dir=None, gaps=None, refit: bool = True, eval_low: float = EVAL_LOW,
              flat_tolerance: float | None = FLAT_TOLERANCE, max_pixels: int | None = None,
              progress: bool = False, align: bool = True) -> Calibration:
    """Fit ``models`` (default: all available) on the same patches, evaluate each by held-out
    prediction (``clblur.calibration.evaluate``) and pick the lowest mean RMSE over ``gaps``
    of the darker target (:func:`selection_score`).  ``gaps`` (stops): None scores 1 and 4
    stops, or the nearest gaps the series has (``series_gaps``: a bracket two stops apart is
    scored at 2 and 4).  A model the series cannot support is
    skipped, its reason in ``Calibration.skipped``, unless it is the only one asked for.
    ``align``: register a series read from ``source`` (``load_series``); a given
    ``ExposureSeries`` is taken as it is (``ExposureSeries.aligned`` registers one).  The best
    model's held-out error is then tested for a dependence on the surround, which no curve
    holds (local tone mapping; ``clblur.calibration.surround``): ``Calibration.surround``.
    BLAS runs on one thread meanwhile (``clblur.blas``)."""
    # checked before the series is read and registered
    if gaps is not None and (not len(gaps) or not all(np.isfinite(g) and g > 0 for g in gaps)):
        raise InputError(f"gaps must be positive numbers of stops, got {list(gaps)}")
    if max_pixels is not None and (isinstance(max_pixels, bool) or not
                                   isinstance(max_pixels, (int, np.integer)) or max_pixels < 1):
        raise InputError(f"max_pixels (pixels scored) must be a positive integer, got "
                         f"{max_pixels!r}")
    series = source if isinstance(source, ExposureSeries) else load_series(source, times,
                                                                            align=align)
    check_brightening(series.images, series.relative_exposures(), series.names,
                      series.white_level)
    names = list(dict.fromkeys(models)) if models else available_models(emor_dir)
    unknown = [m for m in names if m not in MODELS]
    if unknown:
        raise InputError(f"unknown response model(s) {unknown}; choose from {', '.join(MODELS)}")
    if gaps is None:
        gaps = series_gaps(series)
    low = VALID_LOW if fit_low is None else min(fit_low, VALID_LOW)
    sampling = sample_series(series, n_samples, patch=patch, low=low, seed=seed)
    fits, evaluations, skipped = {}, {}, {}
    held_cache: dict = {}  # the held-out pixels and scored values, made once for every model
    for name in tqdm(names, desc="models", disable=not progress):
        opts = {"emor_dir": emor_dir} if name == "emor" else {}
        try:
            fits[name] = fit(series, name, shared=shared, sampling=sampling, low=fit_low,
                             refine_times=refine_times, progress=progress, **opts)
            evaluations[name] = evaluate(series, fits[name], gaps=gaps, refit=refit,
                                         max_pixels=max_pixels, low=eval_low,
                                         flat_tolerance=flat_tolerance, seed=seed,
                                         progress=progress, cache=held_cache)
        except ValueError as e:
            # A family the series cannot support (a spline's knots on a scene of a few grey
            # levels) is left out of the ranking with its reason; the others still compete.
            if len(names) == 1:
                raise
            fits.pop(name, None)
            skipped[name] = str(e)
    if not evaluations:
        raise InputError(f"no model could be fitted; {names[0]}: {skipped[names[0]]}")
    fitted = [n for n in names if n in evaluations]
    if all(np.isnan(list(evaluations[n]["rmse_darker"].values())).all() for n in fitted):
        # nothing was scored: a "best" model would be an arbitrary one
        raise InputError("no model could be scored on held-out pixels: "
                         + "; ".join(nan_reasons(evaluations[fitted[0]])))
    best = min(fitted, key=lambda n: selection_score(evaluations[n]))
    # what no curve can hold: an error that depends on the surround (local tone mapping)
    pairs = darker_pairs(series, gaps)
    if pairs:
        held = held_out(series, fits[best], max_pixels=max_pixels, seed=seed, low=eval_low,
                        flat_tolerance=flat_tolerance, cache=held_cache)
        evaluations[best]["surround"] = surround_dependence(series, fits[best], held, pairs)
    return Calibration(series, fits, evaluations, best, skipped)


def nan_reasons(evaluation: dict) -> list[str]:
    """One line per gap whose RMSE is nan, saying why (no pair that far apart, or no pixel
    that passed the scoring filters)."""
    lines = []
    for g, n_pairs in evaluation["n_pairs"].items():
        if not n_pairs:
            lines.append(f"nan at {g}-stop: no two exposures of this series are {g} stop(s) "
                         "apart (within 1/4 stop), so that gap cannot be scored; choose "
                         "--gaps the series has")
        elif not evaluation["n_values"].get(g):
            lines.append(f"nan at {g}-stop: {n_pairs} pair(s) are {g} stop(s) apart but no "
                         "pixel passed --eval-low / --flat-tolerance")
    return lines


def selection_score(evaluation: dict) -> float:
    """What the best model is chosen by: the held-out RMSE of predicting each darker image
    from the brighter one, the mean over the gaps.

    Why the darker target: there the source's noise reaches the prediction divided by the
    exposure ratio; predicting the brighter image multiplies it by the ratio (16 at 4
    stops), and a curve that bends to shrink that noise (an errors-in-variables bias) then
    scores better than the true one. Pooling both directions chose a free spline over an
    exact Eq. 3 on the paper's own camera (1.3 - 1.8 codes off the true curve) and over an
    exact gamma-offset curve on a linear 16-bit camera (up to 18.5 codes off), both won on
    the 4-stop brighter target alone (a new user's brackets, 2026-11-27); on the darker
    target the exact families win at both gaps. ``docs/studies/memorial-calibration.md``,
    Why the direction matters."""
    return float(np.nanmean(list(evaluation["rmse_darker"].values())))
