"""Calibration report: markdown plus PNG figures (matplotlib, Agg backend).

Figures follow the paper: Figure 1 plots code value against exposure time for a few samples;
Figure 2 plots the same samples against *normalised* exposure (each sample's time multiplied
by its fitted radiance) so they collapse onto the response curve, with every fitted model
drawn over them.  Residual plots show fitted minus observed code values against the observed
value for each model.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from clblur.calibration.censoring import CENSORED
from clblur.calibration.cross_exposure import curve_black_level
from clblur.calibration.evaluate import EVAL_HIGH, EVAL_LOW, FLAT_TOLERANCE
from clblur.calibration.fitting import LIKELIHOOD_LOW, ResponseFit, fit_radiances
from clblur.calibration.series import ExposureSeries, photometric_exposure
from clblur.calibration.surround import describe as describe_surround
from clblur.io import atomic_write, atomic_write_text
from clblur.registration import summary

__all__ = ["CHANNEL_NAMES", "COLOURS", "comparison_table", "curve_table", "darkest_codes",
           "figure_normalised_curves", "figure_residuals", "figure_values_vs_time", "series_table",
           "write_report"]

CHANNEL_NAMES = {1: ["grey"], 3: ["red", "green", "blue"]}
COLOURS = ["tab:red", "tab:green", "tab:blue"]


def _channel_names(n: int) -> list[str]:
    return CHANNEL_NAMES.get(n, [f"channel {i}" for i in range(n)])


def _save(fig, path: Path) -> None:
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))


def _pick_samples(fit: ResponseFit, channel: int, count: int = 8) -> np.ndarray:
    """Indices of ``count`` samples spread over brightness, preferring many valid exposures."""
    s = fit.sampling.per_channel[channel]
    level = np.nanmean(np.where(s.valid, s.values, np.nan), axis=1)
    rich = np.flatnonzero(s.valid.sum(axis=1) >= max(3, s.valid.shape[1] // 4))
    pool = rich if rich.size >= count else np.arange(len(s))
    order = pool[np.argsort(level[pool])]
    return order[np.linspace(0, order.size - 1, min(count, order.size)).astype(int)]


def figure_values_vs_time(series: ExposureSeries, fit: ResponseFit, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = _channel_names(series.channels)
    fig, axes = plt.subplots(1, series.channels, figsize=(4.2 * series.channels, 3.6),
                             squeeze=False)
    t = photometric_exposure(series.exposures, series.f_numbers)
    for c, ax in enumerate(axes[0]):
        s = fit.sampling.per_channel[c]
        for k in _pick_samples(fit, c):
            ok = s.valid[k]
            ax.plot(t, s.values[k] * series.full_scale, color="0.8", lw=0.8)
            ax.plot(t[ok], s.values[k, ok] * series.full_scale, "o-", ms=3, lw=1)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("exposure time (s)" if series.f_numbers is None else "t / N^2")
        ax.set_ylabel("code value")
        ax.set_title(f"{names[c]}: samples vs exposure (paper Fig. 1)")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def figure_normalised_curves(series: ExposureSeries, fits: dict[str, ResponseFit],
                             reference: str, path: Path) -> None:
    """Samples on the reference model's normalised exposure axis, with every model's curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = _channel_names(series.channels)
    ref = fits[reference]
    tau = series.relative_exposures()
    fig, axes = plt.subplots(1, series.channels, figsize=(4.2 * series.channels, 3.8),
                             squeeze=False)
    for c, ax in enumerate(axes[0]):
        s = ref.sampling.per_channel[c]
        resp = ref.responses[c]
        log_e = fit_radiances(resp, s, tau)
        x = np.exp(log_e)[:, None] * tau[None, :]
        top = float(resp.inverse(np.array(0.98)))
        ax.plot((x / top)[s.valid], (s.values * series.full_scale)[s.valid], ".", ms=1.5,
                color="0.6", alpha=0.5, label=f"samples (axis of {reference})")
        grid = np.geomspace(1e-4, 1.5, 400)
        for name, f in fits.items():
            r = f.responses[c]
            # match each curve to the reference axis at mid-grey: only the shape is compared
            scale = float(r.inverse(np.array(0.5)) / (resp.inverse(np.array(0.5)) / top))
            ax.plot(grid, r.forward(grid * scale) * series.full_scale, lw=1.3, label=name)
        ax.set_xscale("log")
        ax.set_xlim(1e-3, 1.5)
        ax.set_xlabel("normalised exposure")
        ax.set_ylabel("code value")
        ax.set_title(f"{names[c]}: normalised curves (paper Fig. 2)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def figure_residuals(series: ExposureSeries, fits: dict[str, ResponseFit], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tau = series.relative_exposures()
    n = len(fits)
    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False,
                             sharey=True)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, (name, f) in zip(axes.ravel(), fits.items(), strict=False):
        # the values every model's likelihood is computed on (see fitting.LIKELIHOOD_LOW)
        common = f.sampling.with_range(max(LIKELIHOOD_LOW, f.sampling.low), f.sampling.high)
        for c in range(series.channels):
            s = common.per_channel[c]
            resp = f.responses[c]
            log_e = fit_radiances(resp, s, tau)
            pred = resp.forward(np.exp(log_e)[:, None] * tau[None, :])
            res = ((pred - s.values) * series.full_scale)[s.valid]
            obs = (s.values * series.full_scale)[s.valid]
            ax.plot(obs, res, ".", ms=1, alpha=0.4, color=COLOURS[c % 3])
            edges = np.linspace(0, series.full_scale, 33)
            idx = np.digitize(obs, edges)
            med = [np.median(res[idx == i]) if np.any(idx == i) else np.nan
                   for i in range(1, edges.size)]
            ax.plot(0.5 * (edges[1:] + edges[:-1]), med, "-", color=COLOURS[c % 3], lw=1.5)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_ylim(-30, 30)
        ax.set_title(f"{name}: fit residual (RMS {f.rmse_fit:.2f})", fontsize=9)
        ax.set_xlabel("observed code value")
        ax.set_ylabel("fitted - observed")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def comparison_table(evaluations: dict[str, dict], gaps) -> str:
    head = ["model"] + [f"{g}-stop both" for g in gaps] + [f"{g}-stop darker" for g in gaps] \
        + [f"{g}-stop brighter" for g in gaps] + [f"{g}-stop R/G/B" for g in gaps] \
        + [f"{g}-stop darker, flat only" for g in gaps] + ["fit RMSE", "params", "AIC", "BIC"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, e in evaluations.items():
        cells = [name] + [f"{e['rmse'][g]:.2f}" for g in gaps]
        cells += [f"{e['rmse_darker'][g]:.2f}" for g in gaps]
        cells += [f"{e['rmse_brighter'][g]:.2f}" for g in gaps]
        cells += [" / ".join(f"{v:.2f}" for v in e["rmse_per_channel"][g]) for g in gaps]
        flat = e.get("flat")
        cells += [f"{flat['rmse_darker'][g]:.2f}" if flat else "-" for g in gaps]
        cells += [f"{e['rmse_fit']:.2f}", str(e["n_params"]), f"{e['aic']:.0f}",
                  f"{e['bic']:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def series_table(series: ExposureSeries, tolerance: float = 0.03) -> str:
    """Per image: median per channel, clipped share (at the series' white level), and
    *impossible* pixels, whose value
    exceeds the next longer exposure's by more than ``tolerance`` of full scale (corrupt
    values, moving objects)."""
    order = np.argsort(series.relative_exposures())
    full = series.full_scale
    # a camera that clips below full scale clips at its white level (the series' own)
    clip = min(series.white_level, 1.0) * full
    lines = ["| image | exposure (s) | median per channel | clipped | impossible |",
             "|---|---|---|---|---|"]
    for pos, i in enumerate(order):
        im = series.images[i].astype(np.float64)
        med = " / ".join(f"{m:g}" for m in np.median(im.reshape(-1, series.channels), axis=0))
        clipped = float(np.mean(im >= clip))
        if pos + 1 < order.size:
            longer = series.images[order[pos + 1]].astype(np.float64)
            bad = f"{float(np.mean(im > longer + tolerance * full)) * 100:.1f} %"
        else:
            bad = "-"
        lines.append(f"| {series.names[i]} | {series.exposures[i]:g} | {med} | "
                     f"{clipped * 100:.1f} % | {bad} |")
    return "\n".join(lines)


# a curve's black level in the report: where its exposure is this far below mid-scale's, so
# close to zero that a power-law toe above the level adds a fraction of a code (gamma 2.2:
# 0.2 DN); the spline's own toe (``curve_black_level``'s default) is a looser 1/1000
BLACK_FRACTION = 1e-6
# the darkest code of a series: this quantile of its darkest image, per channel
DARKEST_QUANTILE = 1e-3
# a black level more than this many uint8 codes below the darkest code is marked as
# extrapolated: a power-law toe nears its level slowly (gamma 2.2 over a level of 13 DN is
# still a code above it 5e-6 of full scale's exposure in), so the darkest codes a series
# holds lie a little above the level even where they measure it
DARK_MARGIN = 3.0


def darkest_codes(series: ExposureSeries, quantile: float = DARKEST_QUANTILE) -> np.ndarray:
    """Per channel, the darkest code the series holds: the ``quantile`` of its darkest
    image's codes above 0 (a quantile, not the minimum, so one dead pixel does not set it;
    code 0 is left out as the calibration leaves it out, a floor that clips, or a masked
    border: Memorial's darkest image is 4 % zeros in red and green, 13 DN and up around
    them)."""
    darkest = series.images[int(np.argmin(series.relative_exposures()))]
    flat = darkest.reshape(-1, series.channels)
    return np.array([np.quantile(c[c > 0], quantile) if (c > 0).any() else 0.0
                     for c in flat.T])


def curve_table(series: ExposureSeries, fits: dict[str, ResponseFit]) -> str:
    """Contrast of each fitted curve: stops from 30 to 230 DN on the uint8 scale (the same
    fractions of full scale in the series' codes), the DN gained per stop at 30 and at 150,
    and its black level (``curve_black_level``: the highest code whose exposure is below
    ``BLACK_FRACTION`` of mid-scale's, in the series' codes), one definition for every
    family.  Beside it the darkest code of the series (:func:`darkest_codes`): a black level
    more than ``DARK_MARGIN`` uint8 codes below that is the curve's extrapolation, not a
    measurement, and is marked so; so is a fitted toe's whose power sits at an end of its
    range (``clblur.calibration.inverse_families.fit_toe``)."""
    scale = series.full_scale / 255.0
    lo, hi, mid = 30 * scale, 230 * scale, 150 * scale
    names = _channel_names(series.channels)
    darkest = darkest_codes(series)
    lines = [f"| model | channel | stops {lo:.0f} -> {hi:.0f} DN | DN per stop at {lo:.0f} | "
             f"DN per stop at {mid:.0f} | black level (DN) | darkest code (DN) |",
             "|---|---|---|---|---|---|---|"]
    extrapolated = False
    for name, f in fits.items():
        for c, resp in enumerate(f.responses):
            def inv(code, r=resp):
                # numpy scalars: a zero inverse gives inf under errstate, not ZeroDivisionError
                return np.float64(r.inverse(np.array(code / series.full_scale)))

            with np.errstate(divide="ignore", invalid="ignore"):
                span = np.log2(inv(hi) / inv(lo))
                at_lo = scale / np.log2(inv(lo + scale) / inv(lo))
                at_mid = scale / np.log2(inv(mid + scale) / inv(mid))
            black = curve_black_level(resp, BLACK_FRACTION) * series.full_scale
            # the channel's darkest code, of every channel for a curve shared by all
            dark = float(darkest[c] if len(f.responses) > 1 else darkest.min())
            toe = getattr(resp, "meta", {}).get("params", {}).get("toe")
            mark = ""
            if black + DARK_MARGIN * scale < dark or (toe is not None and not toe["held"]):
                mark, extrapolated = " *", True
            lines.append(f"| {name} | {names[c]} | {span:.2f} | {at_lo:.1f} | {at_mid:.1f} | "
                         f"{black:.1f}{mark} | {dark:.0f} |")
    if extrapolated:
        lines += ["", "\\* not measured: well below the darkest code of the series, or a toe "
                  "whose power sits at the end of its range (the darker data do not hold it). "
                  "It is the curve's extrapolation; a darker exposure would measure it."]
    return "\n".join(lines)


def write_report(folder: str | Path, series: ExposureSeries, fits: dict[str, ResponseFit],
                 evaluations: dict[str, dict], best: str, command: str = "",
                 skipped: dict[str, str] | None = None) -> Path:
    """Write ``report.md``, ``evaluation.json`` and the figures into ``folder`` (created);
    ``skipped``: models that could not be fitted, with the reason."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    reference = best if best in fits else next(iter(fits))
    figure_values_vs_time(series, fits[reference], folder / "fig1_values_vs_time.png")
    figure_normalised_curves(series, fits, reference, folder / "fig2_normalised_curves.png")
    figure_residuals(series, fits, folder / "residuals.png")
    gaps = list(next(iter(evaluations.values()))["rmse"]) if evaluations else []
    doc = {name: {"fit": fits[name].summary(), "evaluation": evaluations.get(name)}
           for name in fits}
    atomic_write_text(folder / "evaluation.json", json.dumps(doc, indent=1, default=float)
                      + "\n")
    t = series.exposures
    registered = ([] if series.registration is None else
                  ["R" + summary(series.registration, series.names)[1:]
                   + " (`clblur.registration`)."])
    if (note := series.clipping_note()) is not None:
        registered.append(f"The series {note}.")
    if (note := series.moving_note()) is not None:
        registered.append(f"{note[0].upper()}{note[1:]} (`clblur.calibration.ghosts`).")
    lines = [
        "# Calibration report", "",
        f"Series: {len(series.images)} images, {series.shape[1]} x {series.shape[0]} "
        f"(W x H) x {series.channels} {series.dtype}, exposures {t.min():g} s ... "
        f"{t.max():g} s.", *registered,
        f"Best model (lowest mean held-out RMSE over the gaps, darker target): **{best}**.",
        "",
    ]
    if command:
        lines += ["Command:", "", "```", command, "```", ""]
    missing = {g: why for e in evaluations.values() for g, why in e.get("missing", {}).items()}
    if evaluations:
        refitted = all(e.get("refit", True) for e in evaluations.values())
        held_out = ("the model fitted without it (leave-one-exposure-out)" if refitted else
                    "the model fitted on all images (no refit: `--no-refit`, or a series of "
                    "2 images, which leaves nothing to fit without one)")
        low, high = next(iter(evaluations.values())).get("valid", (EVAL_LOW, EVAL_HIGH))
        full = series.full_scale
        stops = " and ".join(f"{g:g}" for g in gaps) + (" stop" if gaps == [1] else " stops")
        flat_dn = next(iter(evaluations.values())).get("flat_tolerance") or FLAT_TOLERANCE
        censored = next(iter(evaluations.values())).get("censored", CENSORED)
        lines += [f"*{g}-stop columns are empty: {why}*" for g, why in missing.items()]
        lines += [f"*{name} is not ranked: {why}*" for name, why in (skipped or {}).items()]
        lines += ["## Held-out prediction (code values) and information criteria", "",
                  comparison_table(evaluations, gaps), "",
                  f"RMSE in code values: predicting each image from the images {stops} "
                  f"away through {held_out}; every pixel outside the fitting samples "
                  f"whose source is valid (codes {math.ceil(low * full):g}.."
                  f"{math.ceil(high * full) - 1:g} of {full:g}) at a source value where at "
                  f"most {censored:.0%} of the targets are clipped (chosen by the source, "
                  f"never by the target's own noise), edges and textures included; the "
                  "*flat only* columns keep pixels whose 3 x 3 neighbourhood spans at most "
                  f"{flat_dn * full:.3g} DN in both images (`clblur.calibration.evaluate`).  "
                  "*darker*: the target is the shorter exposure; *brighter*: "
                  "the longer; *both*: pooled.  AIC/BIC: forward residuals of the sampled "
                  "patches with values in [0.1, 0.98] of full scale, the same for every "
                  "model (Gaussian noise; see `clblur.calibration.fitting`).", ""]
    if evaluations.get(best, {}).get("surround") is not None:
        lines += ["## Does the error depend on the surround?", "",
                  describe_surround(evaluations[best]["surround"], series.channels) + " ("
                  "`clblur.calibration.surround`: the chosen model's held-out error on flat "
                  "pixels, by the code and by the brightness of the pixel's surround, "
                  "cross-fitted on a checkerboard of blocks.)", ""]
    lines += ["## The series", "", series_table(series), "",
              "## Contrast of the fitted curves", "", curve_table(series, fits), "",
              "## Figures", "",
              "![values vs time](fig1_values_vs_time.png)", "",
              "![normalised curves](fig2_normalised_curves.png)", "",
              "![residuals](residuals.png)", ""]
    atomic_write_text(folder / "report.md", "\n".join(lines))
    return folder / "report.md"
