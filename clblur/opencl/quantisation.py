"""Integer output codes without evaluating the response on the device: float64 code
boundaries and a bucket index over them (read by ``quantise`` in response.cl).

Conventions
-----------
* Code k + 1 starts where the response crosses ``(k + 1/2) / Imax``; the kernel counts the
  boundaries below an exposure, which is ``rint(clamp(I(E), 0, 1) * Imax)`` (half to even) up
  to the float32 rounding of the boundary.
"""

from __future__ import annotations

import functools

import numpy as np

from clblur.opencl import response_pack
from clblur.opencl.constants import GRID_SEARCH, QHEAD
from clblur.pixels import imax
from clblur.responses import Table

__all__ = ["BUCKET_MAX_STEPS", "GRID_CELLS", "GRID_MAX_SEARCH", "THRESHOLD_PAD", "box_code_grid",
           "grid_cells", "quantisation_buckets", "quantisation_grid", "quantisation_thresholds"]

THRESHOLD_PAD = 64  # +inf entries after each row: no probe of the search leaves its row
BUCKET_SHIFT = {8: 16, 16: 12}  # keeps 7 (uint8) or 11 (uint16) mantissa bits per bucket
BUCKET_MAX_STEPS = 6
BUCKET_MAX_COUNT = 1 << 20
# uint8 code grid: cells per channel (a cell is 2^-17 of the exposure range, so at most 255
# of them hold a boundary: 0.2 %, and a 12-lane vector of uniformly spread exposures meets
# one about 2.3 % of the time; measured on PoCL, 4K box: 2^16 cells 1.1x the search, 2^17
# 1.2x, 2^18 no gain, its 1 MiB row leaves the cache) and the largest share of such cells
# for which the grid is used (GRID_SEARCH, the flag of such a cell, is a shared constant)
GRID_CELLS = 1 << 17
GRID_MAX_SEARCH = 1 / 64


def quantisation_thresholds(responses, dtype: np.dtype) -> np.ndarray:
    """float32 (channels, 2^bits + THRESHOLD_PAD): where each response crosses the code
    boundaries.

    Entry k < Imax is ``I^-1((k + 1/2) / Imax)`` in float64: an exposure above it quantises to
    a code above k.  A table response is flat outside its samples: levels above its last value
    are never reached (+inf), levels below its first value are exceeded everywhere (-inf).
    Boundaries whose exact tie rounds up (half to even: odd k) are lowered by one float32 step,
    so an exposure equal to the float32 boundary rounds as ``numpy.rint`` does.  The entries
    from Imax on are +inf.
    """
    full = int(imax(dtype))
    bits = 8 if full == 255 else 16
    levels = (np.arange(full, dtype=np.float64) + 0.5) / full
    rows = np.full((len(responses), (1 << bits) + THRESHOLD_PAD), np.inf, dtype=np.float32)
    for row, r in zip(rows, responses, strict=True):
        t = np.asarray(r.inverse(levels), dtype=np.float64)
        if isinstance(r, Table):
            t = np.where(levels > r.value[-1], np.inf, np.where(levels < r.value[0], -np.inf, t))
        t32 = t.astype(np.float32)
        odd = (np.arange(full) % 2 == 1) & np.isfinite(t32)
        t32[odd] = np.nextafter(t32[odd], np.float32(-np.inf))
        row[:full] = np.maximum.accumulate(t32)  # sorted where two boundaries coincide
    return rows


def quantisation_buckets(thresholds: np.ndarray) -> np.ndarray:
    """Bucket table for clblur/opencl/response.cl ``quantise`` (int32).

    Layout: ``[shift, base, nb, steps, stride]`` then ``nb`` counts per channel.  Bucket b
    covers the float32 values whose bit patterns shifted right by ``shift`` equal
    ``base + b`` (bucket 0 also everything below, the last everything above); its count is
    the number of thresholds below its start, and at most ``2^steps - 1`` thresholds lie
    inside any bucket.  When that would need more than BUCKET_MAX_STEPS halvings (or too
    many buckets), the table is one bucket with ``steps = bits``: a plain binary search.
    """
    channels, stride = thresholds.shape
    bits = 8 if stride - THRESHOLD_PAD == 256 else 16
    plain = _table([31, 0, 1, bits, stride], [np.zeros(channels)])
    t = thresholds[:, :(1 << bits) - 1]
    finite = t[np.isfinite(t) & (t > 0)]
    if finite.size == 0:
        return plain
    shift = BUCKET_SHIFT[bits]
    lo = np.float32(finite.min() / 2)
    hi = np.float32(min(float(finite.max()) * 2, 3e38))
    base = int(lo.view(np.uint32)) >> shift
    nb = (int(hi.view(np.uint32)) >> shift) - base + 1
    if nb > BUCKET_MAX_COUNT:
        return plain
    starts = ((np.arange(nb, dtype=np.uint32) + base) << shift).view(np.float32).copy()
    starts[0] = 0.0
    ends = np.append(starts[1:], np.float32(np.inf))
    counts, most = [], 0
    for row in t:
        q0 = np.searchsorted(row, starts, side="left")
        most = max(most, int(np.max(np.searchsorted(row, ends, side="left") - q0)))
        counts.append(q0)
    steps = max(1, int(most).bit_length())  # 2^steps - 1 >= most
    if steps > BUCKET_MAX_STEPS:
        return plain
    return _table([shift, base, nb, steps, stride], counts)


