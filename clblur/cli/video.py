"""``clblur video IN OUT``: motion-blur a video or image sequence along its optical flow."""

from __future__ import annotations

import argparse

import numpy as np

from clblur.cli.options import (
    add_backend_options,
    add_exposure_option,
    check_device,
    check_response,
)
from clblur.errors import InputError
from clblur.io.video import DEFAULT_CRF
from clblur.layering import NAMED_ORDERS
from clblur.video import DEFAULT_RESPONSE, DEFAULT_SHUTTER

__all__ = ["register", "run"]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "video", help="motion-blur a video or image sequence along its optical flow",
        description="Blur every frame along its optical flow: backward flow for the first "
                    "half of the shutter, forward flow for the second, so the path can bend. "
                    "IN and OUT are video files (.mp4 .mkv .mov .avi .webm) or image folders "
                    "(an OUT without a suffix becomes a folder).")
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--shutter", type=float, default=DEFAULT_SHUTTER, metavar="DEG",
                   help="shutter angle in degrees, 0..360 (360: open for the whole frame "
                        "interval; default 180)")
    p.add_argument("--flow", default="dis", metavar="dis|farneback|DIR",
                   help="optical flow method (default dis), or a folder of "
                        "forward_NNNNNN/backward_NNNNNN .flo/.npy files")
    p.add_argument("--samples", type=int, default=None, metavar="N",
                   help="samples per pixel for each half of the shutter (default: "
                        "ceil(|v|)+1 per pixel)")
    add_exposure_option(p)
    p.add_argument("--response", default=DEFAULT_RESPONSE, metavar="SPEC",
                   help="camera response: linear, exp, exp:K, gamma:G, srgb or a JSON file "
                        f"(default {DEFAULT_RESPONSE}; see docs/studies/video.md)")
    p.add_argument("--saturation", type=float, default=1.0, metavar="S",
                   help="exposure of clipped pixels in units of the least saturating one "
                        "(>= 1, default 1)")
    add_backend_options(p)
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate of an image-sequence input (default 30)")
    p.add_argument("--codec", default=None,
                   help="video encoder (default: libx264 for .mp4/.mkv/.mov, mpeg4 for .avi, "
                        "libvpx-vp9 for .webm)")
    p.add_argument("--crf", type=int, default=DEFAULT_CRF,
                   help=f"encoder quality, lower is better (default {DEFAULT_CRF})")
    p.add_argument("--layers", action="store_true",
                   help="layered exposure: moving objects smear over what is behind them "
                        "(ordered by --order); default: gather along each pixel's own vector")
    p.add_argument("--order", choices=NAMED_ORDERS, default=None,
                   help="what is nearer, for --layers (given alone, it implies --layers): "
                        "speed, faster = nearer (default); departure, what moves against the "
                        "frame's dominant motion (a camera that pans or tracks over a static "
                        "scene)")
    p.add_argument("--curved", action="store_true",
                   help="follow the parabola through each pixel's previous, current and next "
                        "positions, not two straight halves (turning or accelerating motion)")
    p.add_argument("--save-flows", default=None, metavar="DIR",
                   help="also write the flows used, in the --flow DIR layout")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)




def run(args: argparse.Namespace) -> int:
    from clblur.video import blur_video

    if args.fps is not None and not (np.isfinite(args.fps) and args.fps > 0):
        raise InputError(f"--fps must be a positive number, got {args.fps}")
    check_response(args.response)
    check_device(args)
    result = blur_video(args.input, args.output, response=args.response, shutter=args.shutter,
                        flow=args.flow, samples=args.samples, backend=args.backend,
                        saturation=args.saturation, device=args.device, fps=args.fps,
                        codec=args.codec, crf=args.crf, save_flows_to=args.save_flows,
                        layers=args.layers or args.order is not None,
                        order=args.order or "speed", progress=not args.quiet,
                        exposure=args.exposure, curved=args.curved)
    audio = {"copied": ", audio copied", "dropped": ", audio dropped (image sequence output)",
             "none": ""}[result.audio]
    print(f"wrote {result.frames} frame(s) at {float(result.fps):g} fps to {result.output}"
          f"{audio}")
    return 0
