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
    default_response,
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
    p.add_argument("--overscan", type=int, default=None, metavar="PX",
                   help="pixels by which the layers extend beyond the output on every side "
                        "(default: what EXR layers' data and display windows say, else 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import clblur
    from clblur.io import IMAGE_FORMATS, check_output, exr_layout, read_image, write_image
    from clblur.io.flows import exr_part
    from clblur.vectors import load_flow

    paths = [exr_part(p)[0] for pair in args.layer for p in pair]
    check_output(args.output, *paths, suffixes=tuple(IMAGE_FORMATS))
    default_response(args, exr_part(args.layer[0][0])[0])
    check_response(args.response)
    check_device(args)
    check_vector_options(args)
    bent = args.path != "straight"
    if bent and args.vectors == "clblur":
        raise InputError(f"--path {args.path} needs a renderer's vector pass: give --vectors "
                         "blender or nuke")
    layers = []
    layout = None  # the first layer's EXR layout: every EXR layer's pixels must share it
    for image_path, vector_path in args.layer:
        image_file, image_layer = exr_part(image_path)
        # one layer of a multilayer EXR, e.g. render.exr:Ball.Combined
        image = read_image(image_file, layer=image_layer)
        if image.ndim == 3 and image.shape[2] not in (1, 2, 3, 4):
            raise InputError(f"layer {image_path}: expected grey or RGB, with or without "
                             f"alpha, got {image.shape[2]} channels")
        own = exr_layout(image_file, image_layer)
        layout = layout or own
        if own is not None and own.data_window != layout.data_window:
            from clblur.io.exr import describe_window

            raise InputError(f"layer {image_path}: its data window "
                             f"{describe_window(own.data_window)} is not the first layer's "
                             f"{describe_window(layout.data_window)}")
        vector_file, vector_layer = exr_part(vector_path)
        flow = load_flow(vector_file, args.vectors, args.vector_shutter, bent=bent,
                         layer=vector_layer)
        if own is not None and vector_file.lower().endswith(".exr"):
            from clblur.io.exr import align

            flow = tuple(align(f, vector_file, own, "vectors") for f in flow) if bent else \
                align(flow, vector_file, own, "vectors")
        layers.append((image, flow))
    overscan = _overscan(args.overscan, layout)
    if layers[0][0].dtype.kind == "f" and not args.output.lower().endswith(
            (".tif", ".tiff", ".exr")):
        raise InputError(f"{args.output} cannot hold float images; write .tif, .tiff or .exr")
    out = clblur.blur_layers(layers, **blur_options(args), overscan=overscan,
                             curved=args.path == "curved")
    write_image(args.output, out, layout=_cut(layout, overscan))
    print(f"wrote {args.output}")
    return 0


def _overscan(given: int | None, layout) -> int:
    """``--overscan``, or what EXR layers' windows say: how far their data window reaches
    beyond their display window (``clblur.io.exr.Layout.overscan``).  Where the windows
    state an overscan a different value is refused; where they state none (the overscan
    stored as picture, as some writers do) the option says it."""
    stated = 0 if layout is None else layout.overscan()
    if given is None:
        return stated
    if stated and given != stated:
        raise InputError(f"--overscan {given}: the layers' data window reaches {stated} px "
                         "beyond their display window on every side (their EXR windows say "
                         "it; leave --overscan out)")
    return given


def _cut(layout, overscan: int):
    """The output's EXR layout: the layers' less the overscan; where their windows did not
    state it, the picture left is the display window too."""
    if layout is None:
        return None
    from dataclasses import replace

    cut = layout.inset(overscan)
    return cut if layout.overscan() else replace(cut, display_window=cut.data_window)
