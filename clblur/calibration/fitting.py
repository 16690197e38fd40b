"""``fit``: one response family fitted to an exposure series, per channel or shared.

Conventions
-----------
* The paper's normalised time axis (used for ``exp``'s ``k``): exposure time divided by the
  longest exposure of the series (photometric exposure ``t / N**2`` when F-numbers are known),
  and scene radiance divided by the *median* radiance of the image's pixels.  ``k`` is then the
  paper's constant for the median pixel: with a stack of a single uniform gray pattern (the
  paper's Figure 1 set-up) it is exactly the paper's ``k``.  ``k_by_f_number`` gives ``k`` on
  the time-only axis ``t / t_max`` for each aperture (Eq. 3 predicts ``k`` proportional to
  ``1 / N**2``).
* Log-likelihood, AIC and BIC come from the *forward* residuals in code values of every fitted
  sample, with each sample's radiance re-estimated for the fitted curve and a Gaussian noise
  whose variance is the maximum-likelihood one.  Parameters counted: curve parameters, one
  radiance per sample, and the re-estimated exposures when ``refine_times`` is set; the same
  sample values (``LIKELIHOOD_LOW < v < high``, whatever range a family was fitted on) are
  scored for every model, so the numbers compare models directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from clblur.calibration.inverse_families import with_toe
from clblur.calibration.models import FAMILIES, MODELS, FamilyFit
from clblur.calibration.sampling import VALID_HIGH, VALID_LOW, SampleSet, Sampling, sample_series
from clblur.calibration.series import ExposureSeries
from clblur.errors import InputError, InputTypeError
from clblur.responses import Exp, Response

__all__ = ["LIKELIHOOD_LOW", "ResponseFit", "fit", "fit_radiances", "forward_residuals",
           "radiance_map", "transfer"]

# Low end of the sample values on which every model's likelihood (and fit RMSE) is computed.
LIKELIHOOD_LOW = 0.1


@dataclass
class ResponseFit:
    """A fitted response family; ``responses`` has one ``Response`` per channel."""

    model: str
    responses: list[Response]
    params: dict
    log_likelihood: float
    n_params: int
    n_observations: int
    rmse_fit: float  # forward RMSE on the fitted samples, code values
    shared: bool
    sampling: Sampling = field(repr=False)
    options: dict = field(repr=False, default_factory=dict)

    @property
    def aic(self) -> float:
        return 2.0 * self.n_params - 2.0 * self.log_likelihood

    @property
    def bic(self) -> float:
        return self.n_params * float(np.log(self.n_observations)) - 2.0 * self.log_likelihood

    def predict(self, image_i: np.ndarray, t_i: float, t_j: float) -> np.ndarray:
        """The image at exposure ``t_j`` predicted from ``image_i`` taken at ``t_i``.

        ``I(I^-1(f_i) * t_j / t_i)`` per channel; float64 in the input's code values (pass
        photometric exposures ``t / N**2`` when the apertures differ).
        """
        from clblur.pixels import imax

        img = np.asarray(image_i)
        full = imax(img.dtype)
        chans = img[..., None] if img.ndim == 2 else img
        if chans.shape[-1] != len(self.responses):
            raise InputError(f"image has {chans.shape[-1]} channel(s), the fit has "
                             f"{len(self.responses)}")
        if not (np.isfinite(t_i) and np.isfinite(t_j) and t_i > 0 and t_j > 0):
            raise InputError(f"exposures must be positive and finite, got {t_i}, {t_j}")
        out = np.empty(chans.shape, dtype=np.float64)
        for c, resp in enumerate(self.responses):
            out[..., c] = transfer(resp, chans[..., c] / full, t_j / t_i) * full
        return out[..., 0] if img.ndim == 2 else out

    def summary(self) -> dict:
        """JSON-ready description (no arrays of samples)."""
        return {"model": self.model, "shared": self.shared, "params": self.params,
                "log_likelihood": self.log_likelihood, "n_params": self.n_params,
                "n_observations": self.n_observations, "aic": self.aic, "bic": self.bic,
                "rmse_fit": self.rmse_fit}


def transfer(resp: Response, values: np.ndarray, ratio: float) -> np.ndarray:
    """Normalised values at one exposure -> normalised values at ``ratio`` times it."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return resp.forward(resp.inverse(np.clip(values, 0.0, 1.0)) * ratio)


