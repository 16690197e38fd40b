"""Integer output codes without evaluating the response on the device: float64 code
boundaries and a bucket index over them (read by ``quantise`` in response.cl).

Conventions
-----------
* Code k + 1 starts where the response crosses ``(k + 1/2) / Imax``; the kernel counts the
  boundaries below an exposure, which is ``rint(clamp(I(E), 0, 1) * Imax)`` (half to even) up
  to the float32 rounding of the boundary.
"""

from __future__ import annotations

import numpy as np

from clblur.opencl.constants import QHEAD
from clblur.pixels import imax
from clblur.responses import Table

__all__ = ["BUCKET_MAX_STEPS", "THRESHOLD_PAD", "quantisation_buckets",
           "quantisation_thresholds"]

THRESHOLD_PAD = 64  # +inf entries after each row: no probe of the search leaves its row
BUCKET_SHIFT = {8: 16, 16: 12}  # keeps 7 (uint8) or 11 (uint16) mantissa bits per bucket
BUCKET_MAX_STEPS = 6
BUCKET_MAX_COUNT = 1 << 20


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


