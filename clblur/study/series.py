"""Exposure series -> study groups: each image predicts the next shorter one and the one after.

With the paper's response the prediction is ``I(r I^-1(v))`` with ``r`` the nominal exposure
ratio (``exposure / f_number^2``); the longer image is the source, so its clipped highlights
are what the shorter image reveals.  A source code at the clip point (255, or lower for a
camera that clips below full scale, :func:`clip_code`) bounds its light from below only, so
such source pixels (and their 4-neighbours) are left out, as ``clblur calibrate`` leaves them
out, and a target at the clip point is censored like 255 (``saturation`` is then not
testable: it belongs to blur, where a clipped highlight's streak is what it measures); a
constant border a registration padded a frame with (``clblur.pixels.series_padding``) is
left out, and so is what does not show one static scene (``clblur.calibration.ghosts``: a
moving object, a border one frame lacks), as calibration leaves it out.  Each channel's
black level is bounded by the step's darker frame: its darkest patch allowing for noise,
grain and shading, not its darkest pixel, which read noise puts below the black level
(:func:`_black_bound`).

Why two gaps: a bracket in whole stops has one ratio ``r`` between neighbours, and with one
ratio a response is known only up to a power (``I^-1`` and ``(I^-1)^a`` predict alike once
the ratio is ``r^a``: the exponential ambiguity of Grossberg & Nayar 2003), which the
``exposure_gain`` effect would absorb, leaving ``response_shape`` unidentified.  Pairs two
steps apart (``r^2``) under the same gain break it.
"""

from __future__ import annotations

import math

import numpy as np

from clblur.calibration.ghosts import moving_pixels
from clblur.calibration.series import check_brightening, photometric_exposure
from clblur.errors import InputError
from clblur.pixels import near_clip, series_clip_level, series_padding
from clblur.study.histograms import Taps, as_hwc, build_group, sample_grid, shifted
from clblur.study.model import Group, censored_ends
from clblur.study.variants import SHIFTS

__all__ = ["clip_code", "series_groups"]


def clip_code(images: list[np.ndarray], exposures: list[float], block: int = 1,
              padding: list[np.ndarray] | None = None) -> int:
    """The 8-bit code at which a series clips (``clblur.pixels.series_clip_level`` of its
    8-bit codes): 255, or lower for a camera that clips below full scale or, stored
    lossless (``block`` 1), whose clipped pixels read below the pile (noise added after the
    clip, ``clblur.pixels.pile_floor``; ``padding`` as it takes it)."""
    codes = [as_hwc(im, f"image {i}") for i, im in enumerate(images)]
    return round(255 * series_clip_level(codes, exposures, lossless=block <= 1,
                                         padding=padding))


# px: the side of the patches whose means bound a black level (:func:`_black_bound`)
FLOOR_BOX = 5


