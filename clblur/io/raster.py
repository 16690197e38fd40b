"""Rasters in files, read and written window by window.

Conventions
-----------
* Array-likes: anything with ``shape``, ``dtype`` and numpy-style ``[rows, cols]`` slicing
  (numpy arrays, zarr arrays, ``MappedRaster``).  Do not keep a long-lived ``np.memmap``:
  every page it touches stays resident; ``as_array_like`` turns one into a ``MappedRaster``.
* ``open_image`` reads uncompressed contiguous TIFFs through ``MappedRaster``, strip and
  tile TIFFs of any compression tifffile decodes through ``TiffWindows`` (the segments a
  window touches, decoded one by one), and every other format whole (after the header check
  of ``clblur.io.images.check_decodable`` with the caller's byte limit).  A TIFF that its
  Orientation tag turns is seen upright through ``OrientedRaster``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.io.images import (
    _decoder_error,
    _orient,
    _tiff_orientation,
    check_decodable,
    describe_size,
    image_format,
    read_image,
    tiff_log,
)
from clblur.io.paths import require_file
from clblur.pixels import SUPPORTED_DTYPES

__all__ = ["MappedRaster", "OrientedRaster", "TiffWindows", "as_array_like", "create_tiff",
           "is_tiff", "open_image"]


def _window(key, shape: tuple[int, ...]) -> tuple[list[tuple[int, int]], list[int], tuple]:
    """A ``[rows, cols, ...]`` key as row and column spans ``(start, stop)``, the axes given
    as integers (to squeeze after the read) and the rest of the key (channels).  Windows
    only: slices of step 1 or integers on the first two axes."""
    key = key if isinstance(key, tuple) else (key,)
    if Ellipsis in key[:2]:
        raise InputTypeError("a raster window takes row and column slices, not Ellipsis")
    key = key + (slice(None),) * max(0, 2 - len(key))
    spans, squeeze = [], []
    for axis, k in enumerate(key[:2]):
        if isinstance(k, (int, np.integer)):
            k = int(k) + shape[axis] if k < 0 else int(k)
            if not 0 <= k < shape[axis]:
                raise IndexError(f"index {k} is out of bounds for axis {axis}")
            squeeze.append(axis)
            k = slice(k, k + 1)
        start, stop, step = k.indices(shape[axis])
        if step != 1:
            raise InputTypeError("a raster window has step 1")
        spans.append((start, max(start, stop)))
    return spans, squeeze, key[2:]


class MappedRaster:
    """A C-ordered raster stored at ``offset`` in a file, mapped only while one window is read
    or written, so resident memory follows the window instead of growing with every page ever
    touched (a long-lived ``np.memmap`` keeps them all)."""

    def __init__(self, path: str | os.PathLike, dtype, shape: tuple[int, ...], offset: int = 0,
                 writable: bool = False):
        self.path = Path(path)
        self.dtype = np.dtype(dtype)
        self.shape = tuple(int(s) for s in shape)
        self.offset = int(offset)
        self.writable = writable
        need = self.offset + self.dtype.itemsize * math.prod(self.shape)
        if not self.path.is_file() or self.path.stat().st_size < need:
            raise InputError(f"{self.path} is shorter than a {self.shape} {self.dtype} raster "
                             f"at offset {self.offset}")

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def _map(self, mode: str) -> np.memmap:
        return np.memmap(self.path, dtype=self.dtype, mode=mode, offset=self.offset,
                         shape=self.shape)

    def __getitem__(self, key) -> np.ndarray:
        m = self._map("r")
        try:
            return np.array(m[key])
        finally:
            del m

    def __setitem__(self, key, value) -> None:
        if not self.writable:
            raise InputError(f"{self.path} is opened read-only")
        m = self._map("r+")
        try:  # no flush: unmapping leaves the written pages to the kernel's writeback
            m[key] = value
        finally:
            del m


class OrientedRaster:
    """A stored raster seen turned as its EXIF/TIFF Orientation tag says (2..8), window by
    window: a window of the turned image is read as the one stored window it comes from,
    then turned (``clblur.io.images._orient``), so a sideways-stored TIFF reads upright
    without being decoded whole.  Keys: slices of step 1 (or integers) on rows and columns,
    then anything for the channels."""

    # orientation -> (rows and columns swapped, stored rows reversed, stored columns reversed)
    _TURN = {2: (False, False, True), 3: (False, True, True), 4: (False, True, False),
             5: (True, False, False), 6: (True, True, False), 7: (True, True, True),
             8: (True, False, True)}

    def __init__(self, base, orientation: int):
        if orientation not in self._TURN:
            raise InputError(f"orientation must be 2..8, got {orientation!r}")
        self.base, self.orientation = base, orientation
        self.dtype = np.dtype(base.dtype)
        shape = tuple(int(s) for s in base.shape)
        swap = self._TURN[orientation][0]
        self.shape = ((shape[1], shape[0]) if swap else shape[:2]) + shape[2:]

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __getitem__(self, key) -> np.ndarray:
        spans, squeeze, rest = _window(key, self.shape)
        swap, flip_rows, flip_cols = self._TURN[self.orientation]
        stored = spans[::-1] if swap else spans  # stored rows, stored columns
        h, w = self.base.shape[:2]
        (r0, r1), (c0, c1) = stored
        if flip_rows:
            r0, r1 = h - r1, h - r0
        if flip_cols:
            c0, c1 = w - c1, w - c0
        block = np.asarray(self.base[r0:r1, c0:c1])
        out = _orient(block, self.orientation)[(slice(None), slice(None)) + rest]
        return out.squeeze(axis=tuple(squeeze)) if squeeze else out


class TiffWindows:
    """A strip or tile TIFF (first page, rows x columns (x samples), samples interleaved)
    read window by window: the segments a window touches are read and decoded one by one,
    with any compression tifffile decodes (imagecodecs: LZW, JPEG, ...), and the file is
    open only during the read.  A segment that does not decode is an ``InputError`` naming
    the file, found when its window is read (a corrupt strip halfway through a large image
    stops the run there, leaving no output: ``clblur.io.atomic``)."""

    def __init__(self, path: str | os.PathLike):
        import tifffile

        self.path = Path(path)
        with tifffile.TiffFile(self.path) as tif:
            page = tif.pages[0]
            shape = tuple(int(d) for d in tif.series[0].shape)
            self.dtype = np.dtype(tif.series[0].dtype)
            self.segment = tuple(int(d) for d in page.chunks[:2])  # rows, cols of a segment
            self.grid = tuple(int(d) for d in page.chunked[:2])  # segments down, across
            self.offsets = np.asarray(page.dataoffsets, np.int64)
            self.counts = np.asarray(page.databytecounts, np.int64)
        if page.planarconfig != 1 or len(shape) not in (2, 3) \
                or self.offsets.size != self.grid[0] * self.grid[1]:
            raise InputError("not a single-plane strip or tile TIFF")  # open_image reads whole
        self.shape = shape

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __getitem__(self, key) -> np.ndarray:
        import tifffile

        ((r0, r1), (c0, c1)), squeeze, rest = _window(key, self.shape)
        out = np.zeros((r1 - r0, c1 - c0) + self.shape[2:], self.dtype)
        (th, tw), (_, across) = self.segment, self.grid
        rows = range(r0 // th, -(-r1 // th)) if r1 > r0 and c1 > c0 else range(0)
        with tifffile.TiffFile(self.path) as tif:
            page, fh = tif.pages[0], tif.filehandle
            for row in rows:
                for col in range(c0 // tw, -(-c1 // tw)):
                    i = row * across + col
                    if self.counts[i] == 0:  # a sparse file's missing segment: zeros
                        continue
                    fh.seek(int(self.offsets[i]))
                    data = fh.read(int(self.counts[i]))
                    try:
                        seg = page.decode(data, i)[0]
                    except Exception as e:  # imagecodecs and tifffile raise their own types
                        raise InputError(f"cannot read image {self.path}: corrupt TIFF "
                                         f"segment {i} ({type(e).__name__}: "
                                         f"{str(e).splitlines()[0] if str(e) else ''})"
                                         ) from None
                    # (a file's last strip may hold fewer rows than the others)
                    seg = np.asarray(seg).reshape((-1, tw) + self.shape[2:])
                    y0, x0 = row * th, col * tw
                    ya, yb = max(r0, y0), min(r1, y0 + seg.shape[0])
                    xa, xb = max(c0, x0), min(c1, x0 + tw, self.shape[1])
                    out[ya - r0:yb - r0, xa - c0:xb - c0] = seg[ya - y0:yb - y0, xa - x0:xb - x0]
        out = out[(slice(None), slice(None)) + rest]
        return out.squeeze(axis=tuple(squeeze)) if squeeze else out


def as_array_like(array):
    """A long-lived ``np.memmap`` becomes a ``MappedRaster`` of the same file; others pass."""
    if isinstance(array, np.memmap) and getattr(array, "filename", None) \
            and array.flags.c_contiguous and not isinstance(array.base, np.ndarray):
        # (a slice of a memmap has the memmap as base and keeps its offset: not re-mappable)
        return MappedRaster(array.filename, array.dtype, array.shape, array.offset,
                            writable=array.mode in ("r+", "w+"))
    return array



def is_tiff(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a TIFF (by extension)."""
    return Path(path).suffix.lower() in (".tif", ".tiff")


