"""Exposure series -> study groups: each image predicts the next shorter one and the one after.

With the paper's response the prediction is ``I(r I^-1(v))`` with ``r`` the nominal exposure
ratio (``exposure / f_number^2``); the longer image is the source, so its clipped highlights
are what the shorter image reveals (the ``saturation`` effect).  A camera that clips below
full scale (:func:`clip_code`) has its pixels at or above the clip point censored, in the
target and at the source pixel; a constant border a registration padded a frame with
(``clblur.pixels.series_padding``) is left out.  The black level is bounded by the darkest
mean code of a ``FLOOR_BOX`` square of light in the step's two frames, not by the darkest
single pixel, which read noise puts below the black level (:func:`_floor`).

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


# px: the side of the box whose mean code bounds a black level (module doc)
FLOOR_BOX = 5


def _floor(image: np.ndarray, padding: np.ndarray) -> int:
    """The darkest mean code of a ``FLOOR_BOX`` square of light (no padding in it), over the
    channels: a black level is at most this.  Single pixels are not a bound: read noise
    scatters a dark frame's codes around its black level, and the darkest of a million
    pixels lies several noise widths below it (Memorial's 1/1024 s frame: a floor of 13-19
    codes, single pixels down to 6)."""
    import cv2

    box = (FLOOR_BOX, FLOOR_BOX)
    clear = cv2.blur((~padding).astype(np.float32), box) >= 1.0 - 1e-6
    r = FLOOR_BOX // 2
    clear[:r], clear[-r:], clear[:, :r], clear[:, -r:] = False, False, False, False
    if not clear.any():
        return int(image[~padding].min()) if (~padding).any() else 0
    means = [cv2.blur(image[..., c].astype(np.float32), box)[clear].min()
             for c in range(image.shape[2])]
    return int(min(means))


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
    floors = [_floor(im, p) for im, p in zip(imgs, pads, strict=True)]
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
                        darkest=min(floors[k], floors[j]))
        if top < 255:
            # a camera that clips below full scale: a code at its clip point is no measure
            # of light, in the target (censored like 255) nor in the source
            g.valid &= (g.target < top) & (src[g.rows, g.cols] < top)
        groups.append(g)
    return groups
