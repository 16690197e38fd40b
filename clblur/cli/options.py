"""Options shared by several commands, and their conversion to library arguments.

Every option declaration a command shares lives here; a command's own options sit in its
module's ``register``.
"""

from __future__ import annotations

import argparse
import math

from clblur.blur import BACKENDS
from clblur.errors import InputError
from clblur.motion import ANCHORS, EXPOSURES

__all__ = ["add_backend_options", "add_blur_options", "add_exposure_option", "default_response",
           "add_memory_option", "add_motion_options", "add_series_options",
           "add_vector_options", "blur_options", "check_device", "check_response",
           "check_vector_options", "motion_from_args", "parse_vector"]


def parse_vector(text: str, option: str = "--motion") -> tuple[float, float]:
    """``"DX,DY"`` -> (dx, dy), finite."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        v = float(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(f"{option} must be DX,DY in pixels (e.g. 12,-3), got {text!r}") from None
    if not all(map(_finite, v)):
        raise InputError(f"{option} must be finite, got {text!r}")
    return v


def _finite(x: float) -> bool:
    return x == x and abs(x) != float("inf")


def add_blur_options(p: argparse.ArgumentParser) -> None:
    """Options shared by every command that blurs (blur, blur-layers, batch).  The response
    defaults to the input's (:func:`default_response`: ``linear`` for an EXR, else ``exp``)."""
    p.add_argument("--response", default=None, metavar="SPEC",
                   help="linear, exp, exp:K, gamma:G, srgb, or a response JSON file "
                        "(default: linear for an EXR input, which holds scene-linear light, "
                        "else exp, the paper's Eq. 3)")
    p.add_argument("--anchor", choices=list(ANCHORS), default="center",
                   help="shutter time the static image shows (default: center)")
    p.add_argument("--samples", type=int, default=None, metavar="N",
                   help="samples per pixel (default: ceil(|v|)+1 per pixel)")
    add_exposure_option(p)
    p.add_argument("--saturation", type=float, default=1.0, metavar="S",
                   help="exposure of clipped pixels, in units of the least saturating "
                        "exposure (>= 1, default 1)")
    add_backend_options(p)


def add_exposure_option(p: argparse.ArgumentParser) -> None:
    """--exposure: how the samples along a vector are weighted (``clblur.motion``)."""
    p.add_argument("--exposure", choices=list(EXPOSURES), default="frames",
                   help="frames: each sample alike, the paper's Eq. 9 and a mean of video "
                        "frames (default); continuous: the vector is a continuous "
                        "exposure's chord (a renderer's vectors, a real shutter): the "
                        "trapezoid rule")


def add_backend_options(p: argparse.ArgumentParser) -> None:
    """--backend and --device, for every command that runs the blur kernels."""
    p.add_argument("--backend", choices=list(BACKENDS), default="auto",
                   help="auto: OpenCL when a device works, else numpy (default: auto)")
    p.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' indices or a name substring (default: "
                        "$CLBLUR_DEVICE, else the first usable device); a named device that "
                        "does not work is an error")


def add_series_options(p: argparse.ArgumentParser, only: str = "") -> None:
    """--times and --no-align: how an exposure series is read (calibrate, study); ``only``
    names the inputs they apply to, where the command takes other kinds too."""
    p.add_argument("--times", metavar="FILE",
                   help="exposure times for a folder: one per line in file-name order, or "
                        "'NAME TIME' lines; fractions like 1/1024 allowed, or stop offsets "
                        "like +2EV; an HDRShop image list (Debevec's stacks) also works "
                        "(default: EXIF ExposureTime, FNumber, and ISO where it varies)")
    p.add_argument("--no-align", action="store_true",
                   help=f"{only}take the images as they are; by default the whole-pixel "
                        "shift and the turn between exposures (a hand-held bracket) are "
                        "measured and the images cropped to the window all of them cover")


def add_memory_option(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--memory-budget", default=None, metavar="SIZE",
                   help=f"{what}, e.g. 2G or 500M (default 512M; TIFFs are tiled, other "
                        "formats must fit whole)")


def add_motion_options(p: argparse.ArgumentParser, required: bool) -> None:
    g = p.add_mutually_exclusive_group(required=required)
    g.add_argument("--motion", metavar="DX,DY",
                   help="one displacement in pixels, x right, y down (negative values: "
                        "--motion=-5,2)")
    g.add_argument("--flow", metavar="FILE", help="per-pixel motion: .npy (H x W x 2) or .flo")
    g.add_argument("--psf", metavar="FILE", help="blur kernel image or .npy (normalised)")


VECTOR_SHUTTER = 0.5  # frames: a 180-degree shutter


