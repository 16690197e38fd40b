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
"""

from __future__ import annotations

import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io.atomic import atomic_write

__all__ = ["IMAGE_FORMATS", "MAX_DECODE_PIXELS", "ImageHeader", "image_format",
           "probe_image", "read_image", "write_image"]

# extension -> format name; read_image/write_image dispatch on the name
IMAGE_FORMATS = {".png": "png", ".tif": "tiff", ".tiff": "tiff", ".jpg": "jpeg",
                 ".jpeg": "jpeg", ".bmp": "bmp", ".webp": "webp", ".exr": "exr"}
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


def _jpeg_header(f) -> ImageHeader | None:
    if f.read(2) != b"\xff\xd8":
        return None
    while True:
        b = f.read(1)
        while b and b != b"\xff":  # skip to the next marker
            b = f.read(1)
        while b == b"\xff":
            b = f.read(1)
        if not b:
            return None
        marker = b[0]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            continue
        raw = f.read(2)
        if len(raw) < 2:
            return None
        (length,) = struct.unpack(">H", raw)
        if marker in _SOF:
            seg = f.read(6)
            if len(seg) < 6:
                return None
            precision, h, w, n = struct.unpack(">BHHB", seg)
            return ImageHeader(h, w, 3 if n >= 3 else 1, 2 if precision > 8 else 1)
        f.seek(length - 2, os.SEEK_CUR)


def probe_image(path: str | os.PathLike) -> ImageHeader:
    """Read an image file's header only (no pixel decoding); ``InputError`` if it has none."""
    path = Path(path)
    fmt = image_format(path)
    if not path.is_file():
        raise InputError(f"image file not found: {path}")
    header = None
    try:
        if fmt == "tiff":
            import tifffile

            with tifffile.TiffFile(path) as tif:
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

            header = ImageHeader(*probe(path))
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
        raise InputError(f"cannot read image {path}: {type(e).__name__}: {e}".splitlines()[0]) \
            from None
    if header is None:
        raise InputError(f"cannot read image {path}: not a {fmt.upper()} file or a corrupt "
                         "header")
    if header.height < 1 or header.width < 1:
        raise InputError(f"image {path} declares an empty size {header.width} x "
                         f"{header.height}")
    return header


def check_decodable(path: str | os.PathLike, max_bytes: int | None = None) -> ImageHeader:
    """Probe ``path`` and refuse it when its decoded size is too large to hold in memory."""
    header = probe_image(path)
    pixels = header.height * header.width
    if pixels > MAX_DECODE_PIXELS:
        raise InputError(f"image {path} claims {header.width} x {header.height} pixels, more "
                         f"than the {MAX_DECODE_PIXELS} a whole-image decoder accepts "
                         "(decompression bomb?); if it is real, " + TILED_TIFF_HINT)
    if max_bytes is not None and header.nbytes > max_bytes:
        raise InputError(f"image {path} decodes to {header.nbytes / 2**20:.0f} MiB "
                         f"({header.width} x {header.height} x {header.channels}), more than "
                         f"the memory budget allows ({max_bytes / 2**20:.0f} MiB for a "
                         f"{image_format(path).upper()}, which is decoded whole); "
                         f"raise --memory-budget or {TILED_TIFF_HINT}")
    return header


def read_image(path: str | os.PathLike, max_bytes: int | None = None) -> np.ndarray:
    """Read an image file whole.

    Parameters
    ----------
    path : path
        PNG, TIFF, JPEG, BMP or WebP (``IMAGE_FORMATS``).
    max_bytes : int, optional
        Refuse (before decoding) images whose decoded pixels take more bytes.

    Returns
    -------
    numpy.ndarray
        uint8, uint16, float32 or float64; H x W or H x W x C in RGB(A) order.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"image file not found: {path}")
    check_decodable(path, max_bytes)
    if image_format(path) == "exr":  # linear float channels: clblur.io.exr
        from clblur.io import exr

        return exr.read_image(path)
    if image_format(path) == "tiff":
        import tifffile

        try:
            img = tifffile.imread(path)
        except Exception as e:  # tifffile raises many types for corrupt files
            raise InputError(f"cannot read image {path}: {e}".splitlines()[0]) from None
    else:
        img = _read_opencv(path)
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64) or img.ndim not in (2, 3):
        raise InputError(f"unsupported image {path}: dtype {img.dtype}, shape {img.shape}")
    return img


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


def _read_opencv(path: Path) -> np.ndarray:
    import cv2

    if image_format(path) == "jpeg" and not _has_jpeg_end(path):
        # libjpeg decodes a truncated file to grey and only warns on stderr
        raise InputError(f"cannot read image {path}: truncated JPEG (no end marker)")
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


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an image atomically; the format follows the extension (``image_format``)."""
    path = Path(path)
    fmt = image_format(path)
    if fmt == "exr":
        from clblur.io import exr

        exr.write_image(path, image)
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
    bgr = image
    if image.ndim == 3 and image.shape[2] in (3, 4):
        bgr = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA if image.shape[2] == 4
                           else cv2.COLOR_RGB2BGR)

    def write(tmp: Path) -> None:
        ok, buf = cv2.imencode(path.suffix.lower(), bgr)
        if not ok:
            raise InputError(f"cannot encode image as {path.suffix}")
        tmp.write_bytes(buf.tobytes())

    atomic_write(path, write)
