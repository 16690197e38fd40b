"""``clblur blur IN OUT``: one image along a motion, flow field or PSF."""

from __future__ import annotations

import argparse

from clblur.cli.options import (
    add_blur_options,
    add_memory_option,
    add_motion_options,
    add_path_option,
    add_vector_options,
    blur_options,
    check_device,
    check_response,
    check_vector_options,
    default_response,
    motion_from_args,
)
from clblur.errors import InputError

__all__ = ["register", "run"]


def register(sub) -> None:
    p = sub.add_parser("blur", help="blur an image along a motion, flow field or PSF",
                       description="Photo-consistent motion blur of one image. Large TIFF "
                                   "images are processed in tiles within --memory-budget.")
    p.add_argument("input", help="the image; in a multilayer EXR, FILE.exr:LAYER names a "
                                 "colour layer (LAYER.R/G/B/A, e.g. ViewLayer.Combined)")
    p.add_argument("output", help="the blurred image; an EXR input's windows (overscan, "
                                  "bounding box), pixel aspect ratio, compression and "
                                  "float16 colour are kept by an EXR output")
    add_motion_options(p, required=True)
    add_blur_options(p)
    add_memory_option(p, "bound memory use")
    add_vector_options(p, "--flow")
    add_path_option(p)
    p.add_argument("--depth", default=None, metavar="FILE|speed|departure",
                   help="occlusion order for a per-pixel --flow, H x W .npy or EXR depth "
                        "(FILE.exr[:CHANNEL]; smaller "
                        "= nearer; integers: layer IDs), or one computed from the flow: speed "
                        "(faster = nearer) or departure (what moves against the dominant "
                        "motion is nearer): layered exposure, moving objects smear over what "
                        "is behind them")
    p.add_argument("--inverse-depth", action="store_true",
                   help="the depth file holds 1 / distance (larger = nearer), as Nuke's "
                        "depth.Z does by default (its ScanlineRender's 1/Z output); 0 is "
                        "infinitely far")
    p.add_argument("--alpha", choices=("auto", "yes", "no"), default="auto",
                   help="the last channel is coverage, blurred linearly with colour "
                        "premultiplied in linear light (auto: 2- and 4-channel images)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from clblur.io import IMAGE_FORMATS, check_output, exr_layout, probe_image
    from clblur.io.flows import exr_part
    from clblur.layering import NAMED_ORDERS
    from clblur.tiling import blur_file, parse_size

    named = args.depth in NAMED_ORDERS  # an ordering computed from the flow, not a file
    depth_file = None if args.depth is None or named else exr_part(args.depth)[0]
    image_file, layer = exr_part(args.input)
    flow_file = None if args.flow is None else exr_part(args.flow)[0]
    check_output(args.output, image_file, flow_file, args.psf, depth_file,
                 suffixes=tuple(IMAGE_FORMATS))
    parse_size(args.memory_budget)
    channels = probe_image(image_file, layer).channels  # the header only: nothing decoded
    if args.inverse_depth and depth_file is None:
        raise InputError("--inverse-depth describes a --depth file, and none was given")
    if args.depth is not None and args.flow is None:
        # one displacement moves every pixel alike: nothing is revealed or hidden, and the
        # result would be the gather's whatever the depth says (a silent no-op otherwise)
        given = "--motion" if args.motion is not None else "--psf"
        raise InputError(f"--depth orders surfaces that move relative to each other; with "
                         f"{given} every pixel moves alike and nothing occludes: give a "
                         "per-pixel --flow, or leave --depth out")
    if args.alpha == "yes" and channels not in (2, 4):
        raise InputError(f"--alpha yes: {args.input} has {channels} channel(s); coverage is "
                         "the last of grey + alpha (2) or RGBA (4)")
    alpha = args.alpha == "yes" or (args.alpha == "auto" and channels in (2, 4))
    default_response(args, image_file)
    check_response(args.response, channels=channels - int(alpha))
    check_device(args)
    check_vector_options(args, args.flow is not None)
    _check_path(args, alpha)
    if args.depth is not None or alpha or args.path != "straight" or layer is not None:
        _blur_whole(args, alpha)  # layered exposure, alpha, paths and EXR layers: whole
    else:
        blur_file(image_file, args.output, motion_from_args(args, layout=exr_layout(image_file)),
                  **blur_options(args), memory_budget=args.memory_budget, progress=True)
    print(f"wrote {args.output}")
    return 0


def _check_path(args: argparse.Namespace, alpha: bool) -> None:
    """A bent or curved path is a renderer's two halves about the frame time."""
    if args.path == "straight":
        return
    if args.flow is None or args.vectors == "clblur":
        raise InputError(f"--path {args.path} needs a renderer's vector pass: give --flow "
                         "with --vectors blender or nuke")
    if args.anchor != "center":
        raise InputError(f"--anchor {args.anchor} applies to a straight path; a {args.path} "
                         "path is anchored at its bend (the frame time)")
    if alpha:
        raise InputError(f"--path {args.path} takes no alpha channel (use --alpha no, or "
                         "clblur blur-layers for RGBA layers)")


def _blur_whole(args: argparse.Namespace, alpha: bool) -> None:
    """Layered exposure and alpha: the whole image in memory, written atomically."""
    import clblur
    from clblur.io import exr_layout, read_depth, read_flow, read_image, write_image
    from clblur.io.flows import exr_part
    from clblur.layering import NAMED_ORDERS
    from clblur.tiling import parse_size

    image_file, layer = exr_part(args.input)
    layout = exr_layout(image_file, layer)  # None unless the image is an EXR
    motion = motion_from_args(args, bent=args.path != "straight",  # bent: the two halves
                              layout=layout)
    if isinstance(motion, str):
        motion = read_flow(motion)
    depth = args.depth  # None, a named ordering (computed from the flow) or a file
    if depth is not None and depth not in NAMED_ORDERS:
        depth_file = exr_part(depth)[0]
        depth = read_depth(depth)
        if layout is not None and depth_file.lower().endswith(".exr"):
            from clblur.io.exr import align

            depth = align(depth, depth_file, layout, "depth")
        if args.inverse_depth:
            depth = _distance(depth, depth_file)

    image = read_image(image_file, max_bytes=parse_size(args.memory_budget), layer=layer)
    if image.dtype.kind == "f" and not args.output.lower().endswith((".tif", ".tiff", ".exr")):
        raise InputError(f"{args.output} cannot hold float images; write .tif, .tiff or .exr")
    if args.path == "straight":
        out = clblur.blur(image, motion, **blur_options(args), depth=depth, alpha=alpha)
    else:
        from clblur.vectors import blur_bent

        options = blur_options(args)
        del options["anchor"]  # the bend (_check_path)
        out = blur_bent(image, *motion, **options, layers=depth is not None, depth=depth,
                        curved=args.path == "curved")
    write_image(args.output, out, layout=layout)


def _distance(inverse, path: str):
    """Distance from a 1 / distance depth (``--inverse-depth``): 0 is infinitely far."""
    import numpy as np

    inverse = np.asarray(inverse, np.float64)
    if np.any(inverse < 0):
        raise InputError(f"--inverse-depth: {path} holds negative values; 1 / distance is "
                         "never below 0")
    with np.errstate(divide="ignore"):
        return np.where(inverse > 0, 1.0 / np.where(inverse > 0, inverse, 1.0), np.inf)
