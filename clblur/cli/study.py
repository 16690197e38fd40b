"""``clblur study MANIFEST|FOLDER --report report.json [--times FILE] [--figures DIR]
[--splits N]``."""

from __future__ import annotations

import argparse
from pathlib import Path

from clblur.cli.options import add_series_options
from clblur.errors import InputError

__all__ = ["register", "run"]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "study", help="show what the paper's simulation gets wrong on measured data",
        description="Fit the paper's model (Eq. 3 + Eq. 9) to measured data, test each effect "
                    "of the vocabulary on held-out pixels, extend the model with the "
                    "significant ones and report the held-out gain.")
    p.add_argument("manifest", metavar="source",
                   help="manifest JSON (exposure-series, blur-pair, frame-stack), or a folder "
                        "of images of one scene at several exposures (as clblur calibrate "
                        "takes it)")
    add_series_options(p, only="exposure series: ")
    p.add_argument("--report", required=True, help="output report JSON (a .md beside it)")
    p.add_argument("--figures", help="folder for the figures (created if missing)")
    p.add_argument("--max-pixels", type=int, default=None,
                   help="target pixels used in all (default 60000)")
    p.add_argument("--alpha", type=float, default=0.05,
                   help="false-positive rate on null data for the whole study (default 0.05)")
    p.add_argument("--splits", type=int, default=1,
                   help="repeat the diagnosis on N splits of the data into two folds and "
                        "report how often each effect is selected (default 1; N times the "
                        "time)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from clblur.calibration.series import folder_series
    from clblur.io import check_output
    from clblur.manifest import load_manifest
    from clblur.study.run import DEFAULT_PIXELS, check_report_name, study

    # every output checked before the study runs (it takes minutes); study() refuses an
    # output that would replace an input
    check_report_name(args.report, "--report")
    check_output(args.report, args.manifest, args.times)
    check_output(Path(args.report).with_suffix(".md"), args.manifest, args.times)
    if args.splits < 1:
        raise InputError(f"--splits must be at least 1, got {args.splits}")
    if args.figures is not None and Path(args.figures).exists() \
            and not Path(args.figures).is_dir():
        raise InputError(f"--figures {args.figures} exists and is not a folder")
    if Path(args.manifest).is_dir():  # an exposure series, read as calibrate reads it
        manifest = folder_series(args.manifest, args.times)
    elif args.times is not None:
        raise InputError("--times is for a folder; a manifest gives its own exposures")
    else:
        manifest = load_manifest(args.manifest)
    result = study(manifest, report=args.report, figures_dir=args.figures,
                   max_pixels=args.max_pixels or DEFAULT_PIXELS, alpha=args.alpha,
                   progress=not args.quiet, splits=args.splits, align=not args.no_align)
    r = result.report
    if "registration" in r:
        print(r["registration"]["summary"])
    for line in ("clipping", "padding", "moving", "psf_estimated"):
        if line in r:
            print(r[line])
    found = ", ".join(r["extended"]["effects"]) or "none"
    print(f"significant effects: {found}; held-out RMSE {r['baseline']['heldout_rmse']:.3f} "
          f"-> {r['extended']['heldout_rmse']:.3f} codes")
    if "splits" in r:
        sp = r["splits"]
        shares = ", ".join(f"{e} {round(v * sp['count'])}/{sp['count']}"
                           for e, v in sp["selected"].items()) or "none"
        print(f"selected over {sp['count']} splits: {shares}; stable: "
              f"{', '.join(sp['stable']) or 'none'}")
    return 0
