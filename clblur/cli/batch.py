"""``clblur batch IN_DIR OUT_DIR``: every image of a folder (``clblur.batch``)."""

from __future__ import annotations

import argparse
import sys
from contextlib import ExitStack
from pathlib import Path

from clblur.cli.options import (
    add_blur_options,
    add_memory_option,
    check_device,
    check_response,
    parse_vector,
)
from clblur.errors import InputError

__all__ = ["register", "run"]


def register(sub) -> None:
    p = sub.add_parser(
        "batch", help="blur every image in a folder (resumable; local or Dask distributed)",
        description="Blur every image in IN_DIR into OUT_DIR. Finished outputs are skipped, "
                    "partial ones redone; an image that fails while it is blurred (a corrupt "
                    "file) is reported and skipped. Exit code 0 when every image is finished, "
                    "1 when any failed, 2 for bad input found before any work: an option, a "
                    "manifest cell or path, a missing image, flow or PSF, an image without a "
                    "motion (nothing is written then, OUT_DIR not even created).")
    p.add_argument("in_dir", metavar="IN_DIR")
    p.add_argument("out_dir", metavar="OUT_DIR")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--motion", metavar="DX,DY", help="one displacement for every image")
    g.add_argument("--flow-dir", metavar="DIR",
                   help="per-image flows named like the images: <stem>.npy or <stem>.flo")
    g.add_argument("--psf", metavar="FILE", help="one blur kernel for every image")
    p.add_argument("--manifest", metavar="CSV",
                   help="per-image overrides: columns image, output, dx, dy, flow, psf, "
                        "response, anchor, samples, saturation, exposure (paths inside the "
                        "manifest's folder or IN_DIR); every cell is checked before any work")
    add_blur_options(p)
    add_memory_option(p, "per-image working memory")
    p.add_argument("--scheduler", default=None, metavar="local[:N]|ADDRESS",
                   help="run on Dask distributed: a LocalCluster of N worker processes, or "
                        "the scheduler of a running cluster (tcp://host:8786)")
    p.add_argument("--force", action="store_true", help="redo finished images too")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from clblur.batch import IMAGE_SUFFIXES, plan_jobs, run_batch, summary
    from clblur.batch_state import Job, remove_partials
    from clblur.distributed import client_for, parse_scheduler
    from clblur.tiling import parse_size

    out_dir = Path(args.out_dir)
    if args.psf is not None and not Path(args.psf).is_file():
        raise InputError(f"PSF file not found: {args.psf}")
    defaults = Job(src="", dst="", motion=parse_vector(args.motion) if args.motion else None,
                   psf=str(Path(args.psf).resolve()) if args.psf else None,
                   response=args.response, anchor=args.anchor, samples=args.samples,
                   saturation=args.saturation, exposure=args.exposure, backend=args.backend,
                   device=args.device,
                   memory_budget=args.memory_budget)
    # fail now, not once per image (plan_jobs checks the rest: motion, PSF, manifest cells)
    parse_size(args.memory_budget)
    if args.response is not None:  # else each image's own (linear for an EXR)
        check_response(args.response)
    if args.scheduler is not None:
        parse_scheduler(args.scheduler)
    check_device(args)
    jobs = plan_jobs(Path(args.in_dir), out_dir, defaults,
                     Path(args.flow_dir) if args.flow_dir else None,
                     Path(args.manifest) if args.manifest else None)
    if not jobs:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {args.in_dir}")
    with ExitStack() as stack:  # reach the scheduler before OUT_DIR is made: a bad one is 2
        client = stack.enter_context(client_for(args.scheduler)) \
            if args.scheduler is not None else None
        out_dir.mkdir(parents=True, exist_ok=True)
        stale = remove_partials(out_dir, [Path(j.dst).name for j in jobs])
        if stale:
            print(f"removed {stale} partial file(s) left by an interrupted run", file=sys.stderr)
        results, skipped = run_batch(jobs, progress=not args.quiet, force=args.force,
                                     client=client)
    print(summary(results, skipped))
    return 0 if all(r.ok for r in results) else 1
