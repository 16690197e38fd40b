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
  order, and ``write_image`` takes the same.  UINT colour channels (IDs) are refused.
* Windows: every reader returns the data window's pixels.  ``layout`` reads what an output
  keeps of an input (windows, pixel aspect ratio, screen window, line order, compression,
  float16 colour) and ``write_image(..., layout=...)`` writes it back; ``align`` puts a
  depth or vector file's pixels on the image's data window (cropped where it covers it,
  refused where it does not).
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

import contextlib
import functools
import io
import os
import sys
import tempfile
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io.paths import require_file

__all__ = ["FLOW_CHANNELS", "Layout", "align", "find_channels", "layout", "probe",
           "read_channels", "read_depth", "read_flow", "read_image", "write_channels",
           "write_flow", "write_image"]

FLOW_CHANNELS = ("flow.x", "flow.y")
_COLOUR = ("R", "G", "B", "A")


def _openexr():
    try:
        import OpenEXR
    except ImportError:
        raise InputError("reading or writing .exr needs the OpenEXR package: "
                         "pip install 'OpenEXR>=3.3' (or clblur[exr])") from None
    return OpenEXR


Window = tuple[int, int, int, int]  # (x0, y0, x1, y1), inclusive, as EXR states windows


@dataclass(frozen=True)
class Layout:
    """What an output keeps of an input EXR's header: its data window (where the pixels
    are) and display window (the picture's frame), pixel aspect ratio, screen window, line
    order, compression, and whether its colour channels are float16.

    The pixels a reader returns are the data window's: an overscan render (a data window
    beyond the display window) gives the blur real context at the frame's edges, and a
    bounding-box window keeps its place when written back with the same layout."""

    data_window: Window
    display_window: Window
    pixel_aspect: float = 1.0
    screen_center: tuple[float, float] = (0.0, 0.0)
    screen_width: float = 1.0
    line_order: object = None  # OpenEXR.LineOrder; None: the library's default
    compression: object = None  # OpenEXR.Compression; None: ZIP
    half: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the data window: the pixels' array shape."""
        x0, y0, x1, y1 = self.data_window
        return y1 - y0 + 1, x1 - x0 + 1

    def overscan(self) -> int:
        """How far the data window reaches beyond the display window on its narrowest side
        (0 where it does not on every side)."""
        (x0, y0, x1, y1), (d0, e0, d1, e1) = self.data_window, self.display_window
        return max(0, min(d0 - x0, e0 - y0, x1 - d1, y1 - e1))

    def inset(self, margin: int) -> Layout:
        """The layout of this one's pixels less ``margin`` on every side (an overscan cut)."""
        x0, y0, x1, y1 = self.data_window
        return replace(self, data_window=(x0 + margin, y0 + margin, x1 - margin, y1 - margin))


def _window(value) -> Window:
    (x0, y0), (x1, y1) = (tuple(int(v) for v in corner) for corner in value)
    return x0, y0, x1, y1


def describe_window(w: Window) -> str:
    return f"({w[0]}, {w[1]}) - ({w[2]}, {w[3]})"


def layout(path: str | os.PathLike, layer: str | None = None) -> Layout:
    """The :class:`Layout` of an EXR file (``layer``: the colour layer whose pixel type
    counts, as :func:`find_channels` picks it).  The bindings tell a channel's pixel type
    only with its pixels, so the file is read; a command asks more than once, so the answer
    is kept per file version (path, size, modification time)."""
    path = Path(path)
    require_file(path, "EXR")
    stat = path.stat()
    return _layout(str(path), stat.st_size, stat.st_mtime_ns, layer)


