"""The pixels that take the layered path, on the OpenCL device.

``clblur.layered_exposure.region_mask`` (the specification) on the device: one upload of the
vectors, six kernels (``region.cl``) whose arrays stay on the device, one small download
for the reach, one download of the mask.  Why: on a GPU host the numpy version cost about
twice the device's whole gather (1280 x 720 on an H100 host, 2026-11-26: 15.8 ms numpy,
1.9 ms here, upload and download included; 7 ms and 5.4 ms on this repo's 2-core PoCL VM).

Conventions
-----------
* The vectors are read as float32 (a float16 field widens exactly; a float64 one is rounded,
  where the reference would compare in float64).  The reach ``R``: ``clblur.halo.reach``
  on the vectors as given, as the reference takes it; for float32 vectors the device finds
  each tile's longest (``x * x + y * y`` in float32 as numpy forms it) and the host finishes
  ``reach`` from those (the same value, without the host's 1 - 2 ms pass over the field).
* The flagged tiles, the motion edges, ``varies`` and ``near`` (within ``R + 2`` of an edge
  pixel) are the reference's bit for bit: min, max and one float32 subtraction compared with
  ``spread`` as numpy compares them, and the distance test in integers against the largest
  squared distance ``k2`` whose double square root is ``<= R + 2`` (the reference's test,
  whichever exact distance transform it is given).
* The reference computes edges on a crop around the flagged tiles (``ceil(R) + 4`` px
  beyond them); the kernels compute them on the whole image.  The two differ only within
  one pixel of the crop's border, which lies more than ``R + 2`` from every flagged pixel, so
  no flagged pixel's ``near``, ``varies`` or vector reads see the difference.
* The inverse departure is read bilinearly in float32, the reference's with ``cv2.remap``,
  which rounds reading positions to 1/32 px.  Every pixel such a read touches lies within
  ``R + sqrt(2)`` of a pixel that is not ``near``, so it is no motion edge and neighbouring
  vectors differ by at most ``spread``: the two departures differ by at most
  ``spread / 32 * |t|`` (and float32 rounding), and the masks only at pixels whose departure
  lies that close to ``spread`` (``tests/test_opencl_region.py`` checks each such pixel).
"""

from __future__ import annotations

import math

import numpy as np

from clblur.halo import reach
from clblur.layered_exposure import SPREAD_PX, TILE
from clblur.opencl.device import pyopencl_module
from clblur.opencl.program import Program

__all__ = ["CPU_RUN", "MAX_SIDE", "near_limit", "region_and_reach", "region_mask"]

MAX_SIDE = 32767  # squared distances and flat offsets in int32 (edge_gaps, region)
PIXEL_LOCAL = (32, 8)  # work-group of the per-pixel kernels: a warp-wide row on a GPU
TILE_LOCAL = (8, 8)  # of the per-tile kernels (a 1280 x 720 frame has 80 x 45 tiles)
GAP_LOCAL = (64, 1)  # of edge_gaps: adjacent columns, so a GPU's reads coalesce
SEGMENT = 32  # rows per edge_gaps work-item: enough work-items for a GPU, short overlaps
# pixels of a row per work-item of the per-pixel kernels on a CPU device: there a
# work-item's fixed cost was most of their time (PoCL, 1280 x 720: 1.5 ms a kernel at 1)
CPU_RUN = 16


def _program(rt) -> Program:
    """The region program, built once per runtime (kept in the runtime's program cache,
    keyed by its build options)."""
    return rt.built(("region.cl",))


