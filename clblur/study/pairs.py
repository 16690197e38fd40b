"""Blur pairs (static, blurred, motion) -> study groups: the spatial form of Eq. 8."""

from __future__ import annotations

import numpy as np

from clblur.blur import blur
from clblur.errors import InputError
from clblur.motion import PSF, Field, Uniform, anchor_value, parse_motion, sample_counts
from clblur.study.histograms import Spread, Taps, as_hwc, build_group, sample_grid, shifted
from clblur.study.model import Group
from clblur.study.variants import OPTICAL_VARIANCES, SCALES, SHIFTS, binomial_offsets

__all__ = ["best_shift", "pair_group", "shift_kernel"]


def pair_group(static: np.ndarray, blurred: np.ndarray, motion, *, anchor: str = "center",
               exposure_ratio: float = 1.0, max_pixels: int = 60000,
               name: str = "pair", align_psf: int = 4) -> Group:
    """Study group of one blur pair; ``motion`` as in ``clblur.blur`` (vector, flow, PSF).

    A measured PSF's origin is not known to the pixel (camera-shake kernels are cropped
    around their support), so a PSF is first re-centred by the integer shift, within
    ``align_psf`` pixels, that best aligns the paper's prediction with the blurred image.
    """
    src = as_hwc(static, "static image")
    tgt = as_hwc(blurred, "blurred image")
    if src.shape != tgt.shape:
        raise InputError(f"static {src.shape} and blurred {tgt.shape} images differ in shape")
    m = parse_motion(motion, src.shape[:2])
    flip = None
    if isinstance(m, PSF):
        # the rotated kernel (psf_orientation) is aligned on its own: a stored kernel in the
        # other orientation is also off-centre by a different shift
        k_flip = m.kernel[::-1, ::-1]
        if align_psf > 0:
            k_flip = shift_kernel(k_flip, *best_shift(src, tgt, k_flip, align_psf))
            m = PSF(shift_kernel(m.kernel, *best_shift(src, tgt, m.kernel, align_psf)))
        flip = PSF(k_flip)
    a = anchor_value(anchor)
    if flip is None and a != 0.5:  # a path centred on the pixel is its own 180-degree turn
        flip = m

    def taps(y, x):
        return _taps(m, a, y, x)

    variants = {"misregistration": {sh: shifted(taps, *sh) for sh in SHIFTS},
                "psf_scale": {s: _scaled(taps, s) for s in SCALES},
                "optical_blur": {var: Spread(tuple(binomial_offsets(var)))
                                 for var in OPTICAL_VARIANCES}}
    if flip is not None:
        f_m = flip
        variants["psf_orientation"] = {
            "flip": (lambda y, x: _taps(f_m, a, y, x)) if isinstance(f_m, PSF)
            else _scaled(taps, -1.0)}
    rows, cols = sample_grid(src.shape[:2], max_pixels)
    timed = not isinstance(m, PSF)
    return build_group(name, [src], tgt, rows, cols, taps, exposure_ratio, vignetting=True,
                       timed=timed, variants=variants)


def _scaled(taps, factor: float):
    """Taps with every displacement multiplied by ``factor`` (-1: the motion turned by 180
    degrees; 1.25: a path 25 % longer), same weights and shutter times."""
    def fn(yy, xx):
        for t in taps(yy, xx):
            yield Taps(t.src, t.dx * factor, t.dy * factor, t.w, t.s)
    return fn


def _taps(m, a: float, yy: np.ndarray, xx: np.ndarray):
    if isinstance(m, Uniform):
        n = int(sample_counts(np.float32(m.dx), np.float32(m.dy)))
        for j in range(n):
            f = (j - a * (n - 1)) / max(n - 1, 1)
            yield Taps(0, m.dx * f, m.dy * f, 1.0 / n, j / (n - 1) if n > 1 else 0.5)
    elif isinstance(m, Field):
        r, c = yy.astype(np.intp), xx.astype(np.intp)
        vx = m.flow[r, c, 0].astype(np.float64)
        vy = m.flow[r, c, 1].astype(np.float64)
        n = sample_counts(m.flow[r, c, 0], m.flow[r, c, 1]).astype(np.float64)
        den = np.maximum(n - 1, 1)
        for j in range(int(n.max())):
            active = j < n
            f = (j - a * (n - 1)) / den
            s = np.where(n > 1, j / den, 0.5)
            yield Taps(0, vx * f, vy * f, np.where(active, 1.0 / n, 0.0), s)
    else:
        cy, cx = m.center
        for (i, j), hij in np.ndenumerate(m.kernel):
            if hij != 0:  # output p reads f(p - s), s = (j - cx, i - cy)
                yield Taps(0, float(j - cx), float(i - cy), float(hij), None)


def best_shift(static: np.ndarray, blurred: np.ndarray, kernel: np.ndarray,
               search: int) -> tuple[int, int]:
    """Integer (dy, dx) with ``blurred(p) ~ paper_prediction(p - (dy, dx))``."""
    pred = blur(static, kernel, "exp", backend="numpy").astype(np.float64)
    obs = blurred.astype(np.float64)
    r = max(kernel.shape) // 2 + search
    if min(obs.shape[:2]) <= 2 * r + 8:
        return 0, 0
    best = (np.inf, 0, 0)
    for dy in range(-search, search + 1):
        for dx in range(-search, search + 1):
            d = (np.roll(pred, (dy, dx), (0, 1)) - obs)[r:-r, r:-r]
            best = min(best, (float((d * d).mean()), dy, dx))
    return best[1], best[2]


def shift_kernel(kernel: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """Pad ``kernel`` so every displacement grows by (dx, dy) (centre stays at size // 2)."""
    h, w = kernel.shape
    out = np.zeros((h + 2 * abs(dy), w + 2 * abs(dx)))
    oy, ox = abs(dy) + dy, abs(dx) + dx
    out[oy:oy + h, ox:ox + w] = kernel
    return out
