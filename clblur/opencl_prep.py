"""Host-side preparation for the OpenCL kernels: pure numpy, no OpenCL.

Turns a validated ``BlurPlan`` into what the kernels read: per-channel linearisation tables,
packed forward-response parameters, and the integration strategy (per-pixel field, a list of
integer taps, or a running-sum box).

Conventions
-----------
* Linearisation happens once per pixel, never per tap: integer images go through a table of
  ``Imax + 1`` exposures per channel (``clblur.pixels.linearisation_table``, float64 rounded to
  float32); float images are linearised here in float64 (``clblur.pixels.linearise``), so the
  saturation policy and ``E_fs`` are exactly the reference's.
* Uniform motion and PSFs become integer taps ``d_t`` with weights ``w_t``:
  ``g(p) = sum_t w_t L(clamp(p + d_t))``.  For uniform motion every pixel's bilinear samples
  share the same fractional offsets, so splatting each sample's four bilinear weights onto the
  integer grid is exact, clamp-to-edge included (a clamped position and a replicated border
  read the same edge pixel).
* Taps that form a run of equal weights along x with ``dy == 0`` (or along y with
  ``dx == 0``) are a box, integrated with running sums whose cost does not depend on the length.
* Half-float intermediate storage is used only for uint8 outputs and only when the propagated
  half rounding error stays below ``HALF_MAX_LSB`` (see ``docs/tolerances.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clblur.motion import PSF, Field, Uniform, uniform_taps
from clblur.pixels import imax, linearise, normalise
from clblur.plan import BlurPlan
from clblur.responses import KIND_CODES, Gamma, Response, Table

RESP_STRIDE = 4  # floats per channel in kernels/response.cl
GROUP = 4  # channels per kernel pass (RGBA-interleaved intermediate)
HALF_MAX_LSB = 0.25  # largest allowed output error from half storage, in uint8 code steps
HALF_UNIT_ROUNDOFF = 2.0**-11
HALF_SUBNORMAL_HALF_STEP = 2.0**-25
HALF_LARGEST = 65504.0


@dataclass(frozen=True)
class Taps:
    """Space-invariant integer taps: read ``L(p + (dx, dy))`` with weight ``w``."""

    dx: np.ndarray  # int32
    dy: np.ndarray  # int32
    w: np.ndarray  # float64

    def box(self) -> tuple[int, int, int] | None:
        """``(axis, lo, hi)`` when the taps are a box of equal weights on offsets lo..hi along
        x (axis 0, dy == 0) or y (axis 1, dx == 0); else None."""
        if not np.all(self.w == self.w[0]):
            return None
        for axis, along, across in ((0, self.dx, self.dy), (1, self.dy, self.dx)):
            if np.all(across == 0):
                offs = np.sort(along)
                if np.array_equal(offs, np.arange(offs[0], offs[0] + offs.size)):
                    return axis, int(offs[0]), int(offs[-1])
        return None


def rasterise(offsets: np.ndarray, weights: np.ndarray) -> Taps:
    """Splat bilinear samples at ``p + offsets[j]`` (N x 2, x then y) onto integer taps."""
    acc: dict[tuple[int, int], float] = {}
    for (ox, oy), wj in zip(offsets, weights, strict=True):
        x0, y0 = math.floor(ox), math.floor(oy)
        fx, fy = ox - x0, oy - y0
        for dx, dy, wt in ((x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)),
                           (x0, y0 + 1, (1 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)):
            if wt * wj != 0.0:
                acc[(dx, dy)] = acc.get((dx, dy), 0.0) + wt * wj
    return _taps_from(acc)


def psf_taps(psf: PSF) -> Taps:
    """A PSF reads ``f(p - s)`` for displacement ``s = (col - cx, row - cy)``."""
    cy, cx = psf.center
    rows, cols = np.nonzero(psf.kernel)
    acc = {(int(cx - c), int(cy - r)): float(psf.kernel[r, c]) for r, c in zip(rows, cols,
                                                                               strict=True)}
    return _taps_from(acc)


def _taps_from(acc: dict[tuple[int, int], float]) -> Taps:
    keys = sorted(acc, key=lambda k: (k[1], k[0]))  # row-major order: neighbouring reads
    return Taps(dx=np.array([k[0] for k in keys], dtype=np.int32),
                dy=np.array([k[1] for k in keys], dtype=np.int32),
                w=np.array([acc[k] for k in keys], dtype=np.float64))


def space_invariant_taps(plan: BlurPlan) -> Taps | None:
    """Integer taps of a uniform motion or PSF plan; None for a per-pixel field."""
    m = plan.motion
    if isinstance(m, Uniform):
        offsets, w = uniform_taps(m, plan.samples, plan.anchor, plan.weights)
        return rasterise(offsets, w)
    if isinstance(m, PSF):
        return psf_taps(m)
    if isinstance(m, Field):
        return None
    raise TypeError(f"unknown motion {m!r}")


def channel_groups(channels: int) -> list[tuple[int, int]]:
    """``(first channel, count)`` of each kernel pass."""
    return [(c, min(GROUP, channels - c)) for c in range(0, channels, GROUP)]


def four_channels(group):
    """A channel group padded to four by repeating its first response (the kernels read
    per-channel tables for all four lanes; the padding lanes are never stored)."""
    group = list(group)
    return group + [group[0]] * (GROUP - len(group))


def response_params(responses: tuple[Response, ...] | list[Response]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Pack up to four channels' forward responses for kernels/response.cl.

    Returns (params: float32[GROUP * RESP_STRIDE], tables: float32, at least one element).
    """
    params = np.zeros(GROUP * RESP_STRIDE, dtype=np.float32)
    tables: list[np.ndarray] = []
    offset = 0
    for k, r in enumerate(responses):
        p = 0.0
        if isinstance(r, Gamma):
            p = 1.0 / r.gamma
        elif r.kind == "exp":
            p = r.device_params()[0]
        start, length = 0, 0
        if isinstance(r, Table):
            start, length = offset, r.exposure.size
            tables += [r.exposure, r.value]
            offset += 2 * length
        params[k * RESP_STRIDE:(k + 1) * RESP_STRIDE] = (KIND_CODES[r.kind], p, start, length)
    flat = np.concatenate(tables).astype(np.float32) if tables else np.zeros(1, np.float32)
    return params, flat