def fit(series: ExposureSeries, model: str, *, shared: bool = False, n_samples: int = 1000,
        patch: int = 3, low: float | None = None, high: float | None = None, seed: int = 0,
        refine_times: bool = False, sampling: Sampling | None = None, progress: bool = False,
        group_options: list[dict] | None = None, **opts) -> ResponseFit:
    """Fit response family ``model`` (one of ``MODELS``) to ``series``.

    ``shared``: one curve for all channels (each sample keeps its own radiance) instead of one
    per channel.  ``n_samples``, ``patch``, ``seed``: sample selection (see
    ``clblur.calibration.sampling``); pass ``sampling`` to reuse a selection (the same patches
    for every model, so their held-out pixels match).  ``low``/``high``: the valid range of
    fitted values; ``low`` defaults to the family's ``default_low``, ``high`` to
    ``VALID_HIGH`` times the series' ``white_level`` (a camera that clips below full scale).
    ``refine_times``: re-estimate the exposures (uncertain shutter times).  Further keyword
    options go to the family (``order`` for polynomial, ``smoothness``/``levels``/
    ``time_sigma`` for nonparametric, ``components``/``emor_dir`` for emor, ``smoothness``
    for spline, chosen by cross-validation when not given).  ``group_options``: one dict of
    further options per fitted curve (per channel, or one when shared), for a refit that
    keeps what the first fit chose from the data (``clblur.calibration.evaluate``).

    ``params`` of the result: ``shared``; ``per_channel`` (one dict of family parameters per
    fitted curve, e.g. ``black_level``, ``gamma``, ``coefficients``); for ``exp`` also ``k``
    and ``k_by_f_number`` (lists, one per curve, on the axis described in the module doc);
    with ``refine_times`` also ``relative_exposures`` (per curve, longest = 1).
    """
    if not isinstance(series, ExposureSeries):
        raise InputTypeError(f"series must be an ExposureSeries (see load_series), got "
                        f"{type(series).__name__}")
    if model not in FAMILIES:
        raise InputError(f"unknown response model {model!r}; choose from {', '.join(MODELS)}")
    family = FAMILIES[model]
    if low is None:
        low = family.default_low
    if high is None:
        high = VALID_HIGH * series.white_level
    if sampling is None:
        sampling = sample_series(series, n_samples, patch=patch, low=min(low, VALID_LOW),
                                 high=high, seed=seed)
    chosen = sampling
    tau = series.relative_exposures()
    pile = {}  # where a camera clips below full scale, the family's censoring level
    if getattr(family, "uses_pixels", False):  # random single pixels, their own valid range
        if not sampling.pixels:
            raise InputError(f"the {model} model needs random pixel samples (sample_series "
                             "with n_pixels > 0)")
        pixels = sampling.pixels
        if series.white_level < 1.0:
            # a camera that clips below full scale (video range, a JPEG engine stopping at
            # 230) piles its highlights up at one code, and the pile is not light: taken for
            # light it bent the spline of a video-range bracket to 23.4 DN held-out, 1 stop
            # darker (2.2 without it; docs/studies/rendered_brackets.py, cam_d).  Only the
            # pile: the codes just below it hold the shoulder (the Canon bracket clipped at
            # 230: 4-stop darker 2.12 DN; cutting 2.5 codes below the pile, as
            # PAIR_HIGH_CODE does at full scale, 3.38)
            top = series.white_level - 0.5 / series.full_scale
            pixels = [p.with_range(family.default_low, top) for p in pixels]
            # a target on the pile is clipped, as one at full scale is: censored, so the
            # pools just below it are not left with their darker targets only
            pile = {"clip_high": top}
        groups = [SampleSet.concat(pixels)] if shared else pixels
    else:
        if (low, high) != (sampling.low, sampling.high):
            sampling = sampling.with_range(low, high)
        groups = [SampleSet.concat(sampling.per_channel)] if shared else sampling.per_channel
    fits: list[FamilyFit] = []
    if group_options is not None and len(group_options) != len(groups):
        raise InputError(f"group_options has {len(group_options)} entries for {len(groups)} "
                         "fitted curve(s)")
    for g, samples in enumerate(tqdm(groups, desc=f"fit {model}", disable=not progress,
                                     leave=False)):
        own = {} if group_options is None else group_options[g]
        fits.append(family.fit(samples, tau, full_scale=series.full_scale,
                               refine_times=refine_times, **{**pile, **own, **opts}))
    if getattr(family, "fits_toe", False) and low > chosen.low:  # below ``low``: the toe
        # the patches and the random pixels over the whole valid range: flat patches are
        # few near the black level (video range: 28 below 10 % of 2000), pixels are not
        whole = chosen.per_channel if chosen.pixels is None else [
            SampleSet.concat([c, p.with_range(chosen.low, chosen.high)])
            for c, p in zip(chosen.per_channel, chosen.pixels, strict=True)]
        whole = [SampleSet.concat(whole)] if shared else whole
        fits = [with_toe(f, samples, low) for f, samples in zip(fits, whole, strict=True)]
    if model == "exp":
        fits = [_on_paper_axis(series, f, list(range(series.channels)) if shared else [c])
                for c, f in enumerate(fits)]
    # the likelihood is judged on one common set of sample values for every model
    common = chosen.with_range(max(LIKELIHOOD_LOW, chosen.low), high)
    scored = [SampleSet.concat(common.per_channel)] if shared else common.per_channel
    n_obs, rss, n_par = 0, 0.0, 0
    for samples, f in zip(scored, fits, strict=True):
        res = forward_residuals(f.response, samples, f.tau) * series.full_scale
        rss += float(np.sum(res**2))
        n_obs += res.size
        n_par += f.n_shape_params + len(samples)  # curve (+ exposures) + radiances
    sigma2 = max(rss / n_obs, 1e-12)
    loglik = -0.5 * n_obs * (np.log(2 * np.pi * sigma2) + 1.0)
    responses = [fits[0].response] * series.channels if shared else [f.response for f in fits]
    params = {"shared": shared, "per_channel": [f.params for f in fits]}
    if refine_times and getattr(family, "refines_times", True):
        params["relative_exposures"] = [f.tau.tolist() for f in fits]
    if model == "exp":
        params["k"] = [f.params["k"] for f in fits]
        params["k_by_f_number"] = [f.params["k_by_f_number"] for f in fits]
    options = dict(opts, shared=shared, refine_times=refine_times, low=low, high=high)
    return ResponseFit(model, responses, params, float(loglik), n_par, n_obs,
                       float(np.sqrt(rss / n_obs)), shared, chosen, options)


