"""``clblur blur`` and ``clblur info``."""

from __future__ import annotations

import argparse
import platform

import numpy as np

from clblur.blur import BACKENDS
from clblur.motion import ANCHORS


def parse_vector(text: str) -> tuple[float, float]:
    """``"DX,DY"`` -> (dx, dy)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f"--motion must be DX,DY in pixels (e.g. 12,-3), got {text!r}") from None


def add_blur_options(p: argparse.ArgumentParser) -> None:
    """Options shared by every command that blurs (blur, batch, video)."""
    p.add_argument("--response", default="exp", metavar="SPEC",
                   help="linear, exp, exp:K, gamma:G, srgb, or a response JSON file "
                        "(default: exp, the paper's Eq. 3)")
    p.add_argument("--anchor", choices=list(ANCHORS), default="center",
                   help="shutter time the static image shows (default: center)")
    p.add_argument("--samples", type=int, default=None, metavar="N",
                   help="samples per pixel (default: ceil(|v|)+1 per pixel)")
    p.add_argument("--saturation", type=float, default=1.0, metavar="S",
                   help="exposure of clipped pixels, in units of the least saturating "
                        "exposure (>= 1, default 1)")
    add_backend_options(p)


def add_backend_options(p: argparse.ArgumentParser) -> None:
    """--backend and --device, for every command that runs the blur kernels."""
    p.add_argument("--backend", choices=list(BACKENDS), default="auto",
                   help="auto: OpenCL when a device works, else numpy (default: auto)")
    p.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' indices or a name substring (default: "
                        "$CLBLUR_DEVICE, else the first usable device)")


def add_motion_options(p: argparse.ArgumentParser, required: bool) -> None:
    g = p.add_mutually_exclusive_group(required=required)
    g.add_argument("--motion", metavar="DX,DY",
                   help="one displacement in pixels, x right, y down (negative values: "
                        "--motion=-5,2)")
    g.add_argument("--flow", metavar="FILE", help="per-pixel motion: .npy (H x W x 2) or .flo")
    g.add_argument("--psf", metavar="FILE", help="blur kernel image or .npy (normalised)")


def motion_from_args(args) -> object:
    """The motion a blur command asked for; a flow stays a path so big ones can be mapped."""
    from clblur.io import read_psf

    if args.motion is not None:
        return parse_vector(args.motion)
    if args.flow is not None:
        if getattr(args, "vectors", "clblur") != "clblur":  # a renderer's vector pass
            from clblur.vectors import load_flow

            return load_flow(args.flow, args.vectors, args.vector_shutter)
        return args.flow
    return read_psf(args.psf)


def blur_options(args) -> dict:
    return dict(response=args.response, anchor=args.anchor, samples=args.samples,
                backend=args.backend, saturation=args.saturation, device=args.device)


def cmd_blur(args) -> int:
    from clblur.io import refuse_overwrite
    from clblur.tiling import blur_file, open_image

    refuse_overwrite(args.output, args.input, args.flow, args.psf, args.depth)
    channels = (tuple(open_image(args.input).shape) + (1,))[2]
    alpha = args.alpha == "yes" or (args.alpha == "auto" and channels in (2, 4))
    if args.depth is not None or alpha:
        _blur_whole(args, alpha)  # layered exposure and alpha need the whole image
    else:
        blur_file(args.input, args.output, motion_from_args(args), **blur_options(args),
                  memory_budget=args.memory_budget, progress=True)
    print(f"wrote {args.output}")
    return 0


def read_depth(path: str) -> np.ndarray:
    """A depth map or layer IDs, H x W, from a ``.npy`` file, or a channel of an EXR file
    (``FILE.exr`` finds ``Z``/``depth.Z``/``<layer>.Depth.Z``; ``FILE.exr:CHANNEL`` names it)."""
    head, sep, channel = path.rpartition(":")
    if sep and head.lower().endswith(".exr"):
        from clblur.exr import read_depth as read_exr_depth

        return read_exr_depth(head, channel)
    if path.lower().endswith(".exr"):
        from clblur.exr import read_depth as read_exr_depth

        return read_exr_depth(path)
    if not path.lower().endswith(".npy"):
        raise ValueError(f"--depth must be a .npy file (H x W) or an EXR depth channel "
                         f"(FILE.exr or FILE.exr:CHANNEL), got {path}")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot read depth {path}: {e}") from None


def _blur_whole(args, alpha: bool) -> None:
    import clblur
    from clblur.io import read_flow, read_image, write_image

    motion = motion_from_args(args)
    if isinstance(motion, str):
        motion = read_flow(motion)
    depth = read_depth(args.depth) if args.depth is not None else None
    image = read_image(args.input)
    if image.dtype.kind == "f" and not args.output.lower().endswith((".tif", ".tiff", ".exr")):
        raise ValueError(f"{args.output} cannot hold float images; write .tif or .tiff instead")
    out = clblur.blur(image, motion, **blur_options(args), depth=depth,
                      alpha=alpha)
    write_image(args.output, out)


def cmd_info(args) -> int:
    import clblur

    print(f"clblur {clblur.__version__}  python {platform.python_version()}  "
          f"numpy {np.__version__}")
    try:
        import pyopencl

        print(f"pyopencl {pyopencl.VERSION_TEXT}")
    except ImportError as e:
        print(f"pyopencl: not importable ({e})")
        return 0
    from clblur import opencl

    found = opencl.devices()
    if not found:
        print("OpenCL devices: none found")
    for d in found:
        state = "builds and runs kernels" if d["works"] else f"UNUSABLE: {d['error']}"
        print(f"[{d['index']}] {d['platform']} / {d['device']} ({d['type']}, {d['version']}, "
              f"fp64={'yes' if d['fp64'] else 'no'}): {state}")
    ok, why = opencl.usable(None)
    print(f"default device: {opencl.current_device() if ok else 'none (' + why + ')'}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("blur", help="blur an image along a motion, flow field or PSF",
                       description="Photo-consistent motion blur of one image. Large TIFF "
                                   "images are processed in tiles within --memory-budget.")
    p.add_argument("input")
    p.add_argument("output")
    add_motion_options(p, required=True)
    add_blur_options(p)
    p.add_argument("--memory-budget", default=None, metavar="SIZE",
                   help="bound memory use, e.g. 2G or 500M (tiles big images)")
    p.add_argument("--vectors", choices=["clblur", "blender", "nuke"], default="clblur",
                   help="convention of --flow: clblur (displacement over the exposure, "
                        "default), blender (Vector pass X,Y,Z,W) or nuke (forward/backward "
                        "u,v); see docs/model.md")
    p.add_argument("--vector-shutter", type=float, default=0.5, metavar="FRAMES",
                   help="with --vectors blender|nuke: centred shutter in frames (default 0.5, "
                        "i.e. 180 degrees)")
    p.add_argument("--depth", default=None, metavar="FILE",
                   help="occlusion order, H x W .npy or EXR depth (FILE.exr[:CHANNEL]; smaller "
                        "= nearer; integers: layer IDs): "
                        "layered exposure, moving objects smear over what is behind them")
    p.add_argument("--alpha", choices=("auto", "yes", "no"), default="auto",
                   help="the last channel is coverage, blurred linearly with colour "
                        "premultiplied in linear light (auto: 2- and 4-channel images)")
    p.set_defaults(func=cmd_blur)
    p = sub.add_parser("info", help="versions and OpenCL devices")
    p.set_defaults(func=cmd_info)
