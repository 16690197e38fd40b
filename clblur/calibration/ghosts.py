"""Pixels of an exposure series that do not show one static scene: what moved between the
exposures (people, leaves, cars, clouds), a frame's border that another frame lacks.

A response curve is calibrated from pixels that saw the same light in every exposure.  Real
brackets are rarely that clean: between two exposures a walker crosses the frame, and at her
pixels the longer exposure is darker or far brighter than the shorter one predicts.  A
least-squares fit bends towards such values, and the held-out score that ranks the families
counts them against every curve alike, so the ranking can flip: with six moving 120 x 120
blocks in two of five frames of the rendered Eq. 3 camera ``cam_c``, the polynomial's held-out
error went 2.7 -> 7.4 codes and the calibration chose a free spline over the exact Eq. 3.

The test needs no response model.  Between each pair of neighbouring exposures (``a`` shorter,
``b`` longer) a static pixel obeys one monotone *intensity mapping* ``b = M(a)`` per channel:
whatever the response, equal light in ``a`` is equal light in ``b``.  ``M`` is the median of
``b`` over the pixels at each level of ``a`` (the joint histogram of the pair), its spread
the median absolute deviation at that level.  A pixel is inconsistent when its ``b`` lies more
than ``K_SPREAD`` robust standard deviations and at least ``FLOOR`` of full scale outside
``M`` of every pixel of its ``a``'s 3 x 3 neighbourhood: the neighbourhood absorbs the
sub-pixel shift between tripod frames and the residue of registering a hand-held bracket,
which otherwise flags every edge (Memorial: 14 % of its pixels without it).  A wider one
absorbs moving objects on a textured scene too: at 5 x 5, a quarter of three objects' pixels
passed on a test scene, differing from the static frame by a median 32 - 54 codes.  Specks
thinner than 3 x 3 are dropped (noise, a single hot pixel), gaps are closed by a 9-pixel
disc, and what is left is widened by 2 pixels, as a moving object's silhouette is blurred.
A pixel is left out when it fails in any pair and any channel: an object in one frame
spoils the pixel's row of the whole series.

Levels are the codes of an 8-bit series and 1024 bins of full scale otherwise (a 16-bit
series' noise spans many codes; ``FLOOR`` is far above a bin), coarser for an image too
small to put ``PER_LEVEL`` pixels in each on average.  Clipped pixels are judged
like the others: a level of ``a`` whose pixels clip in ``b`` maps to the clip, so a bright
object that clips where the scene did not (or a dark one under a clipped level) stands out;
levels with fewer than ``MIN_COUNT`` pixels are not judged.

On the rendered cameras ``cam_a`` .. ``cam_d`` (``docs/studies/rendered_brackets.py``) nothing
is left out; on the Canon 400D night bracket 0.08 % (branches in the wind, a light); on
Memorial 9.4 %, most of it its top 25 rows and its edge columns, which some of its frames
hold at code 0 while the others see the church (a scan border, not light the response
recorded), and a few blobs of 10 - 30 pixels at high-contrast edges.
"""

from __future__ import annotations

import cv2
import numpy as np

from clblur.pixels import imax

__all__ = ["FLOOR", "K_SPREAD", "MIN_COUNT", "PER_LEVEL", "moving_pixels"]

K_SPREAD = 6.0  # robust standard deviations of b at a's level: noise does not get this far
FLOOR = 0.05  # of full scale: below it a difference is texture or noise, not an object
MIN_COUNT = 50  # pixels at a level before its median and spread are trusted
PER_LEVEL = 200  # pixels per level on average: a small image gets coarser levels
_NEIGHBOURHOOD = np.ones((3, 3), np.uint8)
_SPECK = np.ones((3, 3), np.uint8)
_WIDEN = 2
_CLOSE = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))


def _bins(image: np.ndarray) -> int:
    """Levels per channel: the codes of an 8-bit image, 1024 otherwise, fewer where the
    image is too small to fill each with ``PER_LEVEL`` pixels (at least 32)."""
    most = 256 if image.dtype == np.uint8 else 1024
    return int(min(most, max(32, image.shape[0] * image.shape[1] // PER_LEVEL)))


def _levels(image: np.ndarray, full_scale: float, bins: int) -> np.ndarray:
    """Each value's level: one of ``bins`` equal steps of full scale (an 8-bit code when
    ``bins`` is 256)."""
    # int32: a pair's joint index (at most 1024 * 1024) fits, at half the memory of int64
    if image.dtype == np.uint8 and bins == 256:
        return image.astype(np.int32)
    v = image.astype(np.float32) * np.float32(bins / full_scale)
    return np.clip(v, 0, bins - 1).astype(np.int32)


def _mapping(a: np.ndarray, b: np.ndarray, bins: int):
    """Median of ``b``'s level per level of ``a`` and the half-width each may stray by."""
    joint = np.bincount((a * bins + b).ravel(), minlength=bins * bins).reshape(bins, bins)
    count = joint.sum(axis=1)
    median = np.argmax(np.cumsum(joint, axis=1) >= (count[:, None] + 1) // 2, axis=1)
    # the median absolute deviation per level, from the same histogram
    dev = np.abs(np.arange(bins)[None, :] - median[:, None])
    spread = np.bincount((np.arange(bins)[:, None] * bins + dev).ravel(), joint.ravel(),
                         minlength=bins * bins).reshape(bins, bins)
    mad = np.argmax(np.cumsum(spread, axis=1) >= (count[:, None] + 1) / 2, axis=1)
    width = np.maximum(K_SPREAD * 1.4826 * mad, FLOOR * bins).astype(np.float32)
    width[count < MIN_COUNT] = np.inf
    return median.astype(np.float32), width


def moving_pixels(images: list[np.ndarray], exposures,
                  full_scale: float | None = None) -> np.ndarray:
    """Where an exposure series does not show one static scene (module doc).

    Args:
        images: the series' images, H x W x C, one dtype.
        exposures: their photometric exposures (any scale; only the order is used).
        full_scale: the images' full scale (default: ``clblur.pixels.imax`` of their dtype).

    Returns:
        H x W bool, True where some pair of neighbouring exposures disagrees.
    """
    first = images[0]
    if full_scale is None:
        full_scale = imax(first.dtype)
    bins = _bins(first)
    order = np.argsort(np.asarray(exposures, dtype=np.float64), kind="stable")
    out = np.zeros(first.shape[:2], bool)
    for i, j in zip(order[:-1], order[1:], strict=True):
        for c in range(first.shape[2]):
            a = _levels(images[i][..., c], full_scale, bins)
            b = _levels(images[j][..., c], full_scale, bins)
            median, width = _mapping(a, b, bins)
            mapped, slack = median[a], width[a]
            lo = cv2.erode(mapped, _NEIGHBOURHOOD)
            hi = cv2.dilate(mapped, _NEIGHBOURHOOD)
            bad = np.isfinite(slack) & ((b > hi + slack) | (b < lo - slack))
            out |= cv2.morphologyEx(bad.astype(np.uint8), cv2.MORPH_OPEN, _SPECK).astype(bool)
    if out.any():
        size = 2 * _WIDEN + 1
        mask = cv2.morphologyEx(out.astype(np.uint8), cv2.MORPH_CLOSE, _CLOSE)
        out = cv2.dilate(mask, np.ones((size, size), np.uint8)).astype(bool)
    return out
