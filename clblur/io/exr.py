"""OpenEXR files: linear multi-channel images with alpha, depth and motion-vector channels.

Reads and writes through the ``OpenEXR`` Python bindings (>= 3.3, numpy arrays; the Academy
Software Foundation's package on PyPI), imported lazily so clblur works without them except
for ``.exr`` files.

Conventions
-----------
* Pixel values are linear (scene-referred) float32, as EXR stores them; blur them with the
  ``linear`` response (``clblur blur --response linear``), which passes values above 1
  through untouched.  float16 channels are read as float32; ``half=True`` writes float16.
* Colour channels: ``R, G, B`` (and ``A``), or ``Y`` (and ``A``) for one channel, optionally
  under a layer prefix (``"beauty"`` -> ``beauty.R``; Blender multilayer files use
  ``"RenderLayer.Combined"``); a ``Y`` beside ``X`` or ``Z`` is a vector or normal pass, not
  luminance.  ``read_image`` returns H x W x C (C = 1 (as H x W), 2, 3 or 4) in R, G, B, A
  order, and ``write_image`` takes the same.
* Alpha is stored as given; clblur treats RGBA as premultiplied (coverage-weighted linear
  colour), the EXR convention.
* Depth: a ``Z`` channel (``depth.Z``, Blender's ``<layer>.Depth.Z`` are found too); smaller
  is nearer, in whatever unit the renderer wrote (Blender: distance in scene units).
* clblur's own flow (displacement over the exposure, x right, y down, pixels) is stored as
  ``flow.x`` / ``flow.y``.  Renderers' vector passes (Blender ``Vector.X/Y/Z/W``, Nuke
  ``forward.u/v`` and ``backward.u/v``) are read as stored; ``clblur.vectors`` converts them.
* Files are written to a temporary file beside the target and renamed (``clblur.io``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io.paths import require_file

__all__ = ["probe", "read_channels", "write_channels", "read_image", "write_image", "read_depth",
           "read_flow", "write_flow", "find_channels", "FLOW_CHANNELS"]

FLOW_CHANNELS = ("flow.x", "flow.y")
_COLOUR = ("R", "G", "B", "A")


def _openexr():
    try:
        import OpenEXR
    except ImportError:
        raise InputError("reading or writing .exr needs the OpenEXR package: "
                         "pip install 'OpenEXR>=3.3' (or clblur[exr])") from None
    return OpenEXR


def probe(path: str | os.PathLike) -> tuple[int, int, int, int]:
    """``(height, width, colour channels, bytes per sample)`` from the header alone."""
    exr = _openexr()
    try:
        with exr.File(str(path), header_only=True) as f:
            header = f.header()
        if "dataWindow" in header:
            (x0, y0), (x1, y1) = (tuple(int(v) for v in c) for c in header["dataWindow"])
            names = [c.name for c in header.get("channels", [])]
        else:  # some writers' headers come back without it: read the channels instead
            chans = read_channels(path)
            names = list(chans)
            (y1, x1), x0, y0 = next(iter(chans.values())).shape, 1, 1
    except Exception as e:  # the bindings raise several types for corrupt files
        raise InputError(f"cannot read EXR {path}: {e}".splitlines()[0]) from None
    colour = find_channels(names)[1] if names else ["Y"]
    return y1 - y0 + 1, x1 - x0 + 1, len(colour), 4


def read_channels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every channel of the first part of an EXR file, by name, as H x W float32 arrays
    (UINT channels, e.g. object IDs, stay uint32)."""
    exr = _openexr()
    path = Path(path)
    require_file(path, "EXR")
    try:
        with exr.File(str(path), separate_channels=True) as f:
            chans = {name: np.array(c.pixels) for name, c in f.channels().items()}
    except Exception as e:  # the bindings raise several types for corrupt files
        raise InputError(f"cannot read EXR {path}: {e}") from None
    return {k: (v if v.dtype == np.uint32 else v.astype(np.float32)) for k, v in chans.items()}


