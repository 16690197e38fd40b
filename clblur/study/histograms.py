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

from clblur.calibration.surround import surround_codes
from clblur.camera import normalised_radius2
from clblur.errors import InputError, InputTypeError
from clblur.sampling import bilinear_corners
from clblur.study.model import CODES, Group, censored_ends

__all__ = ["Spread", "Taps", "as_hwc", "build_group", "sample_grid", "shifted"]


@dataclass(frozen=True)
class Taps:
    """All taps of the sampled pixels: arrays (n,) or scalars per tap."""

    src: int
    dx: np.ndarray | float
    dy: np.ndarray | float
    w: np.ndarray | float
    s: float | np.ndarray | None


@dataclass(frozen=True)
class Spread:
    """A variant of the group's own taps whose every read is spread over whole-pixel
    ``offsets`` ((dy, dx, weight) triples, weights summing to 1; a blur of the light the
    target sums): a tap reading ``q`` reads ``q - o`` with weight ``b_o`` as well.

    Why not as taps: spreading each of a path's taps by a 9 x 9 kernel multiplies the
    entries a histogram is built from by 81 (gigabytes for a long path on a large image);
    spreading the histogram's source pixels instead costs one sparse product, done in row
    chunks of bounded size."""

    offsets: tuple[tuple[int, int, float], ...]


