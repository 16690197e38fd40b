"""Exposure brackets of a textured scene for the registration and clipping tests: radiance
over about 6 stops, 8-bit codes of a gamma-2.2 camera with read noise."""

from __future__ import annotations

import cv2
import numpy as np


def scene(h: int, w: int, seed: int) -> np.ndarray:
    """Radiance of a textured scene over about 6 stops (blobs at several scales, a few
    hard-edged rectangles), H x W x 3."""
    rng = np.random.default_rng(seed)
    log_l = np.zeros((h, w), np.float32)
    for scale in (4, 16, 64):
        small = rng.normal(size=(h // scale + 2, w // scale + 2)).astype(np.float32)
        log_l += cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)[:h, :w]
    for _ in range(12):
        y, x = rng.integers(0, h - 8), rng.integers(0, w - 8)
        log_l[y:y + rng.integers(4, 40), x:x + rng.integers(4, 40)] += rng.normal(0, 1.5)
    lum = np.exp(1.2 * log_l)
    tint = np.array([0.8, 1.0, 1.2], np.float32)
    return lum[..., None] * tint / np.float32(np.median(lum))


def objects_scene(h: int, w: int, seed: int) -> np.ndarray:
    """Radiance of flat objects on a smooth background, H x W x 3: 40 rectangles 8 - 60 px
    of their own level (log-normal, about 4 stops) over a background that varies on a 64 px
    scale, so that many flat pixels differ from their wide surround (the surround check of
    ``clblur.calibration.surround``)."""
    rng = np.random.default_rng(seed)
    small = rng.normal(size=(h // 64 + 2, w // 64 + 2)).astype(np.float32)
    log_l = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)[:h, :w]
    for _ in range(40):
        y, x = rng.integers(0, h - 8), rng.integers(0, w - 8)
        log_l[y:y + rng.integers(8, 60), x:x + rng.integers(8, 60)] = rng.normal(0, 1.3)
    lum = np.exp(1.2 * log_l)
    tint = np.array([0.8, 1.0, 1.2], np.float32)
    return (lum[..., None] * tint / np.float32(np.median(lum))).astype(np.float64)


def exposure(radiance: np.ndarray, t: float, rng, pedestal: float = 0.0,
             noise: float = 0.004, exact_clip: bool = False,
             gains: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """8-bit codes of a gamma-2.2 camera with read noise (``noise``, fraction of full scale)
    and a pedestal, clipped.  The noise is added after the light clips, so a clipped pixel
    can read a few codes below its pile (``clblur.pixels.pile_floor``); ``exact_clip``:
    every clipped pixel reads the pile, as a sensor's converter clips.  ``gains``: per
    channel, applied after the clip (a white balance that puts a channel's pile below full
    scale)."""
    gain = np.asarray(gains, np.float64)
    v = np.clip(radiance * t, 0, 1) ** (1 / 2.2) * gain + pedestal
    v = v + rng.normal(0, noise, v.shape)
    if exact_clip:  # the converter clips signal and noise alike at the pile
        v = np.minimum(np.where(radiance * t >= 1.0, gain + pedestal, v), gain + pedestal)
    return np.clip(np.rint(v * 255), 0, 255).astype(np.uint8)