def write_channels(path: str | os.PathLike, channels: dict[str, np.ndarray], *,
                   half: bool | set[str] = False, compression: str = "zip") -> None:
    """Write named H x W channels to one EXR file, atomically.

    ``half``: True writes every float channel as float16, a set names the ones to write as
    float16 (colour usually; depth and vectors keep float32 precision).  ``compression``:
    ``none``, ``zip``, ``piz``, ``zips``, ``rle``.
    """
    from clblur.io.atomic import atomic_write

    exr = _openexr()
    if not channels:
        raise InputError("no channels to write")
    comp = {"none": exr.NO_COMPRESSION, "zip": exr.ZIP_COMPRESSION, "zips": exr.ZIPS_COMPRESSION,
            "piz": exr.PIZ_COMPRESSION, "rle": exr.RLE_COMPRESSION}.get(compression)
    if comp is None:
        raise InputError(f"unknown EXR compression {compression!r}")
    shape = None
    out = {}
    for name, a in channels.items():
        a = np.asarray(a)
        if a.ndim != 2:
            raise InputError(f"EXR channel {name!r} must be H x W, got shape {a.shape}")
        if shape is not None and a.shape != shape:
            raise InputError(f"EXR channel {name!r} has shape {a.shape}, the others {shape}")
        shape = a.shape
        if a.dtype.kind in "ui" and a.dtype != np.uint32:
            if a.min(initial=0) < 0:
                raise InputError(f"EXR channel {name!r}: negative integers cannot be stored")
            a = a.astype(np.uint32)
        elif a.dtype.kind == "f" or a.dtype == np.bool_:
            to_half = half is True or (isinstance(half, set) and name in half)
            a = a.astype(np.float16 if to_half else np.float32)
        elif a.dtype != np.uint32:
            raise InputError(f"EXR channel {name!r}: unsupported dtype {a.dtype}")
        out[name] = np.ascontiguousarray(a)
    header = {"compression": comp, "type": exr.scanlineimage}

    def write(tmp: Path) -> None:
        with exr.File(header, out) as f:
            f.write(str(tmp))

    atomic_write(path, write)


def find_channels(names, layer: str | None = None) -> tuple[str, list[str]]:
    """The colour layer of a channel list: ``(prefix, channel names in R, G, B, A order)``.

    ``layer`` given: ``<layer>.R`` ... (or ``R`` ... for ``""``).  Otherwise the unprefixed
    ``R, G, B[, A]`` or ``Y``, else the only prefix that has ``R, G, B``."""
    names = list(names)

    def colour(prefix: str) -> list[str] | None:
        p = f"{prefix}." if prefix else ""
        if all(p + c in names for c in "RGB"):
            return [p + c for c in _COLOUR if p + c in names]
        # Y is luminance unless X or Z sit beside it: Blender's Vector (X, Y, Z, W) and
        # Normal (X, Y, Z) passes are not colour
        if p + "Y" in names and not any(p + c in names for c in "XZ"):
            return [p + "Y"] + ([p + "A"] if p + "A" in names else [])
        return None

    if layer is not None:
        got = colour(layer)
        if got is None:
            raise InputError(f"EXR has no colour layer {layer!r} (channels: {', '.join(names)})")
        return layer, got
    got = colour("")
    if got is not None:
        return "", got
    prefixes = sorted({n.rsplit(".", 1)[0] for n in names if "." in n})
    found = [p for p in prefixes if colour(p) is not None]
    if len(found) == 1:
        return found[0], colour(found[0])
    if not found:
        raise InputError(f"EXR has no R, G, B or Y channels (channels: {', '.join(names)})")
    raise InputError(f"EXR has several colour layers ({', '.join(found)}); name one")