def _on_paper_axis(series: ExposureSeries, f: FamilyFit, channels: list[int]) -> FamilyFit:
    """Rescale the unit-k exponential so the median pixel's radiance is 1 (see module doc)."""
    radiance = np.concatenate([radiance_map(series, f.response, channel=c).ravel()
                               for c in channels])
    radiance = radiance[np.isfinite(radiance)]
    if radiance.size == 0:
        raise InputError("cannot place k on the normalised axis: no pixel is validly exposed")
    k = float(np.median(radiance))
    t = series.exposures
    by_fn = {}
    if series.f_numbers is None:
        by_fn["none"] = k
    else:
        x_max = np.max(t / series.f_numbers**2)
        for n in np.unique(series.f_numbers):
            by_fn[f"{n:g}"] = k * (t.max() / x_max) / n**2
    params = {"k": k, "k_by_f_number": by_fn,
              "axis": "time / longest exposure; radiance / median pixel radiance"}
    return FamilyFit(Exp(k), params, 0, f.tau)


def radiance_map(series: ExposureSeries, resp: Response, channel: int = 0,
                 low: float = VALID_LOW, high: float | None = None) -> np.ndarray:
    """Hat-weighted merge of ``ln(I^-1(v) / tau)`` over the exposures (H x W; NaN where no
    exposure is valid), in the response's exposure unit at relative exposure 1.  ``high``:
    default ``VALID_HIGH`` times the series' ``white_level``."""
    if high is None:
        high = VALID_HIGH * series.white_level
    tau = series.relative_exposures()
    num = np.zeros(series.shape)
    den = np.zeros(series.shape)
    for im, t in zip(series.images, tau, strict=True):
        v = im[..., channel].astype(np.float64) / series.full_scale
        ok = (v > low) & (v < high)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_e = np.log(resp.inverse(v)) - np.log(t)
        w = np.where(ok & np.isfinite(log_e), np.minimum(v, 1.0 - v), 0.0)
        num += w * np.where(w > 0, log_e, 0.0)
        den += w
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.exp(num / den)


def fit_radiances(resp: Response, samples: SampleSet, tau: np.ndarray,
                  iterations: int = 80) -> np.ndarray:
    """Each sample's log radiance minimising its squared forward error under ``resp``
    (vectorised golden-section search; exposures ``exp(log_e) * tau``)."""
    v, ok = samples.values, samples.valid
    with np.errstate(divide="ignore", invalid="ignore"):
        guess = np.log(np.maximum(resp.inverse(v), 1e-12)) - np.log(tau)[None, :]
    guess = np.where(ok & np.isfinite(guess), guess, np.nan)
    # a badly fitting curve puts a sample's best radiance far from most single-image guesses,
    # but never outside their range
    lo, hi = np.nanmin(guess, axis=1) - 1.0, np.nanmax(guess, axis=1) + 1.0

    def cost(log_e):
        pred = resp.forward(np.exp(log_e)[:, None] * tau[None, :])
        return np.sum(np.where(ok, (pred - v) ** 2, 0.0), axis=1)

    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    for _ in range(iterations):
        a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        left = cost(a) < cost(b)
        hi = np.where(left, b, hi)
        lo = np.where(left, lo, a)
    return 0.5 * (lo + hi)


def forward_residuals(resp: Response, samples: SampleSet, tau: np.ndarray) -> np.ndarray:
    """Fitted minus observed normalised values of every valid sample (radiances re-fitted)."""
    log_e = fit_radiances(resp, samples, tau)
    pred = resp.forward(np.exp(log_e)[:, None] * tau[None, :])
    return (pred - samples.values)[samples.valid]