@functools.lru_cache(maxsize=32)
def _layout(path: str, size: int, mtime: int, layer: str | None) -> Layout:
    exr = _openexr()
    with _reading(path), exr.File(str(path), separate_channels=True) as f:
        header = dict(f.header())
        types = {name: c.pixels.dtype for name, c in f.channels().items()}
    data = _window(header["dataWindow"]) if "dataWindow" in header else None
    if data is None:  # some writers' headers come back without it: the pixels' extent
        h, w = next(iter(_read_pixels(Path(path)).values())).shape
        data = (0, 0, w - 1, h - 1)
    display = _window(header["displayWindow"]) if "displayWindow" in header else data
    try:
        colour = find_channels(types, layer, str(path))[1]
    except InputError:
        colour = []
    center = header.get("screenWindowCenter", (0.0, 0.0))
    return Layout(data, display, float(header.get("pixelAspectRatio", 1.0)),
                  (float(center[0]), float(center[1])),
                  float(header.get("screenWindowWidth", 1.0)), header.get("lineOrder"),
                  header.get("compression"),
                  bool(colour) and all(types[c] == np.float16 for c in colour))


def _data_window(path: str | os.PathLike) -> Window:
    """A file's data window from its header alone (from its pixels where the header comes
    back without one)."""
    exr = _openexr()
    require_file(Path(path), "EXR")
    with _reading(path), exr.File(str(path), header_only=True) as f:
        header = dict(f.header())
    if "dataWindow" in header:
        return _window(header["dataWindow"])
    h, w = next(iter(_read_pixels(Path(path)).values())).shape
    return 0, 0, w - 1, h - 1


def align(array: np.ndarray, path: str | os.PathLike, image: Layout, what: str) -> np.ndarray:
    """``array``, read from the EXR ``path``, on the image's data window: as it is where the
    two windows agree, cropped where the file's window covers the image's, else refused
    (the pixels are matched by their place in the picture, not by their array index)."""
    own = _data_window(path)
    want = image.data_window
    if own == want:
        return array
    x0, y0, x1, y1 = own
    if x0 <= want[0] and y0 <= want[1] and x1 >= want[2] and y1 >= want[3]:
        return array[want[1] - y0:want[3] - y0 + 1, want[0] - x0:want[2] - x0 + 1]
    raise InputError(f"{what} {path}: its data window {describe_window(own)} does not cover "
                     f"the image's {describe_window(want)}")


@contextlib.contextmanager
def _library_messages():
    """Collect what the OpenEXR library prints while reading: a corrupt file makes the C++
    library print its diagnosis on standard error (file descriptor 2, below Python) and the
    bindings a warning on standard output, before they raise; clblur's errors are one line.
    Yields a list that holds the lines (errors first) once the block is left.  Only on the
    main thread: the descriptors are the process's, and two threads swapping them would
    leave one pointing at the other's sink (worker threads' reads print as they are)."""
    lines: list[str] = []
    streams = ((sys.stderr, 2), (sys.stdout, 1))
    if threading.current_thread() is not threading.main_thread():
        yield lines
        return
    try:
        for stream, _ in streams:
            stream.flush()
        saved = [os.dup(fd) for _, fd in streams]
    except (OSError, ValueError, AttributeError):  # no usable descriptors (embedded Python)
        yield lines
        return
    printed = io.StringIO()  # the bindings print through sys.stdout, whatever it is
    with tempfile.TemporaryFile() as err, tempfile.TemporaryFile() as out, \
            contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        for sink, (_, fd) in zip((err, out), streams, strict=True):
            os.dup2(sink.fileno(), fd)
        try:
            yield lines
        finally:
            for (_, fd), keep, sink in zip(streams, saved, (err, out), strict=True):
                os.dup2(keep, fd)
                os.close(keep)
                sink.seek(0)
                lines += [ln for ln in sink.read().decode(errors="replace").splitlines()
                          if ln]
            lines += [ln for ln in printed.getvalue().splitlines() if ln]


