"""Image files: read and write by extension, and probe a file's header before decoding it.

Conventions
-----------
* Arrays are uint8, uint16, float32 or float64, H x W or H x W x C, channels in RGB(A) order.
* ``image_format(path)`` is the one place that maps an extension to a format; readers and
  writers dispatch on it.
* Before any decoder runs, ``probe_image`` reads only the header (PNG IHDR, JPEG SOF, TIFF
  page shape, else Pillow's lazy open) and ``read_image`` refuses files whose decoded size
  exceeds ``max_bytes`` (default: ``MAX_DECODE_PIXELS`` pixels), so a small file whose header
  claims 100000 x 100000 pixels is refused instead of exhausting memory.
* ``read_image`` returns pixels as they are meant to be displayed: it applies the EXIF
  Orientation tag, which the decoders ignore.  ``probe_image`` reports the stored size
  (the same bytes, but height and width swapped for orientations 5 to 8).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import struct
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io.atomic import atomic_write
from clblur.io.paths import require_file

__all__ = ["exr_layout", "IMAGE_FORMATS", "MAX_DECODE_PIXELS", "ImageHeader", "codec_block",
           "image_format", "light_channels", "probe_image", "read_image", "response_for_file",
           "write_image"]

# extension -> format name; read_image/write_image dispatch on the name
IMAGE_FORMATS = {".png": "png", ".tif": "tiff", ".tiff": "tiff", ".jpg": "jpeg",
                 ".jpeg": "jpeg", ".bmp": "bmp", ".webp": "webp", ".exr": "exr",
                 ".ppm": "netpbm", ".pgm": "netpbm", ".pnm": "netpbm"}
# OpenCV's own decode limit (CV_IO_MAX_IMAGE_PIXELS); larger images belong in tiled TIFFs
MAX_DECODE_PIXELS = 2**30
TILED_TIFF_HINT = ("convert it to a tiled TIFF, which is read window by window (e.g. "
                   "`vips tiffsave IN OUT.tif --tile --bigtiff`)")


def image_format(path: str | os.PathLike) -> str:
    """The format of an image path, from its extension (one of ``IMAGE_FORMATS``' values)."""
    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_FORMATS:
        raise InputError(f"{path}: unknown image extension {suffix or '(none)'!r}; use one of "
                         f"{', '.join(IMAGE_FORMATS)}")
    return IMAGE_FORMATS[suffix]


def response_for_file(path: str | os.PathLike) -> str:
    """The response an image file's values go through when none is given: ``linear`` for an
    EXR (scene-linear light: a bounded response would clip its highlights at full scale and
    its negatives at 0), else ``exp``, the paper's Eq. 3.  The one rule for every command
    and for ``clblur.tiling.blur_file``."""
    return "linear" if IMAGE_FORMATS.get(Path(path).suffix.lower()) == "exr" else "exp"


@dataclass(frozen=True)
class ImageHeader:
    """What a header says, before decoding: size, channels and bytes per sample."""

    height: int
    width: int
    channels: int
    itemsize: int

    @property
    def nbytes(self) -> int:
        return self.height * self.width * self.channels * self.itemsize


def _png_header(head: bytes) -> ImageHeader | None:
    if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    w, h, depth, colour = struct.unpack(">IIBB", head[16:26])
    # decoded channels as OpenCV returns them (palette and grey+alpha may come out as BGRA)
    channels = {0: 1, 2: 3, 3: 4, 4: 4, 6: 4}.get(colour, 4)
    return ImageHeader(h, w, channels, 2 if depth == 16 else 1)


_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_segments(f):
    """The segments of a JPEG up to its start of scan (only entropy-coded data follows it):
    yields ``(marker, length)`` with ``f`` at the segment's payload (``length - 2`` bytes);
    a segment the caller does not read is skipped.  Stops at a malformed stream."""
    if f.read(2) != b"\xff\xd8":
        return
    while True:
        b = f.read(1)
        while b and b != b"\xff":  # skip to the next marker
            b = f.read(1)
        while b == b"\xff":
            b = f.read(1)
        if not b or b[0] in (0xDA, 0xD9):  # start of scan, end of image
            return
        marker = b[0]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            continue
        raw = f.read(2)
        if len(raw) < 2:
            return
        (length,) = struct.unpack(">H", raw)
        if length < 2:
            return
        start = f.tell()
        yield marker, length
        f.seek(start + length - 2)


def _jpeg_header(f) -> ImageHeader | None:
    for marker, _ in _jpeg_segments(f):
        if marker in _SOF:
            seg = f.read(6)
            if len(seg) < 6:
                return None
            precision, h, w, n = struct.unpack(">BHHB", seg)
            return ImageHeader(h, w, 3 if n >= 3 else 1, 2 if precision > 8 else 1)
    return None


# the JPEG processes that code without a transform (SOF3, 7, 11, 15): no blocks to mix values
_LOSSLESS_SOF = {0xC3, 0xC7, 0xCB, 0xCF}


def codec_block(path: str | os.PathLike) -> int:
    """The side, in pixels, of the largest block a file's lossy codec codes values together
    in: 1 for lossless storage (PNG, TIFF, EXR, Netpbm, BMP, lossless JPEG and WebP).

    A baseline or progressive JPEG codes 8 x 8 blocks of each component, and a chroma
    component subsampled 2 : 1 (4:2:2, 4:2:0) covers 16 pixels with its 8; a lossy WebP
    (VP8) codes 16 x 16 macroblocks.  Within such a block every decoded value depends on
    every coded one, so a clipped highlight's ringing spreads over its blocks
    (``clblur.pixels.near_clip``).  Read from the file's headers; 1 where they cannot be
    read.
    """
    path = Path(path)
    fmt = image_format(path)
    try:
        with open(path, "rb") as f:
            if fmt == "jpeg":
                for marker, length in _jpeg_segments(f):
                    if marker not in _SOF:
                        continue
                    if marker in _LOSSLESS_SOF:
                        return 1
                    seg = f.read(length - 2)
                    n = seg[5] if len(seg) >= 6 else 0
                    factors = [max(b >> 4, b & 15) for b in seg[7:6 + 3 * n:3]]
                    return 8 * max(factors, default=1)
            elif fmt == "webp":
                head = f.read(12)
                if head[:4] == b"RIFF" and head[8:] == b"WEBP":
                    while len(head := f.read(8)) == 8:
                        kind, length = struct.unpack("<4sI", head)
                        if kind == b"VP8 ":
                            return 16
                        if kind == b"VP8L":
                            return 1
                        f.seek(length + (length & 1), os.SEEK_CUR)
    except OSError:
        pass
    return 1


class _Collect(logging.Handler):
    def __init__(self, into: list[str]):
        super().__init__(logging.WARNING)
        self.into = into

    def emit(self, record: logging.LogRecord) -> None:
        self.into.append(record.getMessage().splitlines()[0] if record.getMessage() else "")


@contextlib.contextmanager
def tiff_log():
    """Collect tifffile's warnings while a TIFF is read (a list of messages).

    tifffile logs what it finds wrong in a file (e.g. "invalid offset to first page") and
    raises something less telling afterwards (an IndexError); with a handler of our own on
    its logger the warning is not printed on stderr by Python's last-resort handler, and the
    error can quote it."""
    messages: list[str] = []
    handler = _Collect(messages)
    logger = logging.getLogger("tifffile")
    logger.addHandler(handler)
    try:
        yield messages
    finally:
        logger.removeHandler(handler)


def _decoder_error(path: Path, fmt: str, e: Exception, logged: list[str] = ()) -> InputError:
    """A decoder library's exception as our one-line error (its log's first line if any)."""
    # tifffile's messages start with the object that logs them: "<tifffile.TiffPages @8> "
    why = re.sub(r"^<[^>]*>\s*", "", logged[0]) if logged and logged[0] else \
        f"{type(e).__name__}: {e}"
    return InputError(f"cannot read image {path}: corrupt or truncated {fmt.upper()} "
                      f"({why})".splitlines()[0])


def _only_exr_layers(path: Path, layer: str | None) -> None:
    if layer is not None and image_format(path) != "exr":
        raise InputError(f"{path}:{layer}: only EXR files have named layers")


def probe_image(path: str | os.PathLike, layer: str | None = None) -> ImageHeader:
    """Read an image file's header only (no pixel decoding); ``InputError`` if it has none.
    ``layer``: an EXR file's colour layer (``clblur.io.exr.find_channels``)."""
    path = Path(path)
    fmt = image_format(path)
    require_file(path, "image")
    _only_exr_layers(path, layer)
    header = None
    logged: list[str] = []
    try:
        if fmt == "tiff":
            import tifffile

            with tiff_log() as logged, tifffile.TiffFile(path) as tif:
                s = tif.series[0]
                shape = tuple(int(d) for d in s.shape)
                header = ImageHeader(shape[0] if len(shape) > 1 else 1,
                                     shape[1] if len(shape) > 1 else shape[0],
                                     int(np.prod(shape[2:])) if len(shape) > 2 else 1,
                                     np.dtype(s.dtype).itemsize)
        elif fmt == "png":
            with path.open("rb") as f:
                header = _png_header(f.read(26))
        elif fmt == "jpeg":
            with path.open("rb") as f:
                header = _jpeg_header(f)
        elif fmt == "exr":
            from clblur.io.exr import probe

            header = ImageHeader(*probe(path, layer))
        elif fmt == "netpbm":
            from clblur.io import netpbm

            header = ImageHeader(*netpbm.probe(path))
        else:
            from PIL import Image

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                with Image.open(path) as im:
                    w, h = im.size
                    header = ImageHeader(h, w, len(im.getbands()), 1)
    except InputError:
        raise
    except Exception as e:  # every decoder library raises its own types for corrupt files
        raise _decoder_error(path, fmt, e, logged) from None
    if header is None:
        raise InputError(f"cannot read image {path}: not a {fmt.upper()} file or a corrupt "
                         "header")
    if header.height < 1 or header.width < 1:
        raise InputError(f"image {path} declares an empty size {header.width} x "
                         f"{header.height}")
    return header


def describe_size(nbytes: int | float) -> str:
    """``nbytes`` for a message, in the binary unit that keeps two significant figures: a
    small memory budget must not read as "0 MiB"."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if nbytes >= scale:
            value = nbytes / scale
            return f"{value:.{1 if value < 10 else 0}f} {unit}"
    return f"{int(nbytes)} B"


def check_decodable(path: str | os.PathLike, max_bytes: int | None = None,
                    layer: str | None = None) -> ImageHeader:
    """Probe ``path`` and refuse it when its decoded size is too large to hold in memory
    (``layer``: as for :func:`probe_image`)."""
    header = probe_image(path, layer)
    pixels = header.height * header.width
    if pixels > MAX_DECODE_PIXELS:
        raise InputError(f"image {path} claims {header.width} x {header.height} pixels, more "
                         f"than the {MAX_DECODE_PIXELS} a whole-image decoder accepts "
                         "(decompression bomb?); if it is real, " + TILED_TIFF_HINT)
    if max_bytes is not None and header.nbytes > max_bytes:
        raise InputError(f"image {path} decodes to {describe_size(header.nbytes)} "
                         f"({header.width} x {header.height} x {header.channels}), more than "
                         f"the memory budget allows ({describe_size(max_bytes)} for a "
                         f"{image_format(path).upper()}, which is decoded whole); "
                         f"raise --memory-budget or {TILED_TIFF_HINT}")
    return header


def read_image(path: str | os.PathLike, max_bytes: int | None = None,
               layer: str | None = None) -> np.ndarray:
    """Read an image file whole.

    Parameters
    ----------
    path : path
        PNG, TIFF, JPEG, BMP, WebP, OpenEXR or Netpbm PGM / PPM (``IMAGE_FORMATS``).
    max_bytes : int, optional
        Refuse (before decoding) images whose decoded pixels take more bytes.
    layer : str, optional
        An EXR file's colour layer (``LAYER.R/G/B/A``; ``clblur.io.exr.find_channels``), for
        a multilayer file with more than one.

    Returns
    -------
    numpy.ndarray
        uint8, uint16, float32 or float64; H x W or H x W x C in RGB(A) order, turned as the
        EXIF Orientation tag says (JPEG, PNG, WebP, TIFF): cameras store portrait shots
        sideways and set the tag, so a bracket would otherwise mix turned and upright frames.
    """
    path = Path(path)
    require_file(path, "image")
    check_decodable(path, max_bytes, layer)
    if image_format(path) == "exr":  # linear float channels: clblur.io.exr
        from clblur.io import exr

        return exr.read_image(path, layer)
    if image_format(path) == "netpbm":  # no orientation tag: stored as displayed
        from clblur.io import netpbm

        return netpbm.read_image(path)
    if image_format(path) == "tiff":
        import tifffile

        with tiff_log() as logged:
            try:
                with tifffile.TiffFile(path) as tif:
                    img = tif.asarray()
                    orientation = _tiff_orientation(tif)
            except Exception as e:  # tifffile raises many types for corrupt files
                raise _decoder_error(path, "tiff", e, logged) from None
    else:
        img = _read_other(path)
        # after the decode, so a corrupt file is reported by its decoder as before
        orientation = _exif_orientation(path)
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64) or img.ndim not in (2, 3):
        raise InputError(f"unsupported image {path}: dtype {img.dtype}, shape {img.shape}")
    return _orient(img, orientation)


def light_channels(image: np.ndarray) -> np.ndarray:
    """The channels of an image read from a file that carry light: grey + alpha (2
    channels, as a TIFF with an extra sample stores it) and RGB + alpha (4) without their
    alpha; anything else as it is.  For measurements (calibration, study), where alpha is
    no exposure."""
    if image.ndim == 3 and image.shape[2] in (2, 4):
        return image[..., :image.shape[2] - 1]
    return image


def _orient(img: np.ndarray, orientation: int | None) -> np.ndarray:
    """``img`` turned as EXIF Orientation ``orientation`` says (Pillow's ``exif_transpose``);
    rows and columns are the first two axes, so any channels and dtype."""
    turned = {2: lambda a: a[:, ::-1],                      # flip left-right
              3: lambda a: a[::-1, ::-1],                   # rotate 180
              4: lambda a: a[::-1],                         # flip top-bottom
              5: lambda a: np.swapaxes(a, 0, 1),            # transpose
              6: lambda a: np.rot90(a, -1),                 # rotate 90 clockwise
              7: lambda a: np.swapaxes(a[::-1, ::-1], 0, 1),  # transverse
              8: lambda a: np.rot90(a, 1)}.get(orientation)  # rotate 90 counter-clockwise
    return img if turned is None else np.ascontiguousarray(turned(img))


def _tiff_orientation(tif) -> int | None:
    """The Orientation tag of a TIFF's first page, when its pixels are rows x columns
    (x samples); None for stacks and planar layouts, whose first axes are not the image's."""
    try:
        if tif.series[0].axes not in ("YX", "YXS"):
            return None
        tag = tif.pages[0].tags.get(0x0112)
        value = int(tag.value) if tag is not None else None
    except Exception:  # a malformed tag is no orientation: the pixels decoded fine
        return None
    return value if value is not None and 1 <= value <= 8 else None


def _exif_orientation(path: Path) -> int | None:
    """The EXIF Orientation tag (1..8) of a JPEG, PNG or WebP, else None (absent, corrupt or
    out of range).  Only the headers are read: the EXIF block is found by walking the
    file's segments or chunks, then parsed by Pillow's ``Exif``.  (``Image.open`` is not
    used: it refuses images over ~179 Mpixel as bombs, and a PNG's ``getexif()`` decodes
    the whole image when the file has no eXIf chunk before its pixels.)"""
    try:
        with path.open("rb") as f:
            blob = {"jpeg": _jpeg_exif, "png": _png_exif, "webp": _webp_exif}.get(
                image_format(path), lambda f: None)(f)
        if not blob:
            return None
        from PIL import Image

        with warnings.catch_warnings():  # "Corrupt EXIF data" would reach stderr
            warnings.simplefilter("ignore")
            exif = Image.Exif()
            exif.load(blob)
            value = exif.get(0x0112)
    except Exception:  # corrupt EXIF is no orientation: the pixels decoded fine
        return None
    return value if isinstance(value, int) and 1 <= value <= 8 else None


def _jpeg_exif(f) -> bytes | None:
    """The payload of a JPEG's first APP1 "Exif" segment."""
    for marker, length in _jpeg_segments(f):
        if marker == 0xE1:
            seg = f.read(length - 2)
            if seg.startswith(b"Exif\0\0"):
                return seg
    return None


def _png_chunks(f):
    """The chunks of a PNG up to IEND: yields ``(kind, length)`` with ``f`` at the chunk's
    data; a chunk the caller does not read is skipped by seeking.  Nothing for a file that is
    not a PNG; stops at the end of the file."""
    if f.read(8) != b"\x89PNG\r\n\x1a\n":
        return
    while len(head := f.read(8)) == 8:
        length, kind = struct.unpack(">I4s", head)
        start = f.tell()
        yield kind, length
        if kind == b"IEND":
            return
        f.seek(start + length + 4)  # data and CRC


def _png_exif(f) -> bytes | None:
    """The data of a PNG's eXIf chunk.  Chunks are skipped by seeking up to IEND, as eXIf
    may follow the image data (Pillow, the reference here, reads it there too)."""
    for kind, length in _png_chunks(f):
        if kind == b"eXIf":
            return f.read(length)
    return None


def _png_damage(path: Path) -> str | None:
    """What is wrong with a PNG's chunk stream (truncated, a chunk failing its CRC), or None.

    Checked before libpng sees the file: libpng prints its own error line on stderr, which
    would come before ours."""
    size = path.stat().st_size
    with path.open("rb") as f:
        for kind, length in _png_chunks(f):
            name = kind.decode("latin-1")
            if f.tell() + length + 4 > size:
                return f"truncated PNG (the file ends inside chunk {name!r})"
            crc = zlib.crc32(kind)
            left = length
            while left:
                block = f.read(min(left, 1 << 20))
                crc = zlib.crc32(block, crc)
                left -= len(block)
            if struct.unpack(">I", f.read(4))[0] != crc:
                return f"corrupt PNG (chunk {name!r} fails its CRC check)"
            if kind == b"IEND":
                return None
    return "truncated PNG (no IEND chunk)"


def _webp_exif(f) -> bytes | None:
    """The data of a WebP's EXIF chunk (RIFF chunks, each padded to an even length)."""
    head = f.read(12)
    if len(head) < 12 or head[:4] != b"RIFF" or head[8:] != b"WEBP":
        return None
    while len(head := f.read(8)) == 8:
        kind, length = struct.unpack("<4sI", head)
        if kind == b"EXIF":
            return f.read(length)
        f.seek(length + (length & 1), os.SEEK_CUR)
    return None


def _has_jpeg_end(path: Path) -> bool:
    """Whether the file holds a JPEG end-of-image marker: usually in the last bytes, but
    some cameras append data after it (e.g. a motion photo's video), so search on."""
    size = path.stat().st_size
    with path.open("rb") as f:
        f.seek(max(size - 64, 0))
        if b"\xff\xd9" in f.read():
            return True
        f.seek(0)
        tail = b""
        for block in iter(lambda: f.read(1 << 20), b""):
            if b"\xff\xd9" in tail + block:
                return True
            tail = block[-1:]
    return False


def _read_jpeg(path: Path) -> np.ndarray | None:
    """A grey or RGB JPEG decoded by Pillow (libjpeg-turbo, the same pixels as OpenCV's
    decode), or None for what Pillow does not decode the way OpenCV does (CMYK, images over
    its decompression-bomb limit, which ours has already passed).

    Why not OpenCV: libjpeg treats corrupt entropy-coded data ("premature end of data
    segment") as a warning, which OpenCV prints on stderr before returning a damaged image;
    Pillow raises it, so the file is refused with one line."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's bomb warning: our own limit applies
            with Image.open(path) as im:
                if im.mode not in ("L", "RGB"):
                    return None
                im.load()
                return np.asarray(im)
    except Image.DecompressionBombError:
        return None
    except Exception as e:  # Pillow raises OSError, SyntaxError, ValueError... on bad data
        raise _decoder_error(path, "jpeg", e) from None


def _read_other(path: Path) -> np.ndarray:
    """A PNG, JPEG, BMP or WebP, checked first for the damage its C decoder would only print
    on stderr; grey and RGB JPEGs decoded by Pillow (``_read_jpeg``), the rest by OpenCV."""
    fmt = image_format(path)
    if fmt == "jpeg":
        if not _has_jpeg_end(path):
            # libjpeg decodes a truncated file to grey and only warns on stderr
            raise InputError(f"cannot read image {path}: truncated JPEG (no end marker)")
        img = _read_jpeg(path)
        if img is not None:
            return img
    if fmt == "png" and (damage := _png_damage(path)):
        raise InputError(f"cannot read image {path}: {damage}")
    return _read_opencv(path)


def _read_opencv(path: Path) -> np.ndarray:
    import cv2

    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # we report it ourselves
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise InputError(f"cannot read image {path}: {e}".splitlines()[0]) from None
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise InputError(f"cannot read image {path}: not an image file or corrupt")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return img


# formats OpenCV writes in 8 bits only: it saturates a 16-bit image's codes into them (a
# 16-bit photo came out white), so the codes are scaled to 8 bits here instead
EIGHT_BIT_FORMATS = ("jpeg", "bmp", "webp")


def exr_layout(path: str | os.PathLike, layer: str | None = None):
    """The ``clblur.io.exr.Layout`` of an EXR image file, None for other formats."""
    if image_format(Path(path)) != "exr":
        return None
    from clblur.io import exr

    return exr.layout(path, layer)


def _for_opencv(path: Path, fmt: str, image: np.ndarray) -> np.ndarray:
    """``image`` in a layout and depth OpenCV writes as ``fmt`` without losing what the format
    can hold: grey + alpha as RGBA (no such OpenCV layout), 16-bit codes scaled to the nearest
    8-bit ones for 8-bit formats; alpha refused for JPEG (which would drop it silently)."""
    if image.ndim == 3 and image.shape[2] == 2:
        image = image[..., [0, 0, 0, 1]]
    if fmt == "jpeg" and image.ndim == 3 and image.shape[2] == 4:
        raise InputError(f"{path}: JPEG cannot hold alpha (this image has it); write .png, "
                         ".tif, .webp or .exr")
    if image.dtype == np.uint16 and fmt in EIGHT_BIT_FORMATS:
        image = np.rint(image / 257.0).astype(np.uint8)
    return image


def write_image(path: str | os.PathLike, image: np.ndarray, *, layout=None) -> None:
    """Write an image atomically; the format follows the extension (``image_format``).
    ``layout``: an EXR input's ``clblur.io.exr.Layout`` (:func:`exr_layout`), kept by an EXR
    output (its windows, pixel aspect ratio, screen window, line order, compression and
    float16 colour); other formats have no such header and ignore it."""
    path = Path(path)
    fmt = image_format(path)
    if fmt == "exr":
        from clblur.io import exr

        exr.write_image(path, image, layout=layout)
        return
    if fmt == "netpbm":
        from clblur.io import netpbm

        netpbm.write_image(path, image)
        return
    if fmt == "tiff":
        import tifffile

        rgb = image.ndim == 3 and image.shape[2] in (3, 4)
        atomic_write(path, lambda tmp: tifffile.imwrite(
            tmp, image, photometric="rgb" if rgb else "minisblack"))
        return
    import cv2

    if image.dtype.kind == "f":
        raise InputError(f"{path.suffix} cannot hold float images; write .tif, .tiff or .exr "
                         "instead")
    image = _for_opencv(path, fmt, image)
    bgr = image
    if image.ndim == 3 and image.shape[2] in (3, 4):
        bgr = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA if image.shape[2] == 4
                           else cv2.COLOR_RGB2BGR)

    def write(tmp: Path) -> None:
        # encoded straight into the file: an in-memory encode and its bytes copy held the
        # compressed image twice more (106 against 37 MiB above a 34 MiB uint16 array)
        try:
            ok = cv2.imwrite(str(tmp), bgr)
        except cv2.error as e:
            raise InputError(f"cannot encode image as {path.suffix}: "
                             f"{' '.join(str(e).split())[:200]}") from None
        if not ok:
            raise InputError(f"cannot encode image as {path.suffix}")

    atomic_write(path, write)
