"""``clblur blur IN OUT``: one image along a motion, flow field or PSF."""

from __future__ import annotations

import argparse

from clblur.cli.options import (
    add_blur_options,
    add_memory_option,
    add_motion_options,
    blur_options,
    check_device,
    check_response,
    motion_from_args,
)

__all__ = ["register", "run"]


def register(sub) -> None:
    p = sub.add_parser("blur", help="blur an image along a motion, flow field or PSF",
                       description="Photo-consistent motion blur of one image. Large TIFF "
                                   "images are processed in tiles within --memory-budget.")
    p.add_argument("input")
    p.add_argument("output")
    add_motion_options(p, required=True)
    add_blur_options(p)
    add_memory_option(p, "bound memory use")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from clblur.io import IMAGE_FORMATS, check_output
    from clblur.tiling import blur_file, parse_size

    check_output(args.output, args.input, args.flow, args.psf, suffixes=tuple(IMAGE_FORMATS))
    parse_size(args.memory_budget)
    check_response(args.response)
    check_device(args)
    blur_file(args.input, args.output, motion_from_args(args), **blur_options(args),
              memory_budget=args.memory_budget, progress=True)
    print(f"wrote {args.output}")
    return 0