THRESHOLD_PAD = 64  # +inf entries after each row: no probe of the search leaves its row
BUCKET_SHIFT = {8: 16, 16: 12}  # keeps 7 (uint8) or 11 (uint16) mantissa bits per bucket
BUCKET_MAX_STEPS = 6
BUCKET_MAX_COUNT = 1 << 20
QHEAD = 5  # header length of the bucket table (kernels/response.cl)


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
    """Bucket table for kernels/response.cl ``quantise`` (int32).

    Layout: ``[shift, base, nb, steps, stride]`` then ``nb`` counts per channel.  Bucket b
    covers the float32 values whose bit patterns shifted right by ``shift`` equal
    ``base + b`` (bucket 0 also everything below, the last everything above); its count is
    the number of thresholds below its start, and at most ``2^steps - 1`` thresholds lie
    inside any bucket.  When that would need more than BUCKET_MAX_STEPS halvings (or too
    many buckets), the table is one bucket with ``steps = bits``: a plain binary search.
    """
    channels, stride = thresholds.shape
    bits = 8 if stride - THRESHOLD_PAD == 256 else 16
    plain = np.concatenate([[31, 0, 1, bits, stride], np.zeros(channels)]).astype(np.int32)
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
    return np.concatenate([[shift, base, nb, steps, stride], *counts]).astype(np.int32)


def linearise_float_image(image: np.ndarray, responses, saturation: float) -> np.ndarray:
    """Float H x W x C image -> float32 linear exposures (float64 maths, as the reference)."""
    values = normalise(image)
    out = np.empty(image.shape, dtype=np.float32)
    for c, r in enumerate(responses):
        out[..., c] = linearise(values[..., c], r, image.dtype, saturation)
    return out


def half_error_lsb(resp: Response, exposures: np.ndarray) -> float:
    """Bound on the uint8 output error (code steps) caused by storing exposures in half.

    A weighted mean of half-rounded values ``E_t (1 + e_t) + d_t`` (``|e_t| <= 2^-11``,
    ``|d_t| <= 2^-25`` in the subnormal range) is off by at most ``E u + d`` from the exact
    mean ``E``; the output moves by at most ``max |f(E +- (E u + d)) - f(E)|`` over the
    exposures the blur can produce, i.e. ``[0, max LUT entry]``.
    """
    top = float(np.max(exposures))
    if not math.isfinite(top) or top * (1 + HALF_UNIT_ROUNDOFF) >= HALF_LARGEST:
        return math.inf
    if float(np.min(exposures)) < 0:
        return math.inf
    grid = np.unique(np.concatenate([
        np.linspace(0.0, top, 4097), np.geomspace(1e-9, max(top, 2e-9), 4097),
        np.asarray(exposures, dtype=np.float64),
        resp.exposure if isinstance(resp, Table) else np.zeros(0)]))
    grid = grid[grid <= top]
    slack = grid * HALF_UNIT_ROUNDOFF + HALF_SUBNORMAL_HALF_STEP
    f = resp.forward(grid)
    err = np.maximum(np.abs(resp.forward(grid + slack) - f),
                     np.abs(f - resp.forward(np.maximum(grid - slack, 0.0))))
    return float(np.max(err) * 255.0)


def half_storage_ok(plan: BlurPlan, luts: np.ndarray | None) -> bool:
    """Half storage only for uint8 images whose propagated error bound is small enough."""
    if plan.dtype != np.uint8 or luts is None:
        return False
    return all(half_error_lsb(r, luts[c]) <= HALF_MAX_LSB
               for c, r in enumerate(plan.responses))


def fixed_point_scale(max_abs: float, count: int) -> float:
    """Power of two that maps ``count`` values of magnitude <= ``max_abs`` into int64 sums
    with headroom (the box kernel's exact running sums)."""
    max_abs = max(float(max_abs), 1e-30)
    exponent = math.floor(60 - math.log2(max_abs * (count + 2)))
    return float(2.0 ** min(exponent, 120))