def _padded(n: int, step: int) -> int:
    return max(-(-n // step) * step, step)


def near_limit(r: float) -> int:
    """The largest integer squared distance ``d2`` with ``sqrt(d2) <= r + 2.0`` in double
    (correctly rounded, as numpy's): the reference's ``near`` test in integers.

    Parameters
    ----------
    r : float
        The reach (px, >= 0).

    Returns
    -------
    int
    """
    bound = r + 2.0
    k2 = math.floor(bound * bound)
    while math.sqrt(k2 + 1) <= bound:
        k2 += 1
    while k2 > 0 and math.sqrt(k2) > bound:
        k2 -= 1
    return k2


def region_mask(v: np.ndarray, anchor: float, tile: int = TILE, spread: float = SPREAD_PX,
                device: str | None = None, *, run: int | None = None) -> np.ndarray:
    """:func:`clblur.layered_exposure.region_mask` on the OpenCL device (the mask of
    :func:`region_and_reach`; the parameters are its)."""
    return region_and_reach(v, anchor, tile, spread, device, run=run)[0]


def region_and_reach(v: np.ndarray, anchor: float, tile: int = TILE,
                     spread: float = SPREAD_PX, device: str | None = None, *,
                     run: int | None = None) -> tuple[np.ndarray, float]:
    """:func:`clblur.layered_exposure.region_mask` on the OpenCL device, and the reach
    ``clblur.halo.reach(v, anchor)`` it found on the way (which building the layers needs
    too: ``clblur.layer_planes.prepare``'s ``r``).

    Parameters
    ----------
    v : numpy.ndarray
        H x W x 2 vectors (dx, dy), read as float32 (module Conventions).
    anchor : float
        Anchor time in [0, 1].
    tile : int
        Tile side (px).
    spread : float
        Vector spread (px) that flags tiles and motion edges.
    device : str, optional
        OpenCL device selector (``clblur.opencl.device``).
    run : int, optional
        Pixels of a row per work-item of the per-pixel kernels (default: 1 on a GPU,
        ``CPU_RUN`` elsewhere); any value gives the same mask.

    Returns
    -------
    mask : numpy.ndarray
        H x W bool: the reference's mask, except possibly at pixels whose inverse departure
        lies within ``spread / 32`` of ``spread`` (module Conventions).
    r : float
        ``clblur.halo.reach(v, anchor)``, bit for bit.

    Raises
    ------
    ValueError
        If ``v`` is not H x W x 2, a side exceeds ``MAX_SIDE``, or ``tile`` or ``run`` is
        below 1.
    """
    from clblur.opencl import runtime

    v = np.asarray(v)
    if v.ndim != 3 or v.shape[2] != 2:
        raise ValueError(f"v must be H x W x 2, got shape {v.shape}")
    if max(v.shape[:2]) > MAX_SIDE:
        raise ValueError(f"v is larger than {MAX_SIDE} px a side: {v.shape}")
    tile = int(tile)
    if tile < 1:
        raise ValueError(f"tile must be at least 1, got {tile}")
    if run is not None and int(run) < 1:
        raise ValueError(f"run must be at least 1, got {run}")
    h, w = v.shape[:2]
    out = np.zeros((h, w), np.uint8)
    if not out.size:
        return out.astype(bool), reach(v, anchor)
    th, tw = -(-h // tile), -(-w // tile)
    t0, t1 = -anchor, 1.0 - anchor
    vf = np.ascontiguousarray(v, np.float32)
    cl = pyopencl_module()
    rt = runtime(device)
    with rt.lock:
        program = _program(rt)
        vbuf = rt.share("region.v", vf)
        tmin, tmax = rt.buffer("region.tmin", 8 * th * tw), rt.buffer("region.tmax", 8 * th * tw)
        longest = np.empty((th * tw, 2), np.float32)
        longest_buf = rt.buffer("region.longest", longest.nbytes)
        tiles = (_padded(tw, TILE_LOCAL[0]), _padded(th, TILE_LOCAL[1]))
        program.run("tile_extrema", rt.queue, tiles, TILE_LOCAL, v=vbuf, h=h, w=w, tile=tile,
                    th=th, tw=tw, tmin=tmin, tmax=tmax, longest=longest_buf)
        if vf.dtype == v.dtype:
            # the only wait before the mask's: R sizes the windows of what follows.  The
            # largest of the tiles' longest vectors is the largest of all, and reach takes
            # the largest: the reference's R, bit for bit, without its pass over the field
            cl.enqueue_copy(rt.queue, longest, longest_buf, is_blocking=True)
            r = reach(longest[None], anchor)
        else:
            r = reach(v, anchor)  # in the reference's own arithmetic (float16, float64)
        # beyond the whole grid (or image) a larger window or bound changes nothing: clamped
        # so the kernels' integers stay in range
        around = min(math.ceil((r + 2.0) / tile), max(th, tw))
        k2 = min(near_limit(r), (h - 1) ** 2 + (w - 1) ** 2)
        bound = min(math.isqrt(k2), max(h, w))
        flags = rt.buffer("region.flags", th * tw)
        wanted = rt.buffer("region.wanted", th * tw)
        bits = rt.buffer("region.bits", h * w)
        gap = rt.buffer("region.gap", 4 * h * w)
        mask = rt.buffer("region.mask", h * w)
        run = int(run) if run is not None else 1 if rt.gpu else CPU_RUN
        pixels = (_padded(-(-w // run), PIXEL_LOCAL[0]), _padded(h, PIXEL_LOCAL[1]))
        program.run("tile_flags", rt.queue, tiles, TILE_LOCAL, tmin=tmin, tmax=tmax, th=th,
                    tw=tw, around=around, spread=spread, flags=flags)
        program.run("tile_wanted", rt.queue, tiles, TILE_LOCAL, flags=flags, th=th, tw=tw,
                    around=-(-bound // tile), wanted=wanted)
        program.run("pixel_bits", rt.queue, pixels, PIXEL_LOCAL, v=vbuf, h=h, w=w, tile=tile,
                    tw=tw, run=run, wanted=wanted, spread=spread, bits=bits)
        program.run("edge_gaps", rt.queue,
                    (_padded(w, GAP_LOCAL[0]), _padded(-(-h // SEGMENT), GAP_LOCAL[1])),
                    GAP_LOCAL, bits=bits, wanted=wanted, h=h, w=w, tile=tile, tw=tw,
                    seg=SEGMENT, bound=bound, gap=gap)
        program.run("region", rt.queue, pixels, PIXEL_LOCAL, v=vbuf, bits=bits, gap=gap,
                    flags=flags, h=h, w=w, tile=tile, tw=tw, run=run, bound=bound, k2=k2,
                    t0=t0, t1=t1, abs_t0=abs(t0), abs_t1=abs(t1), spread=spread, out=mask)
        cl.enqueue_copy(rt.queue, out, mask, is_blocking=True)
    return out.view(bool), r