def _table(header: list[int], counts) -> np.ndarray:
    """Header (``QHEAD`` entries: shift, base, bucket count, steps, row stride) + counts."""
    assert len(header) == QHEAD
    return np.concatenate([header, *counts]).astype(np.int32)




def grid_cells(e: np.ndarray, scale: np.float32, cells: int) -> np.ndarray:
    """The cell of each float32 exposure ``e >= 0`` exactly as the kernel computes it:
    ``min(convert_int(fmin(e * scale, cells - 1)), cells - 1)``, the product rounded to float32
    (no contraction), the conversion towards zero."""
    prod = np.minimum(np.asarray(e, np.float32) * np.float32(scale), np.float32(cells - 1))
    return np.minimum(prod.astype(np.int64), cells - 1)


@functools.lru_cache(maxsize=16)
def _grid_cached(key: bytes, shape: tuple[int, int]):
    t = np.frombuffer(key, np.float32).reshape(shape)[:, :255]
    finite = t[np.isfinite(t) & (t > 0)]
    if finite.size == 0:
        return None
    shared = bool(np.all(t == t[0]))  # one row serves every channel (the usual case)
    rows = t[:1] if shared else t
    cells = GRID_CELLS
    # cells of equal width up to just past the last boundary; beyond, the last cell
    scale = np.float32(cells / (float(finite.max()) * (1 + 4 / cells)))
    table = np.concatenate([_grid_row(row, cells, scale) for row in rows])
    if np.count_nonzero(table & GRID_SEARCH) > GRID_MAX_SEARCH * table.size:
        return None
    return table, cells, scale, 0 if shared else cells


def _cell_starts(cells: int, scale: np.float32) -> np.ndarray:
    """The least float32 exposure of each cell (``grid_cells`` of it is the cell, of the
    float32 below it the cell before)."""
    g = np.arange(cells, dtype=np.int64)
    lo = (g.astype(np.float64) / float(scale)).astype(np.float32)  # within an ulp or two
    for _ in range(64):  # up while below the cell
        up = grid_cells(lo, scale, cells) < g
        if not up.any():
            break
        lo[up] = np.nextafter(lo[up], np.float32(np.inf))
    for _ in range(64):  # down while the float32 below is still in the cell
        below = np.nextafter(lo, np.float32(-np.inf))
        down = (grid_cells(below, scale, cells) >= g) & (g > 0)
        if not down.any():
            break
        lo[down] = below[down]
    lo[0] = 0.0  # the kernel clamps exposures to >= 0 first
    assert np.array_equal(grid_cells(lo, scale, cells), g)
    assert np.all(grid_cells(np.nextafter(lo[1:], np.float32(-np.inf)), scale, cells) < g[1:])
    return lo


def _grid_row(row: np.ndarray, cells: int, scale: np.float32) -> np.ndarray:
    lo = _cell_starts(cells, scale)
    ends = np.append(lo[1:], np.float32(np.inf))
    below = np.searchsorted(row, lo, side="left")  # boundaries below the cell's first e
    inside = np.searchsorted(row, ends, side="left") - below  # ... and not below the next
    return (below | np.where(inside > 0, GRID_SEARCH, 0)).astype(np.int32)


def quantisation_grid(thresholds: np.ndarray):
    """Uniform cell table over exposures for uint8 codes (``quantise16`` in response.cl):
    ``(table, cells, scale, channel stride)`` or None.

    The kernel maps an exposure ``e >= 0`` to cell ``grid_cells(e, scale, cells)``.  A cell
    without a code boundary holds its code (the count of boundaries below it, which is every
    exposure's in it); a cell holding one or more boundaries holds ``GRID_SEARCH``, and the
    kernel searches there.  One lookup per value instead of two (bucket, boundary).  int32
    table, GRID_CELLS per channel, channel-major; a channel stride of 0 where every channel
    has the same boundaries.  None for uint16 outputs (65535 boundaries), no positive
    boundary, or more than GRID_MAX_SEARCH of the cells to search.  Cached per thresholds.
    """
    t = np.ascontiguousarray(thresholds, np.float32)
    if t.shape[1] - THRESHOLD_PAD != 256:
        return None
    return _grid_cached(t.tobytes(), t.shape)


def box_code_grid(responses, dtype: np.dtype):
    """The code grid of one group of up to four channels (``quantisation_grid``), or None
    where the box kernels keep the threshold search (outputs other than uint8)."""
    if np.dtype(dtype) != np.uint8:
        return None
    group = response_pack.four_channels(responses)
    return quantisation_grid(quantisation_thresholds(group, dtype))
