"""Build a ``Group``: sample target pixels, trace their taps, collapse them to code histograms.

Conventions
-----------
A *tap* reads source image ``src`` at ``(x - dx, y - dy)`` (bilinear, clamp to edge, as
``clblur.reference``) with weight ``w`` at shutter time ``s`` in [0, 1] (None: no time order,
e.g. a PSF).  Target pixels are taken on a regular grid (stride chosen so at most
``max_pixels`` are used); pixels whose taps leave the image are dropped, because real data do
not share the kernels' clamp-to-edge border.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from clblur.camera import normalised_radius2
from clblur.sampling import bilinear_corners
from clblur.study.model import CODES, Group

__all__ = ["Taps", "as_hwc", "build_group", "sample_grid", "shifted"]


@dataclass(frozen=True)
class Taps:
    """All taps of the sampled pixels: arrays (n,) or scalars per tap."""

    src: int
    dx: np.ndarray | float
    dy: np.ndarray | float
    w: np.ndarray | float
    s: float | np.ndarray | None


def sample_grid(shape: tuple[int, int], max_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    stride = max(1, math.ceil(math.sqrt(h * w / max(max_pixels, 1))))
    rows, cols = np.mgrid[stride // 2:h:stride, stride // 2:w:stride]
    return rows.ravel(), cols.ravel()


def build_group(name: str, sources: list[np.ndarray], target: np.ndarray,
                rows: np.ndarray, cols: np.ndarray,
                taps: Callable[[np.ndarray, np.ndarray], Iterable[Taps]], ratio: float,
                vignetting: bool, timed: bool,
                variants: dict[str, dict] | None = None,
                darkest: int | np.ndarray | None = None) -> Group:
    """Collapse the taps of pixels (rows, cols) into code histograms (see ``model``).

    ``variants`` (``{effect: {key: taps}}``) are alternative tap sets for the geometric
    effects (``clblur.study.variants``): their histograms are built on the same pixels (a
    pixel is kept only if every variant's taps stay inside the image) and attached to the
    group.  ``darkest``: the bound a black level may not exceed (codes; one, or one per
    channel), for sources and target both; default the darkest code of each channel in the
    sources and the target pixels.
    """
    h, w, nc = target.shape
    hw = h * w
    yy, xx = rows.astype(np.float64), cols.astype(np.float64)
    inside = np.ones(rows.size, bool)
    n = rows.size
    total = hw * len(sources)

    def collect(tap_fn):
        nonlocal inside
        entries: dict[int, list] = {0: [], 1: [], 2: []}
        for tap in tap_fn(yy, xx):
            x = xx - tap.dx
            y = yy - tap.dy
            inside &= (x >= -1e-9) & (x <= w - 1 + 1e-9) & (y >= -1e-9) & (y <= h - 1 + 1e-9)
            for r, col, wt in _bilinear(x, y, h, w):
                wt = wt * tap.w
                entries[0].append((r, col + tap.src * hw, wt))
                if timed and tap.s is not None:
                    s = np.broadcast_to(np.asarray(tap.s, dtype=np.float64), wt.shape)
                    entries[1].append((r, col + tap.src * hw, wt * (2 * s - 1)))
                    entries[2].append((r, col + tap.src * hw, wt * (6 * s * s - 6 * s + 1)))
        return {i: _csr(e, n, total) for i, e in entries.items() if e}

    base = collect(taps)
    alt = {eff: {key: collect(fn) for key, fn in d.items()} for eff, d in (variants or {}).items()}
    keep = np.flatnonzero(inside)
    # only the source pixels some tap reads: a one-hot code matrix of every source pixel of
    # an 8-frame 720p stack is 7 million rows, most never read when pixels are sampled
    flag = np.zeros(total, bool)
    for m in [*base.values(), *(m for d in alt.values() for ms in d.values()
                                for m in ms.values())]:
        flag[m.indices] = True
    used = np.flatnonzero(flag)
    r2_src = np.tile(normalised_radius2((h, w)).ravel(), len(sources))[used]
    codes = np.stack([s.reshape(hw, nc) for s in sources]).reshape(total, nc)[used]
    nu = used.size
    onehot = [sp.csr_matrix((np.ones(nu), (np.arange(nu), codes[:, c].astype(np.intp))),
                            shape=(nu, CODES)) for c in range(nc)]
    remap = np.zeros(total, np.intp)
    remap[used] = np.arange(nu)

    def squeeze(m: sp.csr_matrix) -> sp.csr_matrix:
        return sp.csr_matrix((m.data, remap[m.indices], m.indptr), shape=(m.shape[0], nu))

    def hists(mats):
        out = {}
        for i, m in mats.items():
            m = squeeze(m)[keep]
            for k in (0, 1, 2) if vignetting else (0,):
                mk = m if k == 0 else m @ sp.diags(r2_src ** k)
                out[(i, k)] = [(mk @ oh).tocsr() for oh in onehot]
        return out

    hist = hists(base)
    m0 = squeeze(base[0])[keep]
    hist_sq = [(m0.multiply(m0)).tocsr() @ oh for oh in onehot]
    rows, cols = rows[keep], cols[keep]
    tgt = target[rows, cols].astype(np.float64)
    full = 255.0
    valid = (tgt > 0) & (tgt < full)
    r2 = normalised_radius2((h, w))[rows, cols]
    clipped = any(bool((s == 255).any()) for s in sources)
    g = Group(name, tgt, valid, rows, cols, (h, w), float(ratio), hist,
              [hq.tocsr() for hq in hist_sq], r2, source_clipped=clipped)
    from clblur.study.variants import attach

    attach(g, {eff: {key: hists(m) for key, m in d.items()} for eff, d in alt.items()},
           np.min([s.reshape(-1, nc).min(axis=0) for s in sources], axis=0)
           if darkest is None else darkest,
           with_target=darkest is None)
    return g


def shifted(taps: Callable[[np.ndarray, np.ndarray], Iterable[Taps]], sx: float, sy: float):
    """The same taps read ``(sx, sy)`` pixels further back: target ``p`` sees ``p - s``."""
    def fn(yy, xx):
        for t in taps(yy, xx):
            yield Taps(t.src, t.dx + sx, t.dy + sy, t.w, t.s)
    return fn


def _csr(entries, n, total) -> sp.csr_matrix:
    r = np.concatenate([np.broadcast_to(e[0], e[2].shape) for e in entries])
    c = np.concatenate([np.broadcast_to(e[1], e[2].shape) for e in entries])
    v = np.concatenate([e[2] for e in entries])
    nz = v != 0
    return sp.csr_matrix((v[nz], (r[nz], c[nz])), shape=(n, total))


def _bilinear(x, y, h, w):
    """(row index, flat source index, weight) of the four bilinear corners, clamp to edge
    (``clblur.sampling.bilinear_corners``)."""
    y0, y1, x0, x1, fx, fy = bilinear_corners(x, y, h, w)
    r = np.arange(x.size)
    return ((r, y0 * w + x0, (1 - fx) * (1 - fy)), (r, y0 * w + x1, fx * (1 - fy)),
            (r, y1 * w + x0, (1 - fx) * fy), (r, y1 * w + x1, fx * fy))


def as_hwc(image: np.ndarray, what: str) -> np.ndarray:
    """8-bit H x W x C codes of an image; the study's likelihood is written in 8-bit codes.

    A 16-bit image is rounded to the nearest 8-bit code (``x / 257``): exact for 16-bit
    files written from 8-bit data (``x * 257``); for true 16-bit data the rounding adds the
    quantisation the model's 1/12-code variance already assumes, and the finer codes are not
    used.
    """
    if not isinstance(image, np.ndarray):
        raise TypeError(f"{what} must be a numpy array")
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)  # round(x / 257)
    if image.dtype != np.uint8:
        raise ValueError(f"{what} is {image.dtype}; the study reads integer codes (uint8 or "
                         "uint16)")
    if image.ndim == 2:
        return image[..., None]
    if image.ndim != 3:
        raise ValueError(f"{what} must be H x W or H x W x C, got shape {image.shape}")
    return image[..., :3]
