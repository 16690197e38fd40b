"""Rasters in files, read and written window by window.

Conventions
-----------
* Array-likes: anything with ``shape``, ``dtype`` and numpy-style ``[rows, cols]`` slicing
  (numpy arrays, zarr arrays, ``MappedRaster``).  Do not keep a long-lived ``np.memmap``:
  every page it touches stays resident; ``as_array_like`` turns one into a ``MappedRaster``.
* ``open_image`` reads uncompressed contiguous TIFFs through ``MappedRaster``, other TIFFs
  through tifffile's zarr store, and every other format whole (after the header check of
  ``clblur.io.images.check_decodable`` with the caller's byte limit).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io.images import check_decodable, image_format, read_image
from clblur.io.paths import require_file

__all__ = ["MappedRaster", "as_array_like", "create_tiff", "is_tiff", "open_image"]


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
    store (reads only the strips/tiles a window touches); anything else read whole."""
    path = Path(path)
    require_file(path, "image")
    if image_format(path) != "tiff":
        return read_image(path, max_bytes)
    header = check_decodable(path)  # a TIFF needs no whole decode, but its header must parse
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            axes = tif.series[0].axes
            page = tif.series[0].pages[0]
            end = max((o + c for o, c in zip(page.dataoffsets, page.databytecounts,
                                             strict=False)), default=0)
    except Exception as e:  # tifffile raises many types for corrupt files
        raise InputError(f"cannot read image {path}: {e}") from None
    if end > path.stat().st_size:  # found now, not by a window read halfway through
        raise InputError(f"cannot read image {path}: truncated TIFF (pixel data ends at byte "
                         f"{end}, the file at {path.stat().st_size})")
    if axes not in ("YX", "YXS"):  # e.g. planar RGB (SYX), stacks, pyramids' extra axes
        raise InputError(f"{path}: unsupported TIFF layout {axes!r}; expected rows x columns "
                         "(x samples), i.e. YX or YXS")
    try:
        m = tifffile.memmap(path, mode="r")
        raster = MappedRaster(path, m.dtype, m.shape, m.offset)
        del m
        return raster
    except InputError:  # the pixel data runs past the end of the file
        raise InputError(f"cannot read image {path}: truncated TIFF") from None
    except ValueError:  # compressed, tiled or otherwise not mappable
        pass
    except Exception as e:
        raise InputError(f"cannot read image {path}: {e}") from None
    try:
        import zarr

        return zarr.open(tifffile.imread(path, aszarr=True), mode="r")
    except Exception:  # no zarr, or a layout its store cannot index: read it whole
        if max_bytes is not None and header.nbytes > max_bytes:
            raise InputError(f"{path} cannot be read window by window and decodes to "
                             f"{header.nbytes / 2**20:.0f} MiB, more than the memory budget; "
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


