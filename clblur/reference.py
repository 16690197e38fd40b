"""The numpy reference backend: the executable specification of the blur.

Clear float64 code, no cleverness.  Pipeline, per channel:
linearise (pixels.linearise) -> integrate along the motion (bilinear, clamp to edge) ->
forward response -> quantise (pixels.quantise).
"""

from __future__ import annotations

import numpy as np

from clblur.motion import PSF, Field, Uniform, sample_counts, uniform_taps
from clblur.pixels import linearise, normalise, quantise
from clblur.plan import BlurPlan


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray, plan: BlurPlan) -> np.ndarray:
    """Sample the window ``img`` at full-image float positions ``x``, ``y``.

    Positions clamp to the full image (clamp-to-edge), then index the window at
    ``origin``; indices are clipped to the window as a guard (a correct halo never needs it).
    """
    fh, fw = plan.full_shape
    r0, c0 = plan.origin
    h, w = img.shape[:2]
    x = np.clip(x, 0.0, fw - 1.0)
    y = np.clip(y, 0.0, fh - 1.0)
    x0 = np.floor(x).astype(np.intp)
    y0 = np.floor(y).astype(np.intp)
    x1 = np.minimum(x0 + 1, fw - 1)
    y1 = np.minimum(y0 + 1, fh - 1)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x0, x1 = np.clip(x0 - c0, 0, w - 1), np.clip(x1 - c0, 0, w - 1)
    y0, y1 = np.clip(y0 - r0, 0, h - 1), np.clip(y1 - r0, 0, h - 1)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def integrate(lin: np.ndarray, plan: BlurPlan) -> np.ndarray:
    """Weighted mean of the linearised image along each pixel's motion path."""
    h, w = lin.shape[:2]
    r0, c0 = plan.origin
    yy, xx = np.mgrid[r0:r0 + h, c0:c0 + w].astype(np.float64)  # full-image coordinates
    m = plan.motion
    if isinstance(m, Uniform):
        offsets, wts = uniform_taps(m, plan.samples, plan.anchor, plan.weights)
        acc = np.zeros_like(lin)
        for (ox, oy), wj in zip(offsets, wts, strict=True):
            acc += wj * bilinear(lin, xx + ox, yy + oy, plan)
        return acc
    if isinstance(m, Field):
        vx = m.flow[..., 0].astype(np.float64)
        vy = m.flow[..., 1].astype(np.float64)
        if plan.samples is None:
            n = sample_counts(m.flow[..., 0], m.flow[..., 1]).astype(np.float64)
        else:
            n = np.full((h, w), float(plan.samples))
        den = np.maximum(n - 1, 1)
        acc = np.zeros_like(lin)
        for j in range(int(n.max())):
            active = j < n
            num = j - plan.anchor * (n - 1)
            x = xx - (vx * num) / den
            y = yy - (vy * num) / den
            wj = plan.weights[j] if plan.weights is not None else 1.0 / n
            acc += np.where(active, wj, 0.0)[..., None] * bilinear(lin, x, y, plan)
        return acc
    if isinstance(m, PSF):
        cy, cx = m.center
        acc = np.zeros_like(lin)
        for (i, j), hij in np.ndenumerate(m.kernel):
            if hij != 0:  # displacement s = (j - cx, i - cy); output p reads f(p - s)
                acc += hij * bilinear(lin, xx - (j - cx), yy - (i - cy), plan)
        return acc
    raise TypeError(f"unknown motion {m!r}")


def blur(plan: BlurPlan) -> np.ndarray:
    values = normalise(plan.image)
    lin = np.empty_like(values)
    for c, resp in enumerate(plan.responses):
        lin[..., c] = linearise(values[..., c], resp, plan.dtype, plan.saturation)
    acc = integrate(lin, plan)
    out = np.empty_like(acc)
    for c, resp in enumerate(plan.responses):
        out[..., c] = resp.forward(acc[..., c])
    return plan.finish(quantise(out, plan.dtype))
