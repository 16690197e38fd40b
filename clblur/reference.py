"""The numpy reference backend: the executable specification of the blur.

Clear float64 code, no cleverness.  The three stages that ``clblur.pipeline`` composes, per
channel: :func:`linearise` (``pixels.linearise``) -> :func:`integrate` along the motion
(bilinear, clamp to edge) -> :func:`finish` (forward response, ``pixels.quantise``).

Conventions
-----------
* Alpha (``plan.alpha``; the last channel is coverage, not light): coverage is never passed
  through a response.  Integer images carry straight alpha: colour is linearised, then
  premultiplied by the coverage ``a = code / Imax``; after integration the colour exposure is
  divided by the integrated coverage, the response re-applied, and both quantised (colour 0
  where the coverage rounds to code 0: a transparent pixel has no colour).  Float images
  carry premultiplied alpha, the EXR convention: under ``linear`` (scene-linear light) the
  colour channels are light already and pass as given; under any other response the colour
  is premultiplied in the response's domain, so it is divided by the coverage, linearised and
  premultiplied in linear light, and after integration the response is applied to the light
  per unit coverage and multiplied by the integrated coverage (an opaque colour stays at or
  below its coverage under a bounded response).  A pixel without coverage (light without
  coverage, e.g. a glow) is linearised as given.  Coverage is integrated as is and kept in
  [0, 1].
"""

from __future__ import annotations

import numpy as np

from clblur.motion import PSF, Field, Uniform, sample_counts, sample_weight, uniform_taps
from clblur.pixels import linearisation_table, normalise, quantise
from clblur.pixels import linearise as linearise_channel
from clblur.request import BlurPlan
from clblur.sampling import bilinear_corners

__all__ = ["bilinear", "bilinear_at", "lerp_at", "linearise", "integrate", "finish", "blur"]


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray, plan: BlurPlan) -> np.ndarray:
    """Sample the window ``img`` at full-image float positions ``x``, ``y``.

    Positions clamp to the full image (clamp-to-edge), then index the window at
    ``origin``; indices are clipped to the window as a guard (a correct halo never needs it).
    """
    return bilinear_at(img, x, y, plan.origin, plan.full_shape)


def _window_corners(img: np.ndarray, x: np.ndarray, y: np.ndarray, origin: tuple[int, int],
                    full_shape: tuple[int, int]):
    """The four corner values of positions ``x``, ``y`` in a window ``img`` at ``origin`` of
    a ``full_shape`` image (clamp to the image, then to the window) and the fractions."""
    fh, fw = full_shape
    r0, c0 = origin
    h, w = img.shape[:2]
    y0, y1, x0, x1, fx, fy = bilinear_corners(x, y, fh, fw)
    (x0, x1), (y0, y1) = _in_window((x0, x1), c0, w), _in_window((y0, y1), r0, h)
    return img[y0, x0], img[y0, x1], img[y1, x0], img[y1, x1], fx[..., None], fy[..., None]


def _in_window(corners, start: int, size: int):
    """Full-image corner indices on one axis as indices of a window starting at ``start``
    (``size`` long), clipped to it as a guard (a correct halo never needs it)."""
    return tuple(np.clip(i - start, 0, size - 1) for i in corners)


def bilinear_at(img: np.ndarray, x: np.ndarray, y: np.ndarray, origin: tuple[int, int],
                full_shape: tuple[int, int]) -> np.ndarray:
    """:func:`bilinear` for a window ``img`` at ``origin`` (row, col) of a ``full_shape``
    (H, W) image: the one bilinear sampler of the numpy backend."""
    a, b, c, d, fx, fy = _window_corners(img, x, y, origin, full_shape)
    top = a * (1 - fx) + b * fx
    bottom = c * (1 - fx) + d * fx
    return top * (1 - fy) + bottom * fy


