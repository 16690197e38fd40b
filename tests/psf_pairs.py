"""Blur pairs with a known kernel, for the PSF-estimation tests and ``bench/bench_psf.py``.

A scene of rectangles of random colour over smooth noise, in linear light (edges in every
direction), blurred by a camera-shake-like kernel (light spread evenly along a polyline) in
linear light, then sRGB-encoded with read noise and stored as 8-bit codes.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.signal import fftconvolve

from clblur.responses import response

SRGB = response("srgb")


def path_kernel(n: int, points: list[tuple[float, float]]) -> np.ndarray:
    """A camera-shake-like kernel: light spread evenly along a polyline of (dy, dx) offsets
    from the centre of an n x n window."""
    k = np.zeros((n, n))
    pts = np.asarray(points, float)
    for t in np.linspace(0.0, 1.0, 40 * n):
        seg = min(int(t * (len(pts) - 1)), len(pts) - 2)
        u = t * (len(pts) - 1) - seg
        y, x = (1 - u) * pts[seg] + u * pts[seg + 1]
        k[int(round(y)) + n // 2, int(round(x)) + n // 2] += 1
    return k / k.sum()


def scene(rng, h: int = 192, w: int = 192, rectangles: int = 60) -> np.ndarray:
    """Linear light: rectangles of random colour over smooth noise (edges in every
    direction)."""
    img = np.zeros((h, w, 3))
    for _ in range(rectangles):
        y, x = rng.integers(0, h), rng.integers(0, w)
        a, b = rng.integers(5, 40, 2)
        img[y:y + a, x:x + b] = rng.uniform(0.0, 1.0, 3)
    smooth = ndimage.gaussian_filter(rng.uniform(0.0, 1.0, (h, w, 3)), (3, 3, 0))
    return 0.6 * img + 0.4 * smooth


def pair(rng, kernel: np.ndarray, noise: float = 1.0, size: int = 192,
         shape: tuple[int, int] | None = None):
    """(sharp, blurred) 8-bit sRGB codes: the blur in linear light, then read noise.
    ``shape``: (h, w) in place of ``size`` x ``size``, with a rectangle per 600 px."""
    h, w = shape or (size, size)
    lin = scene(rng, h, w, h * w // 600 if shape else 60)
    blurred = np.stack([fftconvolve(lin[..., c], kernel, mode="same") for c in range(3)], 2)
    sharp = np.rint(SRGB.forward(lin) * 255).astype(np.uint8)
    codes = SRGB.forward(np.clip(blurred, 0, 1)) * 255 + rng.normal(0.0, noise, blurred.shape)
    return sharp, np.clip(np.rint(codes), 0, 255).astype(np.uint8)
