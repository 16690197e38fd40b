"""``clblur calibrate``: fit response models to an exposure series, evaluate, write the best.

    clblur calibrate MANIFEST_OR_DIR [--times FILE] [--model M ...] -o response.json
                     [--report DIR] [--shared] [--refine-times] [--samples N] ...

Every model is fitted, evaluated by leave-one-exposure-out prediction, and the one with the
lowest mean held-out RMSE of the darker target is written (one curve per channel unless
``--shared``; ``clblur.calibration.compare.selection_score``).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from clblur.calibration.evaluate import EVAL_LOW, FLAT_TOLERANCE
from clblur.calibration.models import MODELS
from clblur.cli.options import add_series_options
from clblur.errors import InputError

__all__ = ["register", "run"]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate", help="fit camera response curves to an exposure series",
        description="Fit response models (the paper's Eq. 3 and richer families) to images of "
                    "one scene at several exposures; evaluate them on held-out pixels and "
                    "exposures; write the best as a response JSON for clblur blur --response.")
    p.add_argument("source", help="exposure-series manifest (.json) or folder of images")
    add_series_options(p)
    p.add_argument("--model", nargs="+", choices=MODELS, metavar="M",
                   help=f"models to fit: {', '.join(MODELS)} (default: all; emor only when "
                        "its basis files are found)")
    p.add_argument("-o", "--output", required=True, help="response JSON to write")
    p.add_argument("--report", metavar="DIR", help="write a report folder (markdown + PNG)")
    p.add_argument("--shared", action="store_true",
                   help="one curve for all channels instead of one per channel")
    p.add_argument("--refine-times", action="store_true",
                   help="re-estimate the exposures (uncertain shutter times)")
    p.add_argument("--samples", type=int, default=1000, metavar="N",
                   help="calibration patches per channel (default 1000)")
    p.add_argument("--patch", type=int, default=3, help="patch size, odd (default 3)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    p.add_argument("--fit-low", type=_number(float, 0, 1), default=None, metavar="V",
                   help="fit values above V of full scale (default: per family, 0.02 for "
                        "the exp families, 0.1 for the free curves)")
    p.add_argument("--emor-dir", metavar="DIR",
                   help="folder with invemor.txt (default: $CLBLUR_DATA/crf)")
    p.add_argument("--gaps", type=_number(float, 0, low_open=True), nargs="+", default=None,
                   metavar="STOPS",
                   help="prediction gaps in stops (default: 1 and 4, or the nearest gaps "
                        "the series has)")
    p.add_argument("--no-refit", action="store_true",
                   help="evaluate the full fit instead of refitting without each target "
                        "exposure (faster, slightly optimistic)")
    p.add_argument("--eval-low", type=_number(float, 0, 1), default=EVAL_LOW, metavar="V",
                   help="values at or below V of full scale count as clipped black: a "
                        "scored source must be above it, and is scored where its targets "
                        f"seldom fall to it (default {EVAL_LOW:.4f}: codes 3..252 of 255 are "
                        "valid)")
    p.add_argument("--flat-tolerance", type=_number(float, 0, none=True),
                   default=FLAT_TOLERANCE, metavar="V",
                   help="secondary column: pixels whose 3x3 neighbourhood spans at most V of "
                        f"full scale in both images; 'none' drops it (default {FLAT_TOLERANCE})")
    p.add_argument("--eval-pixels", type=_number(int, 0, low_open=True), default=None,
                   metavar="N",
                   help="score a random subset of N held-out pixels (default: all)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def _number(kind: type, low: float, high: float = math.inf, *, low_open: bool = False,
            none: bool = False) -> Callable[[str], float | None]:
    """An argparse type: a finite ``kind`` in ``[low, high)`` (``(low, high)`` with
    ``low_open``); with ``none``, the word 'none' gives None."""
    left = "(" if low_open else "["
    wanted = (f"a {kind.__name__} above {low:g}" if low_open and high == math.inf else
              f"a {kind.__name__} >= {low:g}" if high == math.inf else
              f"a {kind.__name__} in {left}{low:g}, {high:g})")
    or_none = " or 'none'" if none else ""

    def parse(text: str):
        if none and text.lower() == "none":
            return None
        try:
            value = kind(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (value > low if low_open else value >= low)
                and value < high):
            raise argparse.ArgumentTypeError(
                f"expected {wanted}{or_none}, got {text!r}")
        return value
    return parse


def _refined_times(chosen, series) -> str:
    """What ``--refine-times`` found, for the model written: each image's exposure against
    its stated one, in stops (longest = 0 in both; the mean over the channels' curves)."""
    refined = chosen.params.get("relative_exposures")
    if not refined:
        return (f"--refine-times: the {chosen.model} model takes the exposure times as "
                "given; the other models refine them")
    stated = np.asarray(series.relative_exposures(), np.float64)
    stated = stated / stated.max()
    found = np.mean([np.asarray(t, np.float64) / np.max(t) for t in refined], axis=0)
    stops = np.log2(found / stated)
    cells = ", ".join(f"{name} {d:+.2f}" for name, d in zip(series.names, stops, strict=True))
    return f"refined exposure times ({chosen.model}), stops off the stated ones: {cells}"


def check_outputs(args: argparse.Namespace) -> None:
    """Every output path must be writable before the fitting starts (it takes minutes)."""
    from clblur.calibration.series import series_files
    from clblur.io import check_output, refuse_overwrite
    from clblur.io.paths import refuse_folder_of_inputs
    from clblur.manifest import load_manifest, manifest_inputs

    check_output(args.output, args.source, args.times)
    source = Path(args.source)
    if source.is_dir():  # the images the series will read: no output may replace one
        inputs = series_files(source)
    elif source.is_file():
        inputs = manifest_inputs(load_manifest(source))
    else:
        inputs = []
    refuse_overwrite(args.output, *inputs)
    if Path(args.output).suffix.lower() != ".json":  # after the overwrite checks: those first
        raise InputError(f"-o {args.output}: the response is written as JSON; name a .json "
                         "file")
    if args.report is not None:
        report = Path(args.report)
        if report.exists() and not report.is_dir():
            raise InputError(f"--report {report} exists and is not a folder")
        if not report.parent.is_dir():  # the report folder is created, its parent must exist
            raise InputError(f"--report {report}: folder {report.parent} does not exist")
        refuse_folder_of_inputs(report, inputs, "--report")


def run(args: argparse.Namespace) -> int:
    from clblur.calibration.compare import calibrate, nan_reasons
    from clblur.responses import save_channel_set

    check_outputs(args)
    result = calibrate(args.source, args.model, times=args.times, shared=args.shared,
                       refine_times=args.refine_times, n_samples=args.samples,
                       patch=args.patch, seed=args.seed, fit_low=args.fit_low,
                       emor_dir=args.emor_dir, gaps=args.gaps, refit=not args.no_refit,
                       eval_low=args.eval_low, flat_tolerance=args.flat_tolerance,
                       max_pixels=args.eval_pixels, progress=not args.quiet,
                       align=not args.no_align)
    best, evaluations = result.best, result.evaluations
    if result.series.registration is not None:
        from clblur.registration import summary

        print(summary(result.series.registration, result.series.names))
    if (note := result.series.clipping_note()) is not None:
        print(f"the series {note}")
    if (note := result.series.moving_note()) is not None:
        print(note)
    gaps = list(evaluations[best]["rmse"])
    flat = "flat" in evaluations[best]
    print("held-out RMSE (code values) on all valid pixels, target darker / brighter / both"
          + ("; flat pixels only, darker" if flat else "") + "; AIC")
    # every cell starts with a space: a 16-bit series' errors run to thousands of codes
    print("model         " + "".join(f" {str(g) + '-stop':>26}" for g in gaps)
          + ("".join(f" {str(g) + '-stop flat':>12}" for g in gaps) if flat else "")
          + "         AIC")
    for n, e in evaluations.items():
        cells = "".join(f" {e['rmse_darker'][g]:8.2f} {e['rmse_brighter'][g]:8.2f}"
                        f" {e['rmse'][g]:8.2f}" for g in gaps)
        if flat:
            cells += "".join(f" {e['flat']['rmse_darker'][g]:12.2f}" for g in gaps)
        print(f"{n:<14}{cells}  {e['aic']:10.0f}" + ("   <- best" if n == best else ""))
    if "spline" in result.fits:  # its smoothness is chosen from the data: say what and how
        per_curve = result.fits["spline"].params["per_channel"]
        rule = per_curve[0].get("smoothness_cv", {}).get("rule", "as given")
        print(f"spline smoothness ({rule}): "
              + " / ".join(f"{p['smoothness']:.3g}" for p in per_curve))
    if result.surround is not None:  # what no curve holds: local tone mapping
        from clblur.calibration.surround import describe

        print(describe(result.surround, result.series.channels))
    for name, why in result.skipped.items():
        print(f"skipped {name}: {why}")
    for line in nan_reasons(evaluations[best]):  # say why a column is nan
        print(line)
    if not args.no_refit and not evaluations[best]["refit"]:
        print(f"scored with the full fits: a series of {len(result.series.images)} images "
              "cannot be refitted without one of them (held-out refits need 3 or more)")
    chosen = result.fits[best]
    if args.refine_times:
        print(_refined_times(chosen, result.series))
    if args.shared or len(chosen.responses) == 1:
        chosen.responses[0].save(args.output)
    else:
        save_channel_set(args.output, chosen.responses)
    print(f"wrote {args.output} ({best}, {'shared' if args.shared else 'per channel'})")
    if args.report:
        from clblur.calibration.report import write_report

        argv = sys.argv[sys.argv.index("calibrate") + 1:] if "calibrate" in sys.argv else []
        command = "clblur calibrate " + " ".join(shlex.quote(a) for a in argv) if argv else ""
        path = write_report(args.report, result.series, result.fits, evaluations, best,
                            command, result.skipped)
        print(f"wrote {path}")
    return 0