def _black_bound(image: np.ndarray, padding: np.ndarray) -> np.ndarray:
    """A bound on each channel's black level from one frame (float codes): the darkest mean
    of a ``FLOOR_BOX`` square of light plus the deviation the least of that many means can
    have, at most the mean code of the whole frame's light.

    Every pixel's expected code is its channel's black level plus what its light adds, so
    the mean of the frame bounds the level soundly, but loosely (a fit then ranges over
    levels no dark pixel allows, and costs more).  The darkest patch is tighter and biased
    low: the least of ``n`` patch means lies about ``sqrt(2 ln n)`` of a patch mean's noise
    below its level, and grain, pattern noise and shading are correlated over a patch, so
    that noise can be as large as one pixel's.  Hence the darkest mean plus ``sqrt(2 ln n)``
    times the pixels' standard deviation in the darkest patches (the median over the
    darkest 1 %; ``n`` counted as independent patches).  Memorial's 1/1024 s frame: darkest
    5 x 5 means 12.7 / 16.3 / 15.4 codes in R / G / B, which as a bound held the fit below
    the level its dark frames show (a +1-code storage offset stood in for the rest); now
    bounded by its mean, 13.7 / 18.3 / 16.8, and fitted at 13.6 / 18.1 / 16.6.  Where the
    darkest patches are crushed to a constant code (a JPEG's blacks at 0) the bound is that
    code."""
    import cv2

    lit = ~padding
    if not lit.any():
        return np.zeros(image.shape[2])
    # integer codes: the float64 sums are exact either way, and a frame without padding
    # needs no gathered copy of itself (a 10 MP frame's mean took 0.6 s)
    light = image.reshape(-1, image.shape[2]) if lit.all() else image[lit]
    mean = light.mean(axis=0, dtype=np.float64)
    box = (FLOOR_BOX, FLOOR_BOX)
    clear = cv2.blur(lit.astype(np.float32), box) >= 1.0 - 1e-6
    r = FLOOR_BOX // 2
    clear[:r], clear[-r:], clear[:, :r], clear[:, -r:] = False, False, False, False
    if not clear.any():
        return mean
    area = FLOOR_BOX * FLOOR_BOX
    z = math.sqrt(2.0 * math.log(max(int(clear.sum()) / area, 2.0)))
    centres = np.flatnonzero(clear)  # the patches wholly in the light, once for every channel
    out = np.empty(image.shape[2])
    for c in range(image.shape[2]):
        x = image[..., c].astype(np.float32)
        # float32: its order and least value are float64's too
        m = np.take(cv2.blur(x, box), centres)
        k = max(1, m.size // 100)
        darkest = np.argpartition(m, k - 1)[:k]
        # the patches' variance at the darkest ones only (the rest is never read)
        m_dark = m[darkest].astype(np.float64)
        var = np.maximum(np.take(cv2.blur(x * x, box), centres[darkest]) - m_dark * m_dark,
                         0.0) * area / (area - 1)
        out[c] = min(mean[c], float(m.min()) + z * math.sqrt(float(np.median(var))))
    return out


def series_groups(images: list[np.ndarray], exposures: list[float],
                  f_numbers: list[float | None] | None = None, *,
                  max_pixels: int = 60000, notes: dict | None = None,
                  names: list[str] | None = None, block: int = 1) -> list[Group]:
    """The study groups of an exposure series: each image predicts the next shorter one and
    the one after (module doc).  ``notes``, when given, receives what was left out as no
    light: ``clip_code`` (below 255 for a camera that clips below full scale),
    ``padding`` (``{image index: fraction of its pixels}``, ``clblur.pixels.series_padding``)
    and ``moving`` (the fraction of pixels that do not show one static scene,
    ``clblur.calibration.ghosts``).
    A series whose images do not brighten with their exposures is refused, the two images
    named by ``names`` (``clblur.calibration.series.check_brightening``).
    ``block``: the side of the blocks a lossy codec coded the images in
    (``clblur.io.images.codec_block``: 8 or 16 for a JPEG), 1 for lossless storage; a source
    value within that many pixels of a clipped region, in any channel, is left out
    (:func:`_clipped_near`)."""
    if len(images) != len(exposures) or len(images) < 2:
        raise InputError("an exposure series needs at least 2 images, one exposure each")
    h = photometric_exposure(exposures, f_numbers).tolist()
    order = np.argsort(h)[::-1]  # longest first
    for a, b in zip(order[:-1], order[1:], strict=True):
        if h[a] == h[b]:  # a ratio of 1 says nothing of the response
            raise InputError(f"images {min(a, b)} and {max(a, b)} have the same exposure "
                             f"({h[a]:g}); each image of a series needs its own")
    imgs = [as_hwc(images[i], f"image {i}") for i in order]
    h = [h[i] for i in order]
    if any(im.shape != imgs[0].shape for im in imgs):
        raise InputError(f"series images differ in shape: "
                         f"{sorted({im.shape for im in imgs})}")
    # a constant border a registration padded a frame with holds no light: its pixels are
    # neither targets nor sources, and its zeros do not bound a black level
    pads = series_padding(imgs, h)
    top = clip_code(imgs, h, block, pads)
    names = [f"image {i}" for i in range(len(images))] if names is None else names
    check_brightening(imgs, h, [names[i] for i in order], top / 255)
    floors = [_black_bound(im, p) for im, p in zip(imgs, pads, strict=True)]
    # what does not show one static scene (a walker, branches in the wind, a border one
    # frame lacks) is no measurement of the camera: left out, as calibration leaves it out
    moving = moving_pixels(imgs, h, 255.0)
    if notes is not None:
        notes["clip_code"] = top
        notes["padding"] = {int(order[i]): float(p.mean()) for i, p in enumerate(pads)
                            if p.any()}
        notes["moving"] = float(moving.mean())
    steps = [(k, k + gap) for gap in (1, 2) for k in range(len(imgs) - gap)]
    per = max(1000, max_pixels // len(steps))
    groups = []
    dropped = sampled = 0  # sampled values whose source is clipped, of all
    for k, j in steps:
        src, tgt = imgs[k], imgs[j]
        rows, cols = sample_grid(tgt.shape[:2], per)
        lit = ~(pads[k][rows, cols] | pads[j][rows, cols] | moving[rows, cols])
        rows, cols = rows[lit], cols[lit]

        def taps(yy, xx):
            yield Taps(0, 0.0, 0.0, 1.0, None)

        g = build_group(f"step{k:02d}-{j:02d}", [src], tgt, rows, cols, taps,
                        h[j] / h[k], vignetting=False, timed=False,
                        variants={"misregistration": {sh: shifted(taps, *sh) for sh in SHIFTS}},
                        darkest=np.minimum(floors[k], floors[j]))
        # which images each row reads, for the images' own exposures (``effects``' lt:I):
        # the longest and the shortest are held at their nominal times, the rest are free
        g.images = np.tile(np.array([order[k], order[j]], np.intp), (g.rows.size, 1))
        g.__dict__["inner_images"] = tuple(sorted(int(i) for i in order[1:-1]))
        # A source code at the clip point (255, or a camera's lower clip) only bounds its
        # light from below: the shorter image reveals highlights at any multiple of it.
        # One saturation factor for all of them could not fit a scene whose highlights lie
        # 5 - 30 times above the clip (the reason to shoot a series), and their misfit
        # read as false noise, exposure, white-balance and curve findings and as structure
        # left, the paper's own camera included. So such pixels are left out, as
        # calibration leaves them out, with the 4-neighbours the misregistration effect's
        # shifted taps read (in a JPEG, a block around the clipped region as the codec
        # left it: ``_clipped_near``); a target at the clip point is censored like 255 (its
        # likelihood the tail beyond it, ``model.gaussian_nll``).
        clipped = _clipped_near(src, top, block)[g.rows, g.cols]
        g.valid &= (g.target < top) & ~clipped
        g.censored = censored_ends(g.target, ~clipped, top)
        g.top = float(top)
        dropped += int(clipped.sum())
        sampled += clipped.size
        g.source_clipped = False
        g.__dict__["clipped_left_out"] = True
        groups.append(g)
    if notes is not None:
        notes["clipped_sources"] = dropped / max(sampled, 1)
    return groups


def _clipped_near(image: np.ndarray, top: int, block: int = 1) -> np.ndarray:
    """Per pixel and channel (H x W x C bool): the values a clipped one (at or above ``top``)
    biases, which a series leaves out as sources.  Stored losslessly (``block`` 1): the
    clipped value and its 4-neighbours, which the misregistration effect's shifted taps
    read, each channel on its own.  Coded in blocks (a JPEG): everything within ``block``
    pixels of the clipped region as the codec left it, in every channel
    (``clblur.pixels.near_clip``: the codec's ringing pulls the plateau's pixels below the
    clip and shifts its blocks' other values)."""
    import cv2

    if block > 1:
        near = near_clip(image, top, block, reach=block)
        return np.repeat(near[:, :, None], image.shape[2], axis=2)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    near = cv2.dilate((image >= top).astype(np.uint8), cross)  # each channel on its own
    return near.reshape(image.shape).astype(bool)