def open_image(path: str | os.PathLike, max_bytes: int | None = None):
    """An image file as an array-like, read window by window where the format allows:
    uncompressed contiguous TIFF -> ``MappedRaster``; other TIFF -> zarr over tifffile's
    store (reads only the strips/tiles a window touches); anything else read whole.  A TIFF
    whose Orientation tag turns it is seen upright through ``OrientedRaster``, as
    ``read_image`` returns it."""
    path = Path(path)
    require_file(path, "image")
    if image_format(path) != "tiff":
        return read_image(path, max_bytes)
    header = check_decodable(path)  # a TIFF needs no whole decode, but its header must parse
    import tifffile

    with tiff_log() as logged:
        try:
            with tifffile.TiffFile(path) as tif:
                orientation = _tiff_orientation(tif)
                axes = tif.series[0].axes
                dtype = np.dtype(tif.series[0].dtype)
                page = tif.series[0].pages[0]
                end = max((o + c for o, c in zip(page.dataoffsets, page.databytecounts,
                                                 strict=False)), default=0)
        except Exception as e:  # tifffile raises many types for corrupt files
            raise _decoder_error(path, "tiff", e, logged) from None
    if end > path.stat().st_size:  # found now, not by a window read halfway through
        raise InputError(f"cannot read image {path}: truncated TIFF (pixel data ends at byte "
                         f"{end}, the file at {path.stat().st_size})")
    if axes not in ("YX", "YXS"):  # e.g. planar RGB (SYX), stacks, pyramids' extra axes
        raise InputError(f"{path}: unsupported TIFF layout {axes!r}; expected rows x columns "
                         "(x samples), i.e. YX or YXS")
    # refused here, as read_image refuses it, before an output of that dtype is created (a
    # 1-bit TIFF failed there with tifffile's "cannot write non-contiguous empty file")
    if dtype not in [np.dtype(d) for d in SUPPORTED_DTYPES]:
        raise InputError(f"unsupported image {path}: dtype {dtype}; use uint8, uint16, float32 "
                         "or float64")

    def turned(raster):  # a sideways-stored TIFF is read upright, as read_image reads it
        return raster if orientation in (None, 1) else OrientedRaster(raster, orientation)

    try:
        m = tifffile.memmap(path, mode="r")
        raster = MappedRaster(path, m.dtype, m.shape, m.offset)
        del m
        return turned(raster)
    except InputError:  # the pixel data runs past the end of the file
        raise InputError(f"cannot read image {path}: truncated TIFF") from None
    except ValueError:  # compressed, tiled or otherwise not mappable
        pass
    except Exception as e:
        raise _decoder_error(path, "tiff", e) from None
    try:
        return turned(TiffWindows(path))
    except Exception:  # a layout read by segments cannot serve (planar, ...): read it whole
        if max_bytes is not None and header.nbytes > max_bytes:
            raise InputError(f"{path} cannot be read window by window and decodes to "
                             f"{describe_size(header.nbytes)}, more than the memory budget; "
                             "save it as an uncompressed or tiled TIFF") from None
        return read_image(path)


def create_tiff(path: Path, shape: tuple[int, ...], dtype: np.dtype) -> MappedRaster:
    """An uncompressed TIFF (BigTIFF when large) whose pixels are written window by window."""
    import tifffile

    rgb = len(shape) == 3 and shape[2] in (3, 4)
    nbytes = math.prod(shape) * np.dtype(dtype).itemsize
    m = tifffile.memmap(path, shape=shape, dtype=dtype, bigtiff=nbytes >= 2**31,
                        photometric="rgb" if rgb else "minisblack")
    offset = m.offset
    del m
    return MappedRaster(path, dtype, shape, offset, writable=True)