# entries of one chunk's spread code table (rows x offsets) in _spread_hists
_SPREAD_ENTRIES = 1 << 22


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
    effects (``clblur.study.variants``), or a :class:`Spread` of the group's own taps: their
    histograms are built on the same pixels (a pixel is kept only if every variant's taps
    stay inside the image; a spread's reads beyond the border take the edge pixel, so that
    it keeps the pixels the other histograms have) and attached to the group.
    ``darkest``: the bound a black level may not exceed (codes; one, or one per channel),
    for sources and target both; default the darkest code of each channel in the sources
    and the target pixels.
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
    alt = {eff: {key: collect(fn) for key, fn in d.items() if not isinstance(fn, Spread)}
           for eff, d in (variants or {}).items()}
    keep = np.flatnonzero(inside)
    # only the source pixels some tap reads: a one-hot code matrix of every source pixel of
    # an 8-frame 720p stack is 7 million rows, most never read when pixels are sampled
    flag = np.zeros(total, bool)
    for m in [*base.values(), *(m for d in alt.values() for ms in d.values()
                                for m in ms.values())]:
        flag[m.indices] = True
    used = np.flatnonzero(flag)
    # every source pixel's codes and radius (a spread reads beyond the taps' own pixels)
    every = np.stack([s.reshape(hw, nc) for s in sources]).reshape(total, nc)
    r2_all = np.tile(normalised_radius2((h, w)).ravel(), len(sources))
    r2_src = r2_all[used]
    codes = every[used]
    nu = used.size
    onehot = [sp.csr_matrix((np.ones(nu), (np.arange(nu), codes[:, c].astype(np.intp))),
                            shape=(nu, CODES)) for c in range(nc)]
    remap = np.zeros(total, np.intp)
    remap[used] = np.arange(nu)

    def squeeze(m: sp.csr_matrix) -> sp.csr_matrix:
        return sp.csr_matrix((m.data, remap[m.indices], m.indptr), shape=(m.shape[0], nu))

    def hists(mats, squares: bool = False):
        """The code histograms of each time term and vignetting power; with ``squares``
        also under ``"sq"`` those of the squared weights (``Group.hist_sq``): a variant's
        prediction carries its own reads' share of the source's noise."""
        out = {}
        for i, m in mats.items():
            m = squeeze(m)[keep]
            for k in (0, 1, 2) if vignetting else (0,):
                mk = m if k == 0 else m @ sp.diags(r2_src ** k)
                out[(i, k)] = [(mk @ oh).tocsr() for oh in onehot]
            if squares and i == 0:  # uniform time, no vignetting
                out["sq"] = [(m.multiply(m)).tocsr() @ oh for oh in onehot]
        return out

    hist = hists(base, squares=True)
    hist_sq = hist.pop("sq")
    rows, cols = rows[keep], cols[keep]
    tgt = target[rows, cols].astype(np.float64)
    full = 255.0
    valid = (tgt > 0) & (tgt < full)
    r2 = normalised_radius2((h, w))[rows, cols]
    clipped = any(bool((s == 255).any()) for s in sources)
    g = Group(name, tgt, valid, rows, cols, (h, w), float(ratio), hist,
              [hq.tocsr() for hq in hist_sq], r2, source_clipped=clipped,
              censored=censored_ends(tgt, np.ones(tgt.shape, bool), full), top=full,
              surround=surround_codes(target)[rows, cols])
    from clblur.study.variants import attach

    built = {eff: {key: (_spread_hists({i: m[keep] for i, m in base.items()}, fn, every,
                                       r2_all, (h, w), vignetting)
                         if isinstance(fn, Spread) else hists(alt[eff][key], squares=True))
                   for key, fn in d.items()}
             for eff, d in (variants or {}).items()}
    attach(g, built,
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


def _spread_hists(mats: dict[int, sp.csr_matrix], spread: Spread, codes: np.ndarray,
                  r2: np.ndarray, shape: tuple[int, int], vignetting: bool) -> dict:
    """The histograms ``build_group`` makes (``{(i, k): [per channel]}``) of ``mats`` (the
    kept pixels' weights on every source pixel) with every read spread by ``spread``:
    ``(M @ B) @ C_k``, ``B[q, q - o] = b_o`` the spread of a chunk of rows' source pixels and
    ``C_k[p, code] = r2(p)^k [code(p) = code]`` (a one-hot table, vignetting power ``k``);
    and under ``"sq"`` the squared weights' histograms (``Group.hist_sq`` of the spread
    reads).  A read beyond the border takes the edge pixel (clamp to edge, as the taps'
    bilinear reads): only pixels within the kernel's radius of the border see it, and
    dropping them would change every other histogram's pixels."""
    h, w = shape
    hw = h * w
    nc = codes.shape[1]
    dy = np.array([o[0] for o in spread.offsets])
    dx = np.array([o[1] for o in spread.offsets])
    b = np.array([o[2] for o in spread.offsets])
    n = next(iter(mats.values())).shape[0]
    per_row = max(max(int(np.diff(m.indptr).max(initial=1)), 1) for m in mats.values())
    step = max(1, _SPREAD_ENTRIES // (per_row * b.size))
    powers = (0, 1, 2) if vignetting else (0,)
    chunks: dict = {(i, k): [[] for _ in range(nc)] for i in mats for k in powers}
    chunks["sq"] = [[] for _ in range(nc)]
    for start in range(0, n, step):
        sub = {i: m[start:start + step] for i, m in mats.items()}
        cols = np.unique(np.concatenate([m.indices for m in sub.values()]))
        src, pix = np.divmod(cols, hw)
        y, x = np.divmod(pix, w)
        read = (src[:, None] * hw + np.clip(y[:, None] - dy, 0, h - 1) * w
                + np.clip(x[:, None] - dx, 0, w - 1))  # cols x offsets
        pixels, at = np.unique(read.ravel(), return_inverse=True)
        spread_m = sp.csr_matrix((np.broadcast_to(b, read.shape).ravel(),
                                  at.reshape(read.shape).ravel(),
                                  np.arange(0, read.size + 1, b.size)),
                                 shape=(cols.size, pixels.size))
        spread_m.sum_duplicates()  # two offsets clamped onto one edge pixel
        # the chunk's weights moved onto the pixels the spread reads (``M @ B``, columns
        # renumbered to ``cols`` first): one product per time term, then one-hot tables
        spread_w = {i: sp.csr_matrix((m.data, np.searchsorted(cols, m.indices), m.indptr),
                                     shape=(m.shape[0], cols.size)) @ spread_m
                    for i, m in sub.items()}
        ones = np.arange(pixels.size + 1)
        for k in powers:
            wt = r2[pixels] ** k if k else np.ones(pixels.size)
            for c in range(nc):
                table = sp.csr_matrix((wt, codes[pixels, c].astype(np.int32), ones),
                                      shape=(pixels.size, CODES))
                for i, m in spread_w.items():
                    chunks[(i, k)][c].append(m @ table)
                if k == 0:
                    # the squared weights of the spread reads (the source noise a blurred
                    # prediction carries, as Group.hist_sq for the plain one): uniform
                    # time, no vignetting
                    chunks["sq"][c].append(spread_w[0].multiply(spread_w[0]).tocsr() @ table)
    return {key: [_stack_rows(parts) for parts in per_c] for key, per_c in chunks.items()}


def _stack_rows(parts: list[sp.csr_matrix]) -> sp.csr_matrix:
    """``sp.vstack(parts)`` of CSR matrices of one width, by concatenating their arrays
    (scipy's general stacking took a fifth of ``_spread_hists``); no parts: no rows."""
    if not parts:
        return sp.csr_matrix((0, CODES))
    offsets = np.cumsum([0] + [int(p.indptr[-1]) for p in parts])
    # int32 indices where they fit, as scipy's products give: a mix would be copied to int64
    index = np.int32 if offsets[-1] < np.iinfo(np.int32).max else np.int64
    indptr = np.empty(sum(p.shape[0] for p in parts) + 1, index)
    indptr[0], at = 0, 1
    for p, o in zip(parts, offsets, strict=False):
        indptr[at:at + p.shape[0]] = p.indptr[1:] + o
        at += p.shape[0]
    return sp.csr_matrix((np.concatenate([p.data for p in parts]),
                          np.concatenate([p.indices.astype(index, copy=False) for p in parts]),
                          indptr), shape=(indptr.size - 1, parts[0].shape[1]))


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
        raise InputTypeError(f"{what} must be a numpy array")
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)  # round(x / 257)
    if image.dtype != np.uint8:
        raise InputError(f"{what} is {image.dtype}; the study reads integer codes (uint8 or "
                         "uint16)")
    if image.ndim == 2:
        return image[..., None]
    if image.ndim != 3:
        raise InputError(f"{what} must be H x W or H x W x C, got shape {image.shape}")
    return image[..., :3]
