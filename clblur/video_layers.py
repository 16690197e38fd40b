"""Two-layer exposure for one straight shutter half: moving objects smear over what is behind.

Why: ``clblur.blur`` *gathers* along each output pixel's own vector, so a pixel of a static
background next to a moving object never receives the object's light, and the object's streak
stops at its silhouette.  Physically, at shutter time ``t`` pixel ``p`` sees the object if the
object covers ``p`` then, and the background otherwise.

Conventions
-----------
* Layers are told apart by speed: a pixel is *moving* when its vector is longer than the
  slowest vector within ``R`` pixels by more than ``min_px`` (``R`` = the longest vector,
  rounded up) *and* within ``min_px`` of the longest moving vector within ``R`` (a rigid
  object's pixels all carry the fastest motion around them; a smooth speed gradient, as
  perspective gives during a pan, has no edge to smear across).  A camera pan moves everything
  alike, so it has no moving layer, and the result is the plain gather.
* Every pixel gets the longest moving vector within ``R`` pixels, ``D`` (zero where no moving
  pixel is that close).  With ``M`` the moving mask and ``L`` the linearised frame, all in the
  linear domain::

      A = blur(M L, D)      C = blur(M, D)             (object light reaching p; coverage)
      S = blur((1-M) L, v)  W = blur(1 - M, v)         (what is behind, along p's own vector)
      E = A + (1 - C) S / W

  In a scene with a static background and one object moving rigidly, ``E`` is the exact
  exposure wherever the background is visible in the frame.  Where ``W`` is zero (every
  sample of ``p``'s own path is on the object), ``S / W`` falls back to ``L(p)``.
* Where several objects overlap, the faster one is assumed to be in front.
"""

from __future__ import annotations

import math

import numpy as np

from clblur.blur import blur

MIN_PX = 1.0  # speed margin (pixels per shutter half) that marks a pixel as moving


def moving_mask(v: np.ndarray, radius: int, min_px: float = MIN_PX) -> np.ndarray:
    """Pixels moving faster than the slowest pixel within ``radius`` by more than ``min_px``."""
    import cv2

    speed = np.hypot(v[..., 0], v[..., 1]).astype(np.float32)
    k = 2 * radius + 1
    slowest = cv2.erode(speed, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return (speed - slowest) > min_px


def _shifted(a: np.ndarray, d: int, axis: int, fill: float) -> np.ndarray:
    """``a`` moved by ``d`` along ``axis`` (out[i] = a[i - d]), the gap filled with ``fill``."""
    out = np.full_like(a, fill)
    n = a.shape[axis]
    if abs(d) >= n:
        return out
    src = [slice(None)] * a.ndim
    dst = [slice(None)] * a.ndim
    src[axis] = slice(0, n - d) if d >= 0 else slice(-d, n)
    dst[axis] = slice(d, n) if d >= 0 else slice(0, n + d)
    out[tuple(dst)] = a[tuple(src)]
    return out


def _window_longest(length: np.ndarray, vec: np.ndarray, radius: int,
                    axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Longest vector within ``radius`` along ``axis``: doubling spans [x, x + 2^k - 1], then
    two overlapping spans cover [x - r, x + r] (O(log r) array passes instead of O(r))."""
    def better(la, va, lb, vb):
        take = lb > la
        return np.where(take, lb, la), np.where(take[..., None], vb, va)

    # pad by r so that every window start lies inside the array (padding never wins)
    pad = [(0, 0)] * length.ndim
    pad[axis] = (radius, radius)
    length = np.pad(length, pad, constant_values=-1.0)
    vec = np.pad(vec, pad + [(0, 0)], constant_values=0.0)
    k = (2 * radius + 1).bit_length() - 1  # 2^k <= 2r + 1 < 2^(k+1)
    span = 1
    for _ in range(k):
        length, vec = better(length, vec, _shifted(length, -span, axis, -1.0),
                             _shifted(vec, -span, axis, 0.0))
        span *= 2
    right = radius - span + 1  # the span starting there ends at x + r
    length, vec = better(_shifted(length, radius, axis, -1.0), _shifted(vec, radius, axis, 0.0),
                         _shifted(length, -right, axis, -1.0), _shifted(vec, -right, axis, 0.0))
    keep = [slice(None)] * length.ndim
    keep[axis] = slice(radius, length.shape[axis] - radius)
    return length[tuple(keep)], vec[tuple(keep)]


def dilate_vectors(v: np.ndarray, mask: np.ndarray, radius: int) -> np.ndarray:
    """For every pixel, the longest vector of a ``mask`` pixel within the (2r+1)^2 square
    around it (zero where there is none).  Separable: rows, then columns."""
    length = np.where(mask, np.hypot(v[..., 0], v[..., 1]), -1.0).astype(np.float32)
    vec = np.where(mask[..., None], v, 0.0).astype(np.float32)
    for axis in (1, 0):
        length, vec = _window_longest(length, vec, radius, axis)
    return vec


def layered_half(lin: np.ndarray, v: np.ndarray, anchor: str, *, samples: int | None = None,
                 backend: str = "auto", device: str | None = None,
                 min_px: float = MIN_PX) -> np.ndarray:
    """Linear exposure (H x W x C float32) of one straight shutter half with vectors ``v``."""
    opts = dict(anchor=anchor, samples=samples, backend=backend, device=device)
    longest = float(np.hypot(v[..., 0], v[..., 1]).max())
    radius = int(math.ceil(longest))
    mask = moving_mask(v, radius, min_px) if radius > 0 else None
    if mask is not None and mask.any():
        # Keep only pixels that carry the fastest motion around them: a rigid object's own
        # pixels do, while a smooth speed gradient (perspective during a pan) has no edge to
        # smear across and its pixels all lag the fastest vector near them.
        lag = np.hypot(*(dilate_vectors(v, mask, radius) - v).transpose(2, 0, 1))
        mask &= lag <= min_px
    if mask is None or not mask.any():
        return blur(lin, v, "linear", **opts)
    dilated = dilate_vectors(v, mask, radius)
    m = mask.astype(np.float32)[..., None]
    front = blur(np.concatenate([lin * m, m], axis=2), dilated, "linear", **opts)
    behind = blur(np.concatenate([lin * (1 - m), 1 - m], axis=2), v, "linear", **opts)
    a, coverage = front[..., :-1], front[..., -1:]
    s, w = behind[..., :-1], behind[..., -1:]
    background = np.where(w > 1e-6, s / np.maximum(w, 1e-6), lin)
    return a + (1 - coverage) * background