def _read_error(path, e: Exception, messages: list[str] = ()) -> str:
    """One line for a file the bindings could not read: the library's own diagnosis where it
    printed one (its first line, without the file name it starts with), else the exception."""
    text = str(e).splitlines()[0] if str(e) else type(e).__name__
    if messages:
        text = messages[0].removeprefix(f"{path}: ").removeprefix(f"{Path(path).name}: ")
    return f"cannot read EXR {path}: {text}"


@contextlib.contextmanager
def _reading(path):
    """Read with the library's messages held (:func:`_library_messages`): on failure one
    ``InputError`` line; on success the messages are printed as they would have been."""
    with _library_messages() as messages:
        try:
            yield
        except InputError:
            raise
        except Exception as e:  # the bindings raise several types for corrupt files
            failure = e
        else:
            failure = None
    if failure is not None:
        raise InputError(_read_error(path, failure, messages)) from None
    for line in messages:
        print(line, file=sys.stderr)


def probe(path: str | os.PathLike, layer: str | None = None) -> tuple[int, int, int, int]:
    """``(height, width, colour channels, bytes per sample)`` from the header alone
    (``layer``: the colour layer, as :func:`find_channels` takes it)."""
    exr = _openexr()
    with _reading(path):
        with exr.File(str(path), header_only=True) as f:
            header = f.header()
            if "dataWindow" in header:
                (x0, y0), (x1, y1) = (tuple(int(v) for v in c) for c in header["dataWindow"])
                names = [c.name for c in header.get("channels", [])]
    if "dataWindow" not in header:  # some writers' headers come back without it
        chans = read_channels(path)
        names = list(chans)
        (y1, x1), x0, y0 = next(iter(chans.values())).shape, 1, 1
    colour = find_channels(names, layer, str(path))[1] if names else ["Y"]
    return y1 - y0 + 1, x1 - x0 + 1, len(colour), 4


def _read_pixels(path: Path) -> dict[str, np.ndarray]:
    exr = _openexr()
    require_file(path, "EXR")
    with _reading(path), exr.File(str(path), separate_channels=True) as f:
        chans = {name: np.array(c.pixels) for name, c in f.channels().items()}
    return chans