def read_image(path: str | os.PathLike, layer: str | None = None) -> np.ndarray:
    """The colour layer as float32: H x W (Y), H x W x 2 (Y, A), x 3 (RGB) or x 4 (RGBA)."""
    chans = read_channels(path)
    _, names = find_channels(chans, layer)
    if len(names) == 1:
        return chans[names[0]]
    return np.stack([chans[n] for n in names], axis=-1).astype(np.float32)


def write_image(path: str | os.PathLike, image: np.ndarray, *, half: bool = False,
                extra: dict[str, np.ndarray] | None = None) -> None:
    """Write an H x W (``Y``), H x W x 2 (``Y``, ``A``), H x W x 3 (``RGB``) or H x W x 4
    (``RGBA``) image (what ``read_image`` returns), plus
    ``extra`` named channels (depth ``Z``, ``flow.x``/``flow.y``, vector passes, IDs).

    Integer images are written as normalised values (code / Imax), i.e. the stored code
    values, not linearised: EXR holds floats, and the file says nothing about the response.
    ``half`` applies to the colour channels only."""
    from clblur.pixels import normalise

    img = np.asarray(image)
    if img.dtype.kind in "ui":
        img = normalise(img)
    if img.ndim == 2:
        names = ["Y"]
        planes = [img]
    elif img.ndim == 3 and img.shape[2] in (1, 2, 3, 4):
        names = {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}[
            img.shape[2]]
        planes = [img[..., c] for c in range(img.shape[2])]
    else:
        raise InputError(f"cannot write an image of shape {img.shape} to EXR; expected "
                         "H x W, H x W x 2 (Y, A), H x W x 3 or H x W x 4")
    channels = dict(zip(names, planes, strict=True))
    for k, v in (extra or {}).items():
        if k in channels:
            raise InputError(f"extra channel {k!r} clashes with a colour channel")
        channels[k] = v
    write_channels(path, channels, half=set(names) if half else False)


def read_depth(path: str | os.PathLike, channel: str | None = None) -> np.ndarray:
    """A depth channel as H x W float32: ``channel`` if given, else ``Z``, ``depth.Z``,
    ``depth`` or the only channel whose name ends in ``.Z`` under a ``Depth`` layer."""
    chans = read_channels(path)
    if channel is not None:
        if channel not in chans:
            raise InputError(f"{path} has no channel {channel!r} (channels: "
                             f"{', '.join(chans)})")
        return chans[channel].astype(np.float32)
    for name in ("Z", "depth.Z", "depth", "Depth.Z"):
        if name in chans:
            return chans[name].astype(np.float32)
    cands = [n for n in chans if n.endswith(".Depth.Z")]
    if len(cands) == 1:
        return chans[cands[0]].astype(np.float32)
    raise InputError(f"{path} has no depth channel (Z, depth.Z, <layer>.Depth.Z); channels: "
                     f"{', '.join(chans)}")


def read_flow(path: str | os.PathLike) -> np.ndarray:
    """clblur's flow (``flow.x``, ``flow.y``) as H x W x 2 float32.  Renderer vector passes
    need a convention: see ``clblur.vectors.read_vectors``."""
    chans = read_channels(path)
    if not all(c in chans for c in FLOW_CHANNELS):
        raise InputError(f"{path} has no flow.x/flow.y channels (channels: "
                         f"{', '.join(chans)}); for a renderer's vector pass pass its "
                         "convention (--vectors blender|nuke)")
    return np.stack([chans[c] for c in FLOW_CHANNELS], axis=-1).astype(np.float32)


def write_flow(path: str | os.PathLike, flow: np.ndarray) -> None:
    """Write clblur's flow as the ``flow.x``/``flow.y`` channels of an EXR file."""
    f = np.asarray(flow, np.float32)
    if f.ndim != 3 or f.shape[2] != 2:
        raise InputError(f"flow has shape {f.shape}, expected H x W x 2")
    write_channels(path, {FLOW_CHANNELS[0]: f[..., 0], FLOW_CHANNELS[1]: f[..., 1]})
