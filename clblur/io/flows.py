"""Flow fields and PSF files.

Conventions
-----------
* A flow is H x W x 2 (dx, dy) in pixels, x right, y down; files are ``.npy`` (any real
  dtype) or Middlebury ``.flo`` (little-endian float32 with a 202021.25 tag).
* ``open_flow`` maps a ``.npy`` window by window (``MappedRaster``); ``read_flow`` reads whole.
* A PSF is a 2-D non-negative kernel in an image file (grey, any scale) or a ``.npy``, at most
  ``MAX_PSF_SIDE`` on a side (checked from the header, before reading).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io.atomic import atomic_write
from clblur.io.images import read_image
from clblur.io.paths import require_file
from clblur.io.raster import MappedRaster

__all__ = ["FLO_MAGIC", "MAX_PSF_SIDE", "exr_part", "open_flow", "read_depth", "read_flow",
           "read_psf", "write_flow"]

FLO_MAGIC = 202021.25  # Middlebury .flo tag
MAX_PSF_SIDE = 4096


def _open_npy(path: Path, what: str) -> np.ndarray:
    """A ``.npy`` memory-mapped (nothing read yet), with a one-line error for a bad file."""
    require_file(path, what)
    with path.open("rb") as f:  # numpy's own message for another format is about pickles
        if f.read(6) != b"\x93NUMPY":
            kinds = " (a flow is read from .npy, .flo or .exr)" if what == "flow" else ""
            raise InputError(f"{what} {path} is not a NumPy .npy file{kinds}")
    try:
        m = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as e:  # numpy raises several types for corrupt headers or short data
        raise InputError(f"cannot read {what} {path}: {e}".splitlines()[0]) from None
    if not isinstance(m, np.ndarray) or m.dtype.kind not in "fiu":
        raise InputError(f"{what} {path} must hold real numbers, got "
                         f"{getattr(m, 'dtype', type(m).__name__)}")
    return m


def _check_flow_shape(shape: tuple[int, ...], path: Path) -> None:
    if len(shape) != 3 or shape[2] != 2 or shape[0] < 1 or shape[1] < 1:
        raise InputError(f"flow {path} has shape {shape}, expected H x W x 2")


def read_flow(path: str | os.PathLike) -> np.ndarray:
    """Read a flow field (.npy H x W x 2, Middlebury .flo, or EXR flow.x/flow.y) whole, as
    float32."""
    path = Path(path)
    require_file(path, "flow")
    if path.suffix.lower() == ".exr":
        from clblur.io import exr

        return exr.read_flow(path)
    if path.suffix.lower() == ".flo":
        size = path.stat().st_size
        with path.open("rb") as f:
            head = f.read(12)
            if len(head) < 12 or np.frombuffer(head[:4], "<f4")[0] != FLO_MAGIC:
                raise InputError(f"flow {path} is not a Middlebury .flo file (bad header)")
            w, h = (int(v) for v in np.frombuffer(head[4:12], "<i4"))
            if w <= 0 or h <= 0 or size != 12 + 8 * w * h:  # checked before reading the data
                raise InputError(f"flow {path}: truncated or malformed .flo ({w} x {h} declared, "
                                 f"{size} bytes)")
            return np.frombuffer(f.read(), "<f4").reshape(h, w, 2).copy()
    m = _open_npy(path, "flow")
    _check_flow_shape(tuple(m.shape), path)
    return np.asarray(m, dtype=np.float32)


def open_flow(path: str | os.PathLike):
    """A flow file as an array-like: ``.npy`` mapped window by window, ``.flo`` read whole."""
    path = Path(path)
    if path.suffix.lower() != ".npy":
        return read_flow(path)
    m = _open_npy(path, "flow")
    _check_flow_shape(tuple(m.shape), path)
    if not m.flags.c_contiguous:  # Fortran-ordered .npy: rare; small enough to load
        return np.ascontiguousarray(m, dtype=np.float32)
    return MappedRaster(path, m.dtype, m.shape, m.offset)


def write_flow(path: str | os.PathLike, flow: np.ndarray) -> None:
    """Write a flow field as .flo, .exr or .npy (by suffix), atomically."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        from clblur.io import exr

        exr.write_flow(path, flow)
        return
    flow = np.asarray(flow, dtype=np.float32)
    if path.suffix.lower() == ".flo":
        h, w = flow.shape[:2]
        data = (np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
                + flow.astype("<f4").tobytes())
        atomic_write(path, lambda tmp: tmp.write_bytes(data))
    else:
        atomic_write(path, lambda tmp: np.save(tmp, flow))