def read_channels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every channel of the first part of an EXR file, by name, as H x W float32 arrays
    (UINT channels, e.g. object IDs, stay uint32): the data window's pixels
    (:class:`Layout`)."""
    chans = _read_pixels(Path(path))
    return {k: (v if v.dtype == np.uint32 else v.astype(np.float32)) for k, v in chans.items()}


def write_channels(path: str | os.PathLike, channels: dict[str, np.ndarray], *,
                   half: bool | set[str] = False, compression: str | None = None,
                   layout: Layout | None = None) -> None:
    """Write named H x W channels to one EXR file, atomically.

    ``half``: True writes every float channel as float16, a set names the ones to write as
    float16 (colour usually; depth and vectors keep float32 precision).  ``compression``:
    ``none``, ``zip``, ``piz``, ``zips``, ``rle`` (default: the layout's, else ``zip``).
    ``layout``: the windows, pixel aspect ratio, screen window and line order to write (an
    input's, :func:`layout`); its data window must have the channels' shape.  Default: both
    windows at the origin, the channels' size.
    """
    from clblur.io.atomic import atomic_write

    exr = _openexr()
    if not channels:
        raise InputError("no channels to write")
    if compression is None:
        comp = layout.compression if layout is not None and layout.compression is not None \
            else exr.ZIP_COMPRESSION
    else:
        comp = {"none": exr.NO_COMPRESSION, "zip": exr.ZIP_COMPRESSION,
                "zips": exr.ZIPS_COMPRESSION, "piz": exr.PIZ_COMPRESSION,
                "rle": exr.RLE_COMPRESSION}.get(compression)
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
    if layout is not None:
        if layout.shape != shape:
            raise InputError(f"EXR layout: data window {describe_window(layout.data_window)} "
                             f"holds {layout.shape[1]} x {layout.shape[0]} pixels, the "
                             f"channels {shape[1]} x {shape[0]}")
        x0, y0, x1, y1 = layout.data_window
        d0, e0, d1, e1 = layout.display_window
        header.update({"dataWindow": (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32)),
                       "displayWindow": (np.array([d0, e0], np.int32),
                                         np.array([d1, e1], np.int32)),
                       "pixelAspectRatio": float(layout.pixel_aspect),
                       "screenWindowCenter": np.array(layout.screen_center, np.float32),
                       "screenWindowWidth": float(layout.screen_width)})
        if layout.line_order is not None:
            header["lineOrder"] = layout.line_order

    def write(tmp: Path) -> None:
        with exr.File(header, out) as f:
            f.write(str(tmp))

    atomic_write(path, write)


def find_channels(names, layer: str | None = None,
                  where: str = "EXR") -> tuple[str, list[str]]:
    """The colour layer of a channel list: ``(prefix, channel names in R, G, B, A order)``.

    ``layer`` given: ``<layer>.R`` ... (or ``R`` ... for ``""``).  Otherwise the unprefixed
    ``R, G, B[, A]`` or ``Y``, else the only prefix that has ``R, G, B``.  ``where``: the
    file, for messages."""
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
            raise InputError(f"{where} has no colour layer {layer!r} (channels: "
                             f"{', '.join(names)})")
        return layer, got
    got = colour("")
    if got is not None:
        return "", got
    prefixes = sorted({n.rsplit(".", 1)[0] for n in names if "." in n})
    found = [p for p in prefixes if colour(p) is not None]
    if len(found) == 1:
        return found[0], colour(found[0])
    if not found:
        raise InputError(f"{where} has no colour channels: R, G and B, or Y alone (channels: "
                         f"{', '.join(names)})")
    raise InputError(f"{where} has several colour layers ({', '.join(found)}); name one: "
                     f"{where if where != 'EXR' else 'FILE.exr'}:LAYER")


def read_image(path: str | os.PathLike, layer: str | None = None) -> np.ndarray:
    """The colour layer as float32: H x W (Y), H x W x 2 (Y, A), x 3 (RGB) or x 4 (RGBA)."""
    chans = read_channels(path)
    _, names = find_channels(chans, layer, str(path))
    ids = [n for n in names if chans[n].dtype == np.uint32]
    if ids:
        raise InputError(f"{path}: colour channel(s) {', '.join(ids)} hold unsigned integers "
                         "(IDs), not light")
    bad = sum(int(np.count_nonzero(~np.isfinite(chans[n]))) for n in names)
    if bad:
        raise InputError(f"{path}: {bad} value(s) of the colour channels are NaN or infinite")
    if len(names) == 1:
        return chans[names[0]]
    return np.stack([chans[n] for n in names], axis=-1).astype(np.float32)


def write_image(path: str | os.PathLike, image: np.ndarray, *, half: bool | None = None,
                extra: dict[str, np.ndarray] | None = None,
                layout: Layout | None = None) -> None:
    """Write an H x W (``Y``), H x W x 2 (``Y``, ``A``), H x W x 3 (``RGB``) or H x W x 4
    (``RGBA``) image (what ``read_image`` returns), plus
    ``extra`` named channels (depth ``Z``, ``flow.x``/``flow.y``, vector passes, IDs).

    Integer images are written as normalised values (code / Imax), i.e. the stored code
    values, not linearised: EXR holds floats, and the file says nothing about the response.
    ``half`` applies to the colour channels only (default: as ``layout`` says, else float32).
    ``layout``: an input's (:func:`layout`): its windows, pixel aspect ratio, screen window,
    line order and compression are kept."""
    if half is None:
        half = layout is not None and layout.half
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
    write_channels(path, channels, half=set(names) if half else False, layout=layout)


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
    if cands:
        raise InputError(f"{path} has several depth channels ({', '.join(sorted(cands))}); "
                         f"name one: {path}:CHANNEL")
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