def lerp_at(img: np.ndarray, x: np.ndarray, y: np.ndarray, origin: tuple[int, int],
            full_shape: tuple[int, int]) -> np.ndarray:
    """:func:`bilinear_at` written ``a + f (b - a)``: where the four corners are equal it
    returns them exactly (the sampler of vector fields, so that a field that does not vary
    is read back bit for bit)."""
    a, b, c, d, fx, fy = _window_corners(img, x, y, origin, full_shape)
    top = a + fx * (b - a)
    bottom = c + fx * (d - c)
    return top + fy * (bottom - top)


def shifted(img: np.ndarray, ox: float, oy: float, plan: BlurPlan) -> np.ndarray:
    """``bilinear(img, xx + ox, yy + oy, plan)`` for one offset shared by every pixel: the
    position's column depends on the pixel's column only and its row on the row only, so the
    corners are found per axis and read with two 1-D takes (the same values and arithmetic,
    bit for bit; per-pixel fancy indexing had made a 9 x 9 PSF on 256 x 256 take a second)."""
    h, w = img.shape[:2]
    r0, c0 = plan.origin
    fh, fw = plan.full_shape
    x = np.arange(c0, c0 + w, dtype=np.float64) + ox
    y = np.arange(r0, r0 + h, dtype=np.float64) + oy
    _, _, x0, x1, fx, _ = bilinear_corners(x, np.zeros_like(x), fh, fw)
    y0, y1, _, _, _, fy = bilinear_corners(np.zeros_like(y), y, fh, fw)
    (x0, x1), (y0, y1) = _in_window((x0, x1), c0, w), _in_window((y0, y1), r0, h)
    if not (fx.any() or fy.any()):  # a whole-pixel offset: the corner itself, exactly
        return np.take(np.take(img, y0, axis=0), x0, axis=1)
    shape = (1, w) + (1,) * (img.ndim - 2)
    fx = fx.reshape(shape)
    fy = fy.reshape((h, 1) + (1,) * (img.ndim - 2))
    rows0, rows1 = np.take(img, y0, axis=0), np.take(img, y1, axis=0)
    a, b = np.take(rows0, x0, axis=1), np.take(rows0, x1, axis=1)
    c, d = np.take(rows1, x0, axis=1), np.take(rows1, x1, axis=1)
    top = a * (1 - fx) + b * fx
    bottom = c * (1 - fx) + d * fx
    return top * (1 - fy) + bottom * fy


def integrate(lin: np.ndarray, plan: BlurPlan) -> np.ndarray:
    """Weighted mean of the linearised image along each pixel's motion path."""
    h, w = lin.shape[:2]
    m = plan.motion
    if isinstance(m, Uniform):
        offsets, wts = uniform_taps(m, plan.samples, plan.anchor, plan.weights)
        acc = np.zeros_like(lin)
        for (ox, oy), wj in zip(offsets, wts, strict=True):
            acc += wj * shifted(lin, ox, oy, plan)
        return acc
    if isinstance(m, Field):
        r0, c0 = plan.origin
        yy, xx = np.mgrid[r0:r0 + h, c0:c0 + w].astype(np.float64)  # full-image coordinates
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
            wj = plan.weights[j] if plan.weights is not None else sample_weight(j, n,
                                                                                  plan.ends)
            acc += np.where(active, wj, 0.0)[..., None] * bilinear(lin, x, y, plan)
        return acc
    if isinstance(m, PSF):
        cy, cx = m.center
        acc = np.zeros_like(lin)
        for (i, j), hij in np.ndenumerate(m.kernel):
            if hij != 0:  # displacement s = (j - cx, i - cy); output p reads f(p - s)
                acc += hij * shifted(lin, -(j - cx), -(i - cy), plan)
        return acc
    raise TypeError(f"unknown motion {m!r}")


