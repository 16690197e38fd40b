"""Blur images held as Dask arrays (e.g. opened from zarr) with ``map_overlap``.

Conventions
-----------
* Each output chunk is computed from its chunk grown by ``depth`` (the halo of
  ``clblur.tiling``: ``ceil(reach) + 2`` per axis) with ``boundary="none"``: nothing is
  invented outside the image.  The block function locates its window in the full image from
  the chunk grid and blurs it with ``make_plan(..., region=...)``, so positions clamp to the
  *image* edge exactly as in the in-memory blur, and returns only its own chunk
  (``trim=False``; output chunks = input chunks).  Result: bitwise ``clblur.blur`` on the same
  backend.
* Dask needs one depth for all chunks, so a flow field's depth comes from its largest vector:
  computed here (one pass over the flow) unless ``max_displacement=(max |dx|, max |dy|)`` is
  given.  Chunks smaller than the depth are merged by rechunking.
* Backends are chosen inside the worker (``"auto"``: OpenCL when that process has a device), so
  OpenCL objects are never created in the client nor pickled.
"""

from __future__ import annotations

from functools import partial

import dask.array as da
import numpy as np

from clblur.blur import blur_plan, check_backend
from clblur.halo import fixed_halo, halo_for_reach, tiled_motion
from clblur.motion import PSF, Uniform, anchor_value
from clblur.request import make_plan

__all__ = ["blur"]


def blur(array, motion, response="exp", *, anchor: str = "center", samples: int | None = None,
         weights=None, backend: str = "auto", saturation: float = 1.0,
         device: str | None = None, max_displacement: tuple[float, float] | None = None,
         exposure: str = "frames"):
    """Lazy photo-consistent blur of an H x W or H x W x C Dask array (see ``clblur.blur``).

    ``motion``: ``(dx, dy)``, a 2-D PSF, or an H x W x 2 flow (numpy, zarr or Dask array, or
    a ``.npy`` path read chunk by chunk).  Returns a Dask array with the input's shape and
    dtype, and its chunks except that channels form one chunk and chunks narrower than the
    halo are merged.
    """
    if not isinstance(array, da.Array):
        raise TypeError(f"array must be a dask array, got {type(array).__name__}")
    if array.ndim not in (2, 3):
        raise ValueError(f"image must be H x W or H x W x C, got shape {array.shape}")
    check_backend(backend)
    h, w = array.shape[:2]
    a = anchor_value(anchor)
    flow = None
    if isinstance(motion, da.Array) and motion.ndim == 3:
        flow = motion
        if motion.shape != (h, w, 2):
            raise ValueError(f"flow field has shape {motion.shape}, expected ({h}, {w}, 2) to "
                             "match the image")
        fixed = None
    else:
        tm = tiled_motion(motion, (h, w))
        fixed = tm.fixed
        if tm.flow is not None:  # numpy, zarr or a file read window by window
            flow = da.from_array(tm.flow, chunks=(array.chunks[0], array.chunks[1], 2))
    # Validate every option now, in the client, so errors surface before compute().
    make_plan(np.zeros((1, 1) + array.shape[2:], array.dtype), (0.0, 0.0), response,
              anchor=anchor, samples=samples, weights=weights, saturation=saturation,
              exposure=exposure)
    if flow is not None:
        depth = _flow_depth(flow, a, max_displacement)
    else:
        depth = fixed_halo(fixed, a)
    if array.ndim == 3:
        array = array.rechunk({2: -1})
    array = _rechunk_at_least(array, depth)
    options = dict(response=response, anchor=anchor, samples=samples, weights=weights,
                   exposure=exposure, saturation=saturation, backend=backend, device=device,
                   fixed=fixed,
                   halo=depth, grid=array.chunks[:2], extent=(h, w))
    axes = {0: depth[0], 1: depth[1]}
    if array.ndim == 3:
        axes[2] = 0
    block = partial(_blur_block, **options)
    meta = np.empty((0,) * array.ndim, array.dtype)
    if flow is None:
        return da.map_overlap(block, array, depth=axes, boundary="none", trim=False,
                              dtype=array.dtype, chunks=array.chunks, meta=meta)
    flow = flow.rechunk((array.chunks[0], array.chunks[1], 2))
    return da.map_overlap(block, array, flow, depth=[axes, {0: depth[0], 1: depth[1], 2: 0}],
                          boundary="none", trim=False, dtype=array.dtype, chunks=array.chunks,
                          meta=meta, align_arrays=False)


def _flow_depth(flow, anchor: float, max_displacement) -> tuple[int, int]:
    if max_displacement is None:
        amax = np.asarray(da.abs(flow.astype(np.float32)).max(axis=(0, 1)).compute(),
                          dtype=np.float64)
    else:
        amax = np.abs(np.asarray(max_displacement, dtype=np.float64))
        if amax.shape != (2,):
            raise ValueError(f"max_displacement must be (max |dx|, max |dy|), got "
                             f"{max_displacement!r}")
    if not np.isfinite(amax).all():
        raise ValueError("flow field contains NaN or infinite values")
    f = max(anchor, 1.0 - anchor)
    return halo_for_reach(amax[1] * f), halo_for_reach(amax[0] * f)


def _rechunk_at_least(array, depth: tuple[int, int]):
    """Merge chunks narrower than the depth into a neighbour (map_overlap takes each halo from
    the adjacent chunk only, so a chunk must be at least as wide as the depth)."""
    new = {}
    for axis in (0, 1):
        sizes = list(array.chunks[axis])
        if min(sizes) >= depth[axis]:
            continue
        while len(sizes) > 1 and min(sizes) < depth[axis]:
            i = sizes.index(min(sizes))
            j = i - 1 if i > 0 else i + 1
            sizes[min(i, j)] = sizes[i] + sizes[j]
            del sizes[max(i, j)]
        new[axis] = tuple(sizes)
    return array.rechunk(new) if new else array


def _origin(index: int, chunks: tuple[int, ...], depth: int) -> tuple[int, int]:
    """(start of the grown window, start of the chunk) along one axis."""
    start = int(sum(chunks[:index]))
    return max(start - depth, 0), start


def _blur_block(image, flow=None, *, response, anchor, samples, weights, exposure, saturation,
                backend, device, fixed: Uniform | PSF | None, halo, grid, extent,
                block_info=None):
    loc = block_info[0]["chunk-location"]
    (wr0, r0), (wc0, c0) = (_origin(loc[i], grid[i], halo[i]) for i in (0, 1))
    th, tw = grid[0][loc[0]], grid[1][loc[1]]
    motion = fixed if flow is None else flow
    plan = make_plan(image, motion, response, anchor=anchor, samples=samples, weights=weights,
                     saturation=saturation, region=(wr0, wc0, *extent), exposure=exposure)
    out = blur_plan(plan, backend, device)
    return out[r0 - wr0:r0 - wr0 + th, c0 - wc0:c0 - wc0 + tw]