def read_psf(path: str | os.PathLike) -> np.ndarray:
    """Read a PSF from an image (grey, any scale) or .npy; returned as float64 (unnormalised,
    validated by ``clblur.motion.psf`` when used)."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        m = _open_npy(path, "PSF")
        shape = tuple(m.shape)
    else:
        from clblur.io.images import probe_image

        header = probe_image(path)
        shape = (header.height, header.width)
        m = None
    if len(shape) < 2 or max(shape[:2]) > MAX_PSF_SIDE:
        raise InputError(f"PSF {path} has shape {shape}; expected a 2-D kernel at most "
                         f"{MAX_PSF_SIDE} px on a side")
    k = np.array(m) if m is not None else read_image(path)
    if k.ndim == 3 and m is None:
        k = _kernel_weights(k)
    if k.ndim != 2:
        raise InputError(f"PSF {path} has shape {k.shape}; expected a 2-D kernel")
    k = np.asarray(k, dtype=np.float64)
    if not np.isfinite(k).all() or (k < 0).any() or k.sum() <= 0:
        raise InputError(f"PSF {path} must be finite, non-negative and not all zero")
    if m is None and k.size > 1 and 0 < k.min() < 0.2 * k.max():
        # an image whose every pixel holds light, but faintly at its darkest: a background
        # (scanner, screenshot) under the kernel, which blurs as light (a box is all peak)
        warnings.warn(f"PSF {path}: no pixel is black (the darkest holds {k.min() / k.max():.1%} "
                      "of the peak), and that floor blurs as light; subtract the background "
                      "if it is one", stacklevel=2)
    return k


def _kernel_weights(image: np.ndarray) -> np.ndarray:
    """A kernel image's weights: the mean of its colour channels, times its coverage where it
    has an alpha channel (2 or 4 channels): a white-on-transparent kernel drawn in an editor
    has colour everywhere and weight only where it is opaque."""
    from clblur.pixels import imax

    channels = image.shape[2]
    has_alpha = channels in (2, 4)
    weight = image[..., :channels - 1 if has_alpha else 3].astype(np.float64).mean(axis=2)
    if has_alpha:
        alpha = image[..., -1].astype(np.float64)
        weight *= alpha / imax(image.dtype) if image.dtype.kind == "u" else alpha
    return weight


def exr_part(spec: str | os.PathLike) -> tuple[str, str | None]:
    """``(file, EXR name or None)`` of a file spec: ``FILE``, or ``FILE.exr:NAME`` naming a
    channel (a depth spec: ``FILE.exr:CHANNEL``) or a layer prefix (``clblur blur-layers``:
    ``render.exr:Ball.Combined``).  The one parser for readers and output checks."""
    spec = os.fspath(spec)
    head, sep, channel = spec.rpartition(":")
    if sep and head.lower().endswith(".exr"):
        return head, channel
    return spec, None


def read_depth(path: str | os.PathLike) -> np.ndarray:
    """A depth map or layer IDs, H x W, from a ``.npy`` file or a channel of an EXR file.

    ``FILE.exr`` finds ``Z`` / ``depth.Z`` / ``<layer>.Depth.Z``; ``FILE.exr:CHANNEL`` names
    the channel.  Smaller is nearer (see ``clblur.blur``'s ``depth``).
    """
    path, channel = exr_part(path)
    if path.lower().endswith(".exr"):
        from clblur.io.exr import read_depth as read_exr_depth

        return read_exr_depth(path, channel)
    if not path.lower().endswith(".npy"):
        raise InputError(f"depth must be a .npy file (H x W) or an EXR depth channel "
                         f"(FILE.exr or FILE.exr:CHANNEL), got {path}")
    return np.array(_open_npy(Path(path), "depth"))
