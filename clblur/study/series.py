"""Exposure series -> study groups: each image predicts the next shorter one and the one after.

With the paper's response the prediction is ``I(r I^-1(v))`` with ``r`` the nominal exposure
ratio (``exposure / f_number^2``); the longer image is the source, so its clipped highlights
are what the shorter image reveals (the ``saturation`` effect).  A camera that clips below
full scale (:func:`clip_code`) has its pixels at or above the clip point censored, in the
target and at the source pixel; a constant border a registration padded a frame with
(``clblur.pixels.series_padding``) is left out.  Each channel's black level is bounded by the
mean code of the step's darker frame, not by its darkest pixel or patch, which noise and
shading put below the black level (:func:`_black_bound`).

Why two gaps: a bracket in whole stops has one ratio ``r`` between neighbours, and with one
ratio a response is known only up to a power (``I^-1`` and ``(I^-1)^a`` predict alike once
the ratio is ``r^a``: the exponential ambiguity of Grossberg & Nayar 2003), which the
``exposure_gain`` effect would absorb, leaving ``response_shape`` unidentified.  Pairs two
steps apart (``r^2``) under the same gain break it.
"""

from __future__ import annotations

import numpy as np

from clblur.pixels import series_clip_level, series_padding
from clblur.study.histograms import Taps, as_hwc, build_group, sample_grid, shifted
from clblur.study.model import Group
from clblur.study.variants import SHIFTS

__all__ = ["clip_code", "series_groups"]


def clip_code(images: list[np.ndarray], exposures: list[float]) -> int:
    """The 8-bit code at which a series clips (``clblur.pixels.series_clip_level`` of its
    8-bit codes): 255, or lower for a camera that clips below full scale."""
    codes = [as_hwc(im, f"image {i}") for i, im in enumerate(images)]
    return round(255 * series_clip_level(codes, exposures))


def _black_bound(image: np.ndarray, padding: np.ndarray) -> np.ndarray:
    """The mean code of a frame's light (its pixels but the padding), per channel: that
    channel's black level is at most this (float codes).

    Why the mean and not the darkest code or patch: every pixel's expected code is its
    channel's black level plus what its light adds (zero or more; rounding at code 0 and
    clipping at the top only keep it there), so the mean over a whole frame bounds the
    level up to a negligible sampling error.  The darkest pixel does not: read noise puts it
    several noise widths below the level (Memorial's 1/1024 s frame: channel means 13.7 /
    18.3 / 16.8 codes, single pixels down to 6).  Nor does the darkest patch: film grain,
    pattern noise and shading vary the black over the frame, so its darkest 5 x 5 mean lies
    1 - 3 codes below the level (12.5 / 15.4 / 14.8) and even its darkest 32 x 32 mean
    below it (12.9 / 16.5 / 15.5); bounded there the fit stopped short of the level the
    frames show (13.5 / 17.9 / 16.6 unbounded) and an offset of the stored codes stood in
    for the rest.  A bound that is a little loose only lets the likelihood decide."""
    lit = image[~padding]
    if not lit.size:
        return np.zeros(image.shape[2])
    return lit.reshape(-1, image.shape[2]).mean(axis=0, dtype=np.float64)


def series_groups(images: list[np.ndarray], exposures: list[float],
                  f_numbers: list[float | None] | None = None, *,
                  max_pixels: int = 60000, notes: dict | None = None) -> list[Group]:
    """The study groups of an exposure series: each image predicts the next shorter one and
    the one after (module doc).  ``notes``, when given, receives what was left out as no
    light: ``clip_code`` (below 255 for a camera that clips below full scale) and
    ``padding`` (``{image index: fraction of its pixels}``, ``clblur.pixels.series_padding``)."""
    if len(images) != len(exposures) or len(images) < 2:
        raise ValueError("an exposure series needs at least 2 images, one exposure each")
    f_numbers = f_numbers or [None] * len(images)
    if len({f is None for f in f_numbers}) > 1:  # else exposures in two units get mixed
        raise ValueError("give an F-number for every image of the series or for none")
    h = [e / (f * f if f else 1.0) for e, f in zip(exposures, f_numbers, strict=True)]
    order = np.argsort(h)[::-1]  # longest first
    for a, b in zip(order[:-1], order[1:], strict=True):
        if h[a] == h[b]:  # a ratio of 1 says nothing of the response
            raise ValueError(f"images {min(a, b)} and {max(a, b)} have the same exposure "
                             f"({h[a]:g}); each image of a series needs its own")
    imgs = [as_hwc(images[i], f"image {i}") for i in order]
    h = [h[i] for i in order]
    if any(im.shape != imgs[0].shape for im in imgs):
        raise ValueError(f"series images differ in shape: "
                         f"{sorted({im.shape for im in imgs})}")
    top = clip_code(imgs, h)
    # a constant border a registration padded a frame with holds no light: its pixels are
    # neither targets nor sources, and its zeros do not bound a black level
    pads = series_padding(imgs, h)
    floors = [_black_bound(im, p) for im, p in zip(imgs, pads, strict=True)]
    if notes is not None:
        notes["clip_code"] = top
        notes["padding"] = {int(order[i]): float(p.mean()) for i, p in enumerate(pads)
                            if p.any()}
    steps = [(k, k + gap) for gap in (1, 2) for k in range(len(imgs) - gap)]
    per = max(1000, max_pixels // len(steps))
    groups = []
    for k, j in steps:
        src, tgt = imgs[k], imgs[j]
        rows, cols = sample_grid(tgt.shape[:2], per)
        lit = ~(pads[k][rows, cols] | pads[j][rows, cols])
        rows, cols = rows[lit], cols[lit]

        def taps(yy, xx):
            yield Taps(0, 0.0, 0.0, 1.0, None)

        g = build_group(f"step{k:02d}-{j:02d}", [src], tgt, rows, cols, taps,
                        h[j] / h[k], vignetting=False, timed=False,
                        variants={"misregistration": {sh: shifted(taps, *sh) for sh in SHIFTS}},
                        darkest=np.minimum(floors[k], floors[j]))
        if top < 255:
            # a camera that clips below full scale: a code at its clip point is no measure
            # of light, in the target (censored like 255) nor in the source
            g.valid &= (g.target < top) & (src[g.rows, g.cols] < top)
        groups.append(g)
    return groups