def add_vector_options(p: argparse.ArgumentParser, what: str) -> None:
    """--vectors and --vector-shutter: the convention of the vector files ``what`` names."""
    p.add_argument("--vectors", choices=["clblur", "blender", "nuke"], default="clblur",
                   help=f"convention of {what}: clblur (displacement over the exposure, "
                        "default), blender (Vector pass X,Y,Z,W) or nuke (forward/backward "
                        "u,v); see docs/model.md")
    p.add_argument("--vector-shutter", type=float, default=VECTOR_SHUTTER, metavar="FRAMES",
                   help="with --vectors blender|nuke: centred shutter in frames (default "
                        f"{VECTOR_SHUTTER}, i.e. 180 degrees)")


def check_vector_options(args: argparse.Namespace, vector_files: bool = True) -> None:
    """--vectors and --vector-shutter only where they apply: a renderer's convention needs
    vector files (``vector_files``: the command was given some), a shutter needs that
    convention; an option that would be ignored is an error, not a silent default."""
    if args.vectors != "clblur" and not vector_files:
        raise InputError(f"--vectors {args.vectors} describes a --flow vector pass, and no "
                         "--flow was given")
    if args.vector_shutter != VECTOR_SHUTTER:
        if args.vectors == "clblur":
            raise InputError("--vector-shutter applies with --vectors blender or nuke (clblur "
                             "vectors are already the displacement over the exposure)")
        if not (math.isfinite(args.vector_shutter) and args.vector_shutter > 0):
            raise InputError(f"--vector-shutter must be a positive number of frames, got "
                             f"{args.vector_shutter}")


PATHS = ("straight", "bent", "curved")


def add_path_option(p: argparse.ArgumentParser) -> None:
    """--path: how a renderer's vector pass is followed over the shutter."""
    p.add_argument("--path", choices=list(PATHS), default="straight",
                   help="with --vectors blender|nuke: the exposure chord (straight, default), "
                        "the two halves about the frame time (bent), or the parabola through "
                        "their three points (curved)")


def motion_from_args(args: argparse.Namespace, bent: bool = False, layout=None) -> object:
    """The motion a blur command asked for; a flow stays a path so big ones can be mapped.
    ``bent``: a renderer's vector pass as its two halves about the frame time (``--path
    bent|curved``; `clblur blur` checks first that a pass was given).  ``--flow
    FILE.exr:LAYER`` names a Blender view layer's vector pass.  ``layout``: an EXR image's
    (``clblur.io.exr.Layout``): an EXR flow or vector file is then read and its pixels put
    on the image's data window (``clblur.io.exr.align``)."""
    from clblur.io import read_psf
    from clblur.io.flows import exr_part

    if args.motion is not None:
        return parse_vector(args.motion)
    if args.flow is not None:
        path, layer = exr_part(args.flow)
        on_image = layout is not None and path.lower().endswith(".exr")
        if getattr(args, "vectors", "clblur") != "clblur" or layer is not None:
            from clblur.vectors import load_flow

            motion = load_flow(path, getattr(args, "vectors", "clblur"),
                               getattr(args, "vector_shutter", 0.5), bent=bent, layer=layer)
        elif on_image:
            from clblur.io import read_flow

            motion = read_flow(path)
        else:
            return path
        if on_image:
            from clblur.io.exr import align

            what = "flow" if getattr(args, "vectors", "clblur") == "clblur" else "vectors"
            motion = tuple(align(m, path, layout, what) for m in motion) if bent else \
                align(motion, path, layout, what)
        return motion
    return read_psf(args.psf)


def check_device(args: argparse.Namespace) -> None:
    """An explicitly named device (``--device``) must exist and work: no silent fallback."""
    device = getattr(args, "device", None)
    if device is None or getattr(args, "backend", "auto") == "numpy":
        return
    try:
        from clblur import opencl
    except ImportError as e:
        raise InputError(f"--device {device}: the OpenCL backend is unavailable ({e})") from None
    ok, why = opencl.usable(device)
    if not ok:
        raise InputError(f"--device {device}: {why} (`clblur info` lists the devices)")


def check_response(spec: str, option: str = "--response", channels: int | None = None) -> None:
    """Parse a response spec before any work, naming the option in the message.
    ``channels``: the image's colour channels where known (``clblur.responses.check_spec``)."""
    from clblur.responses import check_spec

    try:
        check_spec(spec, channels)
    except InputError as e:
        raise InputError(str(e) if spec in str(e) else f"{option} {spec}: {e}") from None


def default_response(args: argparse.Namespace, image_file: str) -> None:
    """Set ``--response`` where it was left out, by the input's format
    (``clblur.io.response_for_file``: ``linear`` for an EXR, else ``exp``)."""
    from clblur.io import response_for_file

    if args.response is None:
        args.response = response_for_file(image_file)


def blur_options(args: argparse.Namespace) -> dict:
    """The library keyword arguments of the shared blur options."""
    return dict(response=args.response, anchor=args.anchor, samples=args.samples,
                backend=args.backend, saturation=args.saturation, device=args.device,
                exposure=args.exposure)
