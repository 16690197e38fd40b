"""How far a pixel's samples reach: the halo a window needs so that it blurs exactly as the
whole image does (``clblur.tiling``, ``clblur.dask_array``).

Conventions
-----------
* Halo, per axis: ``ceil(reach) + 2``.  ``reach`` is the farthest a sample lies from its pixel:
  ``max |v_axis| * max(a, 1 - a)`` for a uniform or per-pixel motion (samples lie at
  ``p - v (s - a)`` with ``s`` in [0, 1]; anchor ``a``), the kernel's extent from its centre
  for a PSF.  ``+1`` is the bilinear neighbour, ``+1`` a margin for sample positions that a
  float32 kernel rounds past the exact reach.
* Flows are read window by window (array-likes from ``clblur.io``), never whole.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.io import as_array_like, open_flow
from clblur.motion import PSF, Field, Uniform, parse_motion, psf

__all__ = ["TiledMotion", "fixed_halo", "flow_halo", "global_flow_halo", "halo_for_reach",
           "reach", "tiled_motion"]


@dataclass(frozen=True)
class TiledMotion:
    """The motion of a tiled run: a uniform vector or PSF (in memory), or a flow array-like
    read window by window."""

    fixed: Uniform | PSF | None = None
    flow: object | None = None  # array-like H x W x 2


def tiled_motion(motion, shape: tuple[int, int]) -> TiledMotion:
    """Classify ``motion`` without loading a flow field: ``(dx, dy)``, an H x W x 2 array-like
    (numpy, np.memmap, zarr, MappedRaster), a ``.npy``/``.flo`` path, or a 2-D PSF."""
    if isinstance(motion, (Uniform, PSF)):
        return TiledMotion(fixed=parse_motion(motion, (1, 1)))
    if isinstance(motion, Field):
        motion = motion.flow
    if isinstance(motion, (str, os.PathLike)):
        motion = open_flow(motion)
    if not hasattr(motion, "shape"):
        motion = np.asarray(motion)
    if np.ndim(motion) == 1 or tuple(motion.shape) == (2,):
        return TiledMotion(fixed=parse_motion(motion, (1, 1)))
    if len(motion.shape) == 2:
        return TiledMotion(fixed=psf(np.asarray(motion)))
    if len(motion.shape) == 3:
        h, w = shape
        if tuple(motion.shape) != (h, w, 2):
            raise InputError(f"flow field has shape {tuple(motion.shape)}, expected "
                             f"({h}, {w}, 2) to match the image")
        if np.dtype(motion.dtype).kind not in "fiu":
            raise InputTypeError(f"flow field must be numeric, got dtype {motion.dtype}")
        return TiledMotion(flow=as_array_like(motion))
    raise InputError(f"motion has shape {tuple(motion.shape)}; expected (2,), (H, W, 2) or a "
                     "2-D PSF")


def halo_for_reach(reach: float) -> int:
    """Halo for a sample reach (pixels): see the module conventions."""
    return int(math.ceil(reach)) + 2


def fixed_halo(motion: Uniform | PSF, anchor: float) -> tuple[int, int]:
    """(rows, cols) halo of a uniform motion or PSF."""
    if isinstance(motion, PSF):
        kh, kw = motion.kernel.shape
        cy, cx = motion.center
        return halo_for_reach(max(cy, kh - 1 - cy)), halo_for_reach(max(cx, kw - 1 - cx))
    f = max(anchor, 1.0 - anchor)
    dx, dy = np.float32(motion.dx), np.float32(motion.dy)
    return halo_for_reach(abs(float(dy)) * f), halo_for_reach(abs(float(dx)) * f)


def flow_halo(flow: np.ndarray, anchor: float) -> tuple[int, int]:
    """(rows, cols) halo covering every vector of ``flow`` (any H x W x 2 block)."""
    v = np.asarray(flow).reshape(-1, 2)
    if v.size == 0:
        return halo_for_reach(0.0), halo_for_reach(0.0)
    if v.dtype == np.float16:  # numpy reduces float16 slowly; the float32 copy is exact
        v = v.astype(np.float32)
    # per-column max and min: no |v| temporary, and fast on the strided columns
    amax = np.array([max(abs(float(v[:, k].max())), abs(float(v[:, k].min())))
                     for k in (0, 1)])
    if not np.isfinite(amax).all():
        raise InputError("flow field contains NaN or infinite values")
    f = max(anchor, 1.0 - anchor)
    return halo_for_reach(amax[1] * f), halo_for_reach(amax[0] * f)


def global_flow_halo(flow, anchor: float, rows_per_read: int) -> tuple[int, int]:
    """The largest halo over the whole flow, read in bands of ``rows_per_read`` rows."""
    hy = hx = halo_for_reach(0.0)
    for r in range(0, flow.shape[0], max(rows_per_read, 1)):
        y, x = flow_halo(flow[r:r + rows_per_read], anchor)
        hy, hx = max(hy, y), max(hx, x)
    return hy, hx


def reach(v: np.ndarray, anchor: float) -> float:
    """Farthest any sample of ``v`` lands from its pixel: ``max |v| * max(a, 1 - a)``."""
    if not v.size:
        return 0.0
    x, y = v[..., 0], v[..., 1]
    longest = math.sqrt(float(np.max(x * x + y * y)))  # float32 squares, rounded up below
    return longest * (1 + 1e-6) * max(anchor, 1.0 - anchor)