def linearise(plan: BlurPlan, dtype: type = np.float64) -> np.ndarray:
    """Pixel values -> linear exposures (H x W x C, ``dtype``); alpha as in the Conventions.

    Integer images go through the per-code table (``clblur.pixels.linearisation_table``):
    the same function at the same inputs, evaluated once per code value instead of once per
    pixel.  ``dtype``: float64 (the reference), or float32 for a caller whose every later
    step is float32 (the device's layers): the float64 values rounded, without the float64
    array."""
    colour = plan.colour_channels
    if plan.dtype.kind == "u":
        lin = np.empty(plan.image.shape, dtype)
        for c in range(colour):
            table = linearisation_table(plan.responses[c], plan.dtype, plan.saturation)
            np.take(table.astype(dtype, copy=False), plan.image[..., c], out=lin[..., c])
        values = None
    else:
        values = normalise(plan.image)
        lin = np.empty(values.shape, dtype)
        for c in range(colour):
            v, cover = values[..., c], _premultiplied_cover(plan, c, values)
            if cover is not None:  # premultiplied in the response's domain: un-premultiply
                v = np.where(cover > 0, v / np.where(cover > 0, cover, 1.0), v)
            lin[..., c] = linearise_channel(v, plan.responses[c], plan.dtype, plan.saturation)
            if cover is not None:  # and premultiply the light
                lin[..., c] *= np.where(cover > 0, cover, 1.0)
    if plan.alpha:
        a = values[..., -1] if values is not None else normalise(plan.image[..., -1])
        lin[..., -1] = a
        if plan.dtype.kind == "u":  # straight alpha in the file: premultiply in linear light
            lin[..., :colour] *= a[..., None]
    return lin


def _premultiplied_cover(plan: BlurPlan, c: int, values: np.ndarray) -> np.ndarray | None:
    """The coverage that float colour channel ``c`` is premultiplied by, where the channel's
    response is not ``linear`` (under ``linear`` the colour is light already and passes as
    is); else None."""
    if not plan.alpha or plan.dtype.kind == "u" or plan.responses[c].kind == "linear":
        return None
    return values[..., -1]


def finish(acc: np.ndarray, plan: BlurPlan) -> np.ndarray:
    """Linear exposures -> output: forward response, (alpha) un-premultiply, quantise."""
    out = np.empty_like(acc)
    colour = plan.colour_channels
    straight = plan.alpha and plan.dtype.kind == "u"
    if straight:
        a = acc[..., -1]
        # a pixel whose coverage rounds to code 0 is transparent in the file: it has no
        # colour (0).  Its float coverage is a rounding residue whose sign and size depend
        # on the backend's arithmetic (float32 on a device), and colour / coverage there
        # would write that residue out as a colour
        seen = quantise(a, plan.dtype) > 0
        acc = acc.copy()
        acc[..., :colour] = np.where(seen[..., None], acc[..., :colour]
                                     / np.where(seen, a, 1.0)[..., None], 0.0)
    for c in range(colour):
        cover = _premultiplied_cover(plan, c, acc)
        if cover is None:
            out[..., c] = plan.responses[c].forward(acc[..., c])
            continue
        # premultiplied float colour: the response of the light per unit coverage, times
        # the coverage (a pixel without coverage keeps its light's response as is)
        seen = cover > 0
        unit = np.where(seen, cover, 1.0)
        out[..., c] = plan.responses[c].forward(acc[..., c] / unit) * unit
    if plan.alpha:
        # a mean of coverages in [0, 1] stays there; float32 sums (a device's) can end one
        # step past 1, and an "over" would then take a negative share of what is behind
        out[..., -1] = np.clip(acc[..., -1], 0.0, 1.0)
        if straight:
            out[..., :colour] = np.where(seen[..., None], out[..., :colour], 0.0)
    return plan.finish(quantise(out, plan.dtype))


def blur(plan: BlurPlan) -> np.ndarray:
    """The whole numpy pipeline for ``plan`` (``clblur.pipeline.run`` on these stages)."""
    from clblur.pipeline import run_numpy

    return run_numpy(plan)
