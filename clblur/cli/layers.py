"""``clblur blur-layers OUT --layer IMAGE VECTORS ...``: a multi-layer render, front to back."""

from __future__ import annotations

import argparse

from clblur.cli.options import (
    add_blur_options,
    add_path_option,
    add_vector_options,
    blur_options,
    check_device,
    check_response,
    check_vector_options,
)
from clblur.errors import InputError

__all__ = ["register", "run"]


def register(sub) -> None:
    p = sub.add_parser(
        "blur-layers", help="blur a multi-layer render: each layer with its own vectors",
        description="Motion blur of a multi-layer render (clblur.blur_layers): every layer "
                    "(an RGBA image: straight alpha for 8/16-bit files, premultiplied for "
                    "float) moves along its own vectors and the layers occlude each other "
                    "front to back at every shutter sample, in linear light.")
    p.add_argument("output")
    p.add_argument("--layer", nargs=2, action="append", required=True,
                   metavar=("IMAGE", "VECTORS"),
                   help="one layer, nearest first (repeat the option): an image with alpha "
                        "(without alpha: opaque, e.g. the background) and its vectors (.npy "
                        "H x W x 2, .flo or EXR, in the --vectors convention); in a multilayer "
                        "EXR, FILE.exr:PREFIX names a layer (image: PREFIX.R/G/B/A, e.g. "
                        "Ball.Combined; vectors: PREFIX.Vector.X/Y/Z/W with --vectors blender)")
    add_blur_options(p)
    add_vector_options(p, "the layers' vector files")
    add_path_option(p)
    p.add_argument("--overscan", type=int, default=0, metavar="PX",
                   help="pixels by which the layers extend beyond the output on every side "
                        "(default 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import clblur
    from clblur.io import IMAGE_FORMATS, check_output, read_image, write_image
    from clblur.io.flows import depth_source as exr_part
    from clblur.vectors import load_flow

    paths = [exr_part(p)[0] for pair in args.layer for p in pair]
    check_output(args.output, *paths, suffixes=tuple(IMAGE_FORMATS))
    check_response(args.response)
    check_device(args)
    check_vector_options(args)
    bent = args.path != "straight"
    if bent and args.vectors == "clblur":
        raise InputError(f"--path {args.path} needs a renderer's vector pass: give --vectors "
                         "blender or nuke")
    layers = []
    for image_path, vector_path in args.layer:
        image_file, image_layer = exr_part(image_path)
        if image_layer is None:
            image = read_image(image_file)
        else:  # one layer of a multilayer EXR, e.g. render.exr:Ball.Combined
            from clblur.io import exr

            image = exr.read_image(image_file, image_layer)
        if image.ndim == 3 and image.shape[2] not in (1, 2, 3, 4):
            raise InputError(f"layer {image_path}: expected grey or RGB, with or without "
                             f"alpha, got {image.shape[2]} channels")
        vector_file, vector_layer = exr_part(vector_path)
        flow = load_flow(vector_file, args.vectors, args.vector_shutter, bent=bent,
                         layer=vector_layer)
        layers.append((image, flow))
    if layers[0][0].dtype.kind == "f" and not args.output.lower().endswith(
            (".tif", ".tiff", ".exr")):
        raise InputError(f"{args.output} cannot hold float images; write .tif, .tiff or .exr")
    out = clblur.blur_layers(layers, **blur_options(args), overscan=args.overscan,
                             curved=args.path == "curved")
    write_image(args.output, out)
    print(f"wrote {args.output}")
    return 0
