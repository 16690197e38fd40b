"""Netpbm files (``.ppm``, ``.pgm``, ``.pnm``): the raw format of classic exposure series.

Debevec & Malik's stacks (the Memorial church among them) were distributed as binary PPM, and
``dcraw`` writes its linear 16-bit output as PPM too, so a calibration input may well be one.
The format is simple enough to read and write here without a decoder library, which keeps its
errors ours (OpenCV prints a truncated file's error on stderr before returning nothing).

Conventions
-----------
* Read: grey ``P2``/``P5`` and colour ``P3``/``P6`` (plain ASCII and binary), ``#`` comments in
  the header; one image per file (the first).  Bilevel ``P1``/``P4`` and ``PAM`` (``P7``) are
  refused with their name.
* Samples are ``value / maxval`` of full scale.  ``maxval`` 255 and 65535 come back as the
  codes (uint8, uint16); any other ``maxval`` is rescaled to the full scale of the smallest of
  those that holds it (a 12-bit file, ``maxval`` 4095, becomes uint16 with 4095 -> 65535), so
  that full scale means the dtype's maximum everywhere in clblur.
* Write: uint8 or uint16, grey as ``P5`` and RGB as ``P6`` (big-endian 16-bit samples, as the
  format says); ``.pgm`` takes grey only and ``.ppm`` colour only; alpha and floats are
  refused (Netpbm has no place for them).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io.atomic import atomic_write

__all__ = ["probe", "read_image", "write_image"]

_CHANNELS = {b"P2": 1, b"P5": 1, b"P3": 3, b"P6": 3}
_OTHER = {b"P1": "bilevel PBM", b"P4": "bilevel PBM", b"P7": "PAM"}
_HEADER_BYTES = 4096  # a header with comments longer than this is not an image file


def _header(head: bytes, path: Path) -> tuple[bytes, int, int, int, int]:
    """``(magic, width, height, maxval, offset of the first sample)`` of a Netpbm header."""
    magic = head[:2]
    if magic in _OTHER:
        raise InputError(f"cannot read image {path}: {_OTHER[magic]} files are not supported "
                         "(convert to PGM or PPM)")
    if magic not in _CHANNELS:
        raise InputError(f"cannot read image {path}: not a Netpbm file (no P2, P3, P5 or P6 "
                         "magic number)")
    fields: list[int] = []
    i = 2
    while len(fields) < 3:
        while i < len(head) and head[i:i + 1].isspace():
            i += 1
        if head[i:i + 1] == b"#":  # a comment runs to the end of its line
            end = head.find(b"\n", i)
            i = len(head) if end < 0 else end + 1
            continue
        j = i
        while j < len(head) and head[j:j + 1].isdigit():
            j += 1
        if j == i or j >= len(head):
            raise InputError(f"cannot read image {path}: corrupt or truncated Netpbm header")
        fields.append(int(head[i:j]))
        i = j
    width, height, maxval = fields
    if not head[i:i + 1].isspace():
        raise InputError(f"cannot read image {path}: corrupt Netpbm header (no whitespace "
                         "after maxval)")
    if width < 1 or height < 1:
        raise InputError(f"image {path} declares an empty size {width} x {height}")
    if not 1 <= maxval <= 65535:
        raise InputError(f"cannot read image {path}: Netpbm maxval {maxval} is outside "
                         "1 .. 65535")
    return magic, width, height, maxval, i + 1  # one whitespace byte ends the header


def probe(path: str | os.PathLike) -> tuple[int, int, int, int]:
    """``(height, width, channels, bytes per sample)`` from the header alone."""
    path = Path(path)
    with path.open("rb") as f:
        magic, width, height, maxval, _ = _header(f.read(_HEADER_BYTES), path)
    return height, width, _CHANNELS[magic], 1 if maxval < 256 else 2


def read_image(path: str | os.PathLike) -> np.ndarray:
    """A PGM or PPM as H x W (grey) or H x W x 3 uint8 / uint16 (module Conventions)."""
    path = Path(path)
    data = path.read_bytes()
    magic, width, height, maxval, start = _header(data[:_HEADER_BYTES], path)
    channels = _CHANNELS[magic]
    count = width * height * channels
    if magic in (b"P5", b"P6"):
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
        if len(data) - start < count * dtype.itemsize:
            raise InputError(f"cannot read image {path}: truncated Netpbm file (needs "
                             f"{count * dtype.itemsize} bytes of samples, has "
                             f"{len(data) - start})")
        values = np.frombuffer(data, dtype, count, start).astype(np.int64)
    else:  # plain (ASCII) samples, whitespace separated; comments only in the header
        tokens = data[start - 1:].split()
        if len(tokens) < count:
            raise InputError(f"cannot read image {path}: truncated Netpbm file ({len(tokens)} "
                             f"of {count} samples)")
        try:
            values = np.array([int(t) for t in tokens[:count]], dtype=np.int64)
        except ValueError:
            raise InputError(f"cannot read image {path}: a plain Netpbm sample is not an "
                             "integer") from None
    if values.size and values.max() > maxval:
        raise InputError(f"cannot read image {path}: a sample exceeds maxval {maxval} "
                         f"({values.max()})")
    out_dtype, top = (np.uint8, 255) if maxval <= 255 else (np.uint16, 65535)
    if maxval != top:  # value / maxval of full scale, rounded to the dtype's codes
        values = (values * (2 * top) + maxval) // (2 * maxval)
    shape = (height, width) if channels == 1 else (height, width, channels)
    return values.astype(out_dtype).reshape(shape)


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write ``image`` (uint8 or uint16, grey or RGB) as binary PGM / PPM, atomically."""
    path = Path(path)
    if image.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{path.suffix} holds 8- or 16-bit integer codes, not {image.dtype}; "
                         "write .tif, .tiff or .exr instead")
    grey = image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1)
    colour = image.ndim == 3 and image.shape[2] == 3
    if not (grey or colour):
        raise InputError(f"{path}: Netpbm holds grey or RGB, not {image.shape[2]} channels "
                         "(no alpha); write .png or .tif")
    suffix = path.suffix.lower()
    if (suffix == ".pgm" and colour) or (suffix == ".ppm" and grey):
        raise InputError(f"{path}: {suffix} holds {'grey' if suffix == '.pgm' else 'colour'} "
                         f"images; write {'.ppm' if colour else '.pgm'} or .pnm")
    height, width = image.shape[:2]
    maxval = 255 if image.dtype == np.uint8 else 65535
    head = f"{'P5' if grey else 'P6'}\n{width} {height}\n{maxval}\n".encode()
    body = np.ascontiguousarray(image, dtype=">u2" if maxval > 255 else np.uint8).tobytes()
    atomic_write(path, lambda tmp: tmp.write_bytes(head + body))
