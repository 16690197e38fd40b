"""Blur images held as Dask arrays (e.g. opened from zarr), chunk by chunk with halos.

Conventions
-----------
* Each output chunk is computed from its chunk grown by a halo (``clblur.halo``:
  ``ceil(reach) + 2`` per axis, clipped to the image): nothing is invented outside the image.
  The window is blurred with ``make_plan(..., region=...)``, so positions clamp to the *image*
  edge exactly as in the in-memory blur, and only the chunk is kept.  Result: bitwise
  ``clblur.blur`` on the same backend.  Output chunks are the input's, except that channels
  form one chunk.
* A flow field's halo is each chunk's own: from the largest ``|dx|`` and ``|dy|`` among the
  chunk's pixels (one pass over the flow, at graph time), since a pixel's samples land within
  its own vector's reach.  A fast object then grows only the windows of the chunks it covers,
  as ``clblur.tiling`` does for tiles, and a window may span several input chunks.
* With ``max_displacement=(max |dx|, max |dy|)`` (no pass over the flow) or a uniform motion or
  PSF, every chunk has the same halo and ``map_overlap`` runs (``boundary="none"``,
  ``trim=False``); chunks smaller than that halo are merged by rechunking, since
  ``map_overlap`` takes a halo from the adjacent chunk only.  Each chunk checks its own
  vectors against that halo when it is computed: a bound that does not hold is an
  ``InputError`` naming the chunk, never a result wrong at the seams.
* Backends are chosen inside the worker (``"auto"``: OpenCL when that process has a device), so
  OpenCL objects are never created in the client nor pickled.
"""

from __future__ import annotations

from functools import partial

import dask.array as da
import numpy as np

from clblur.blur import blur_plan, check_backend
from clblur.errors import InputError, InputTypeError
from clblur.halo import fixed_halo, flow_halo, halo_for_reach, tiled_motion
from clblur.motion import PSF, Uniform, anchor_value
from clblur.request import make_plan

__all__ = ["blur"]


def blur(array, motion, response="exp", *, anchor: str = "center", samples: int | None = None,
         weights=None, backend: str = "auto", saturation: float = 1.0,
         device: str | None = None, max_displacement: tuple[float, float] | None = None,
         exposure: str = "frames"):
    """Lazy photo-consistent blur of an H x W or H x W x C Dask array (see ``clblur.blur``).

    ``motion``: ``(dx, dy)``, a 2-D PSF, or an H x W x 2 flow (numpy, zarr or Dask array, or
    a ``.npy`` path read chunk by chunk).  ``max_displacement``: a bound on the flow's
    ``(|dx|, |dy|)``, which saves the pass over the flow that sizes each chunk's own halo
    (module Conventions).  Returns a Dask array with the input's shape and dtype, and its
    chunks except that channels form one chunk and, with one halo for all chunks (a uniform
    motion, a PSF or ``max_displacement``), chunks narrower than it are merged.
    """
    if not isinstance(array, da.Array):
        raise InputTypeError(f"array must be a dask array, got {type(array).__name__}")
    if array.ndim not in (2, 3):
        raise InputError(f"image must be H x W or H x W x C, got shape {array.shape}")
    check_backend(backend)
    h, w = array.shape[:2]
    a = anchor_value(anchor)
    flow = None
    if isinstance(motion, da.Array) and motion.ndim == 3:
        flow = motion
        if motion.shape != (h, w, 2):
            raise InputError(f"flow field has shape {motion.shape}, expected ({h}, {w}, 2) to "
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
    # one layout inside: H x W x C (a grey image is given back as it came, H x W); with a
    # flow beside it, map_overlap needs both arrays of one rank
    grey = array.ndim == 2
    array = (array[..., None] if grey else array).rechunk({2: -1})
    out = _blur_hwc(array, flow, fixed, a, (h, w), max_displacement,
                    dict(response=response, anchor=anchor, samples=samples, weights=weights,
                         exposure=exposure, saturation=saturation, backend=backend,
                         device=device))
    return out[..., 0] if grey else out


def _blur_hwc(array, flow, fixed, a: float, extent: tuple[int, int], max_displacement,
              blur_options: dict):
    """:func:`blur` of an H x W x C array (its channels one chunk)."""
    h, w = extent
    if flow is not None and max_displacement is None:
        flow = flow.rechunk((array.chunks[0], array.chunks[1], 2))
        return _blur_own_halos(array, flow, _chunk_halos(flow, a), blur_options)
    bound = None
    if flow is not None:
        depth = _flow_depth(max_displacement, a)
        bound = (tuple(float(b) for b in np.abs(np.asarray(max_displacement, np.float64))), a)
    else:
        depth = fixed_halo(fixed, a)
    # a halo beyond the image is the image (positions clamp to its edge): along an axis no
    # longer than the halo the chunks merge into one, which needs no overlap at all (and
    # map_overlap refuses a depth larger than the array)
    depth = (min(depth[0], h), min(depth[1], w))
    array = _rechunk_at_least(array, depth)
    depth = tuple(0 if len(array.chunks[i]) == 1 else depth[i] for i in (0, 1))
    options = dict(blur_options, fixed=fixed, halo=depth, grid=array.chunks[:2], extent=(h, w),
                   bound=bound)
    axes = {0: depth[0], 1: depth[1], 2: 0}
    block = partial(_blur_block, **options)
    meta = np.empty((0,) * array.ndim, array.dtype)
    if flow is None:
        return da.map_overlap(block, array, depth=axes, boundary="none", trim=False,
                              dtype=array.dtype, chunks=array.chunks, meta=meta)
    flow = flow.rechunk((array.chunks[0], array.chunks[1], 2))
    return da.map_overlap(block, array, flow, depth=[axes, {0: depth[0], 1: depth[1], 2: 0}],
                          boundary="none", trim=False, dtype=array.dtype, chunks=array.chunks,
                          meta=meta, align_arrays=False)


def _flow_depth(max_displacement, anchor: float) -> tuple[int, int]:
    """The (rows, cols) halo of every chunk from the caller's bound on the vectors."""
    amax = np.abs(np.asarray(max_displacement, dtype=np.float64))
    if amax.shape != (2,):
        raise InputError(f"max_displacement must be (max |dx|, max |dy|), got "
                         f"{max_displacement!r}")
    if not np.isfinite(amax).all():
        raise InputError("flow field contains NaN or infinite values")
    f = max(anchor, 1.0 - anchor)
    return halo_for_reach(amax[1] * f), halo_for_reach(amax[0] * f)


def _chunk_halos(flow, anchor: float) -> np.ndarray:
    """The (rows, cols) halo of each chunk of ``flow`` from its own vectors
    (``clblur.halo.flow_halo``; rows x cols of chunks x 2 int), computed now (one pass over
    the flow)."""

    def own(block: np.ndarray) -> np.ndarray:
        return np.array(flow_halo(block, anchor)).reshape(1, 1, 2)

    return np.asarray(flow.map_blocks(own, chunks=(1, 1, 2), dtype=np.int64).compute())


def _blur_own_halos(array, flow, halos: np.ndarray, options: dict):
    """Each chunk blurred from a window grown by its own halo (module Conventions)."""
    h, w = array.shape[:2]
    starts = [np.concatenate([[0], np.cumsum(c)]).astype(int) for c in array.chunks[:2]]
    meta = np.empty((0,) * array.ndim, array.dtype)
    rows = []
    for i, th in enumerate(array.chunks[0]):
        row = []
        for j, tw in enumerate(array.chunks[1]):
            hy, hx = min(int(halos[i, j, 0]), h), min(int(halos[i, j, 1]), w)
            r0, c0 = int(starts[0][i]), int(starts[1][j])
            win = (slice(max(r0 - hy, 0), min(r0 + th + hy, h)),
                   slice(max(c0 - hx, 0), min(c0 + tw + hx, w)))
            # the window as one block of each array, blurred into the chunk's one block
            image_w, flow_w = (a[win].rechunk(-1) for a in (array, flow))
            row.append(da.map_blocks(
                _blur_window, image_w, flow_w, origin=(win[0].start, win[1].start),
                chunk=(r0, c0, th, tw), extent=(h, w), **options,
                chunks=((th,), (tw,)) + tuple((n,) for n in array.shape[2:]),
                dtype=array.dtype, meta=meta))
        rows.append(da.concatenate(row, axis=1))
    return da.concatenate(rows, axis=0)


def _blur_window(image, motion, *, origin, chunk, extent, response, anchor, samples, weights,
                 exposure, saturation, backend, device):
    """One chunk of the blur, from its window (``origin``: the window's top-left pixel;
    ``chunk``: (row, col, height, width) of the chunk in the image; ``motion``: the window's
    flow, or the uniform motion or PSF)."""
    wr0, wc0 = origin
    r0, c0, th, tw = chunk
    plan = make_plan(image, motion, response, anchor=anchor, samples=samples, weights=weights,
                     saturation=saturation, region=(wr0, wc0, *extent), exposure=exposure)
    out = blur_plan(plan, backend, device)
    return out[r0 - wr0:r0 - wr0 + th, c0 - wc0:c0 - wc0 + tw]


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


def _blur_block(image, flow=None, *, fixed: Uniform | PSF | None, halo, grid, extent,
                bound: tuple | None, block_info=None, **options):
    """One chunk of ``map_overlap``: its window located from the chunk grid.  ``bound``: the
    caller's ``max_displacement`` (and the anchor), which sized the halo; a
    chunk whose own vectors reach beyond that halo is refused, since its samples would be
    read from outside the window (the result would be wrong at the seams, silently)."""
    loc = block_info[0]["chunk-location"]
    (wr0, r0), (wc0, c0) = (_origin(loc[i], grid[i], halo[i]) for i in (0, 1))
    th, tw = grid[0][loc[0]], grid[1][loc[1]]
    if bound is not None:
        (bx, by), anchor = bound
        own = flow[r0 - wr0:r0 - wr0 + th, c0 - wc0:c0 - wc0 + tw]
        need = flow_halo(own, anchor)  # what the chunk's own vectors reach
        if any(len(grid[i]) > 1 and need[i] > halo[i] for i in (0, 1)):
            most = np.abs(np.asarray(own, np.float64)).reshape(-1, 2).max(axis=0)
            raise InputError(
                f"the flow exceeds max_displacement=({bx:g}, {by:g}): |dx| up to {most[0]:g} "
                f"and |dy| up to {most[1]:g} in the chunk at row {r0}, column {c0}; give a "
                "bound that holds, or none (each chunk's halo is then sized from its own "
                "vectors)")
    return _blur_window(image, fixed if flow is None else flow, origin=(wr0, wc0),
                        chunk=(r0, c0, th, tw), extent=extent, **options)
