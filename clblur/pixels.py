"""Pixel values <-> linear exposure: the two ends of the blur pipeline.

Conventions
-----------
* dtypes: uint8 (Imax 255), uint16 (Imax 65535), float32 / float64 (Imax 1.0).  The output
  has the input's dtype and shape.
* Normalised value ``v = code / Imax``.
* Linearise (``E = I^-1(v)``), with a saturation policy for full-scale pixels:
  - integer images: a pixel at code Imax is clipped, so its true exposure is only known to be
    at least ``E_fs``; it gets ``saturation * E_fs``.  ``saturation >= 1``, default 1.
  - float images: ``v >= 1`` is full scale and treated the same way, except under the
    unbounded ``linear`` response, where values pass through untouched.
  - ``E_fs = I^-1(1)`` when that is finite; for responses that reach full scale only at
    infinite exposure (the paper's Eq. 3) it is ``I^-1(1 - q/4)`` with ``q`` one code step
    (1/255 for uint8, 1/65535 for uint16 and floats): a finite exposure whose value lies inside
    the top code bin with a margin for float32 arithmetic, so a constant saturated region stays
    at full scale.
* Clipping below full scale (``clip_level``): a camera whose highlights stop under full
  scale; measurement code (calibration, the study) treats that level as the clip point.
  Padding (``series_padding``): a constant-colour border a registration or crop added, which
  holds no light; the study leaves it out.
* Quantise: integer outputs are ``rint(clip(v, 0, 1) * Imax)``, round half to even (the IEEE
  default, identical in numpy and OpenCL).  Float outputs are not rounded; bounded responses
  already land in [0, 1].
"""

from __future__ import annotations

import math

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.responses import Response

__all__ = ["SUPPORTED_DTYPES", "clip_level", "code_step", "full_scale_exposure", "imax",
           "linearisation_table", "linearise", "near_clip", "normalise", "pile_floor",
           "quantise", "series_clip_level",
           "series_padding", "top_value", "validate_saturation"]

SUPPORTED_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)


def imax(dtype: np.dtype) -> float:
    """Full-scale code value of a dtype."""
    dtype = np.dtype(dtype)
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    if dtype in (np.float32, np.float64):
        return 1.0
    raise InputTypeError(f"unsupported image dtype {dtype}; use uint8, uint16, float32 or float64")


def code_step(dtype: np.dtype) -> float:
    """One code value in normalised units; floats are treated as 16-bit precise."""
    return 1.0 / 255.0 if np.dtype(dtype) == np.uint8 else 1.0 / 65535.0


def full_scale_exposure(resp: Response, dtype: np.dtype) -> float:
    """``E_fs``: the exposure assigned to a full-scale pixel before the saturation factor."""
    top = float(resp.inverse(np.array(1.0)))
    if math.isfinite(top):
        return top
    return float(resp.inverse(np.array(1.0 - code_step(dtype) / 4.0)))


def top_value(resp: Response, dtype: np.dtype) -> float:
    """Largest normalised value linearised as is; above it the saturation policy applies."""
    return 1.0 if math.isfinite(float(resp.inverse(np.array(1.0)))) else \
        1.0 - code_step(dtype) / 4.0


def linearise(values: np.ndarray, resp: Response, dtype: np.dtype,
              saturation: float) -> np.ndarray:
    """Normalised values of one channel (float64) -> linear exposure (float64)."""
    if not resp.bounded:
        if np.dtype(dtype).kind == "f":
            return resp.inverse(values)
        return np.where(values >= 1.0, saturation * resp.inverse(np.array(1.0)),
                        resp.inverse(values))
    e_fs = full_scale_exposure(resp, dtype)
    v = np.clip(values, 0.0, top_value(resp, dtype))
    return np.where(values >= 1.0, saturation * e_fs, resp.inverse(v))


def linearisation_table(resp: Response, dtype: np.dtype, saturation: float) -> np.ndarray:
    """Exposure for every code value of an integer dtype (float64, length Imax + 1)."""
    n = int(imax(dtype))
    return linearise(np.arange(n + 1, dtype=np.float64) / n, resp, dtype, saturation)


def normalise(image: np.ndarray) -> np.ndarray:
    """Image -> float64 normalised values (same shape)."""
    return image.astype(np.float64) / imax(image.dtype)


def quantise(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Normalised float64 values -> output dtype (rounding rule in the module docstring)."""
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        return values.astype(dtype)
    full = imax(dtype)
    return np.rint(np.clip(values, 0.0, 1.0) * full).astype(dtype)


def validate_saturation(saturation: float) -> float:
    try:
        s = float(saturation)
    except (TypeError, ValueError):
        raise InputTypeError(f"saturation must be a number, got {saturation!r}") from None
    if not math.isfinite(s) or s < 1.0:
        raise InputError(f"saturation must be a finite number >= 1 (a clipped pixel is at "
                         f"least as bright as full scale), got {saturation}")
    return s


# a pile-up at the highest code: at least this share of the pixels (and 50), and this many
# times the mean count of the 8 codes below it (a scene's own highlights taper off)
_PILE_SHARE = 5e-4
_PILE_RATIO = 4.0
# clipped pixels hold many radiances: one exposure shorter they spread over at least this
# fraction of full scale (10th to 90th percentile), or sit at the same top code again
_CLIP_SPREAD = 8.0 / 255.0


def clip_level(brightest: np.ndarray, darker: np.ndarray | None = None) -> float:
    """The fraction of full scale at which an integer image clips, 1.0 when it clips at full
    scale or shows no clipping (float images: 1.0).

    A clipped channel piles its pixels up at one highest code.  A channel whose highest code
    is below full scale and holds such a pile-up (``_PILE_SHARE`` of the pixels and
    ``_PILE_RATIO`` times the codes just below) clips there, if ``darker`` (the same scene
    at a shorter exposure, when there is one) agrees: a clipped code stands for every
    radiance above the clip point, so in the darker image those pixels spread over at least
    ``_CLIP_SPREAD`` or are clipped again, where a flat patch that is merely the brightest
    thing in view (a test chart) stays one value.  The lowest such level over the channels
    is returned (one valid range serves every channel)."""
    if brightest.dtype.kind != "u":
        return 1.0
    if brightest.ndim == 2:
        brightest = brightest[..., None]
        darker = None if darker is None else darker.reshape(brightest.shape)
    full = imax(brightest.dtype)
    level = 1.0
    for c in range(brightest.shape[2]):
        plane = brightest[..., c]
        counts = np.bincount(plane.ravel())
        top = counts.size - 1
        if top >= full or top < 16:
            continue
        piled = (counts[top] >= max(50, _PILE_SHARE * plane.size)
                 and counts[top] >= _PILE_RATIO * counts[top - 8:top].mean())
        if piled and darker is not None:
            there = darker[..., c][plane == top].astype(np.float64)
            lo, hi = np.percentile(there, [10, 90])
            piled = hi - lo >= _CLIP_SPREAD * full or np.mean(there == top) >= 0.5
        if piled:
            level = min(level, top / full)
    return level


# A clipped pixel can read below its pile where noise was added after the clip (a film
# scanner's, or a generator that adds read noise to code values and then clips them).  A bin
# of 1/255 of full scale belongs to that spread when at least this share of the surely
# clipped pixels reads in it and every bin up to the pile does too: Memorial's scans put
# 0.02 - 0.03 % of them one code below 255, read noise of 1 code 6 % and 0.6 % one and two
# codes below.  Fewer surely clipped pixels than the minimum say nothing.
_SPREAD_SHARE = 1e-3
_SPREAD_PIXELS = 500
# how far below the top code (bins of 1/255) a pile spread both ways by noise is looked for,
# and the longest spread below a pile read as noise: 4 noise sigmas of 3 codes
_PILE_REACH = 12


def pile_floor(images: list[np.ndarray], exposures,
               padding: list[np.ndarray] | None = None) -> float:
    """The lowest value (fraction of full scale, on a grid of 1/255) that a clipped pixel of
    an exposure series reads; 1.0 where its clipped pixels read only the top code, or where
    too few are surely clipped to tell (float images: 1.0).

    A pixel at a channel's pile in one image (its top code; or, where noise spreads a pile
    below full scale both ways, the longest image's most common value near the top, the
    top code then being the spread's upper tail) is clipped there, so it is clipped in every
    longer exposure too (at least 1.2 times longer).  Where noise was added after the clip,
    those pixels spread below the top in the longer image, and a value in that spread may be
    a clipped pixel, not light: as a source its light is far above what it reads (two pools
    of such pixels at code 252 put a spline fit 10 - 65 codes off at its top), as a target it
    reads below what the curve predicts.  The spread is the run of bins below the top that
    each hold ``_SPREAD_SHARE`` of those pixels (outliers of a misregistered edge or a moving
    object far below it are not contiguous with it).  ``padding``: per image, pixels that
    hold no light (``series_padding``), left out; computed when not given.  The lowest such
    level over the channels is returned.  Lossless images only: a JPEG's clipped region is
    spread by its codec in blocks, and ``near_clip`` leaves that out."""
    if images[0].dtype.kind != "u" or len(images) < 2:
        return 1.0
    h = np.asarray(exposures, np.float64)
    order = np.argsort(h)  # shortest first
    pairs = [(d, b) for d, b in zip(order[:-1], order[1:], strict=True) if h[b] >= 1.2 * h[d]]
    if not pairs:
        return 1.0
    if padding is None:
        padding = series_padding(images, exposures)
    full = int(imax(images[0].dtype))
    level = 1.0
    for c in range(images[0].shape[2]):
        # the pile's bin: the top code's, or, where noise spreads a pile below full scale
        # both ways, the most common bin of the longest image within _PILE_REACH of the top
        # code (which is then the spread's upper tail)
        top = max(int(im[..., c].max()) for im in images) * 255 // full
        if top < 16:  # as for clip_level: no highlights to clip
            continue
        longest = np.bincount(images[order[-1]][..., c].ravel().astype(np.int64) * 255 // full,
                              minlength=256)
        reach = max(0, top - _PILE_REACH)
        peak = reach + int(np.argmax(longest[reach:top + 1]))
        start = -(-peak * full // 255)  # the lowest code in the pile's bin
        read = [images[b][..., c][(images[d][..., c] >= start) & ~padding[d] & ~padding[b]]
                for d, b in pairs]
        values = np.concatenate(read).astype(np.int64)
        if values.size < _SPREAD_PIXELS:
            continue
        bins = np.bincount(values * 255 // full, minlength=256)
        piled = int(np.argmax(bins))  # where the surely clipped pixels read most often
        if abs(piled - peak) > 1:  # ... not at the pile: they are not piled
            continue
        lowest = piled
        while lowest > 0 and bins[lowest - 1] >= _SPREAD_SHARE * values.size:
            lowest -= 1
        if piled - lowest > _PILE_REACH:  # a run that long is the scene's, not noise on a pile
            continue
        level = min(level, lowest / 255.0)
    return level


def series_clip_level(images: list[np.ndarray], exposures, lossless: bool = True,
                      padding: list[np.ndarray] | None = None) -> float:
    """:func:`clip_level` of an exposure series: its longest exposure, which clips the most,
    checked on the next longest (``exposures`` in any consistent unit); for ``lossless``
    images, lowered to the :func:`pile_floor` where noise spreads the pile below its code
    (``padding`` as it takes it)."""
    order = np.argsort(np.asarray(exposures, np.float64))[::-1]
    level = clip_level(images[order[0]], images[order[1]] if len(order) > 1 else None)
    if lossless:
        level = min(level, pile_floor(images, exposures, padding))
    return level


def near_clip(image: np.ndarray, top: float, block: int, reach: int) -> np.ndarray:
    """H x W bool: the clipped region of an image a lossy codec coded in ``block``-pixel
    blocks (a JPEG's 8 or 16, ``clblur.io.images.codec_block``), grown by ``reach`` pixels.

    The region is every pixel at or above ``top`` in any channel, with the gaps narrower
    than a block between such pixels closed.  The codec rings around a clipped highlight's
    edge: some of its plateau's pixels come out a few codes below the clip, and so escape
    a test on their own code although their light is far above it (a calibration bent its
    curve's top 24 - 98 % up for them), and the ringing shifts the other values of the
    plateau's blocks in a pattern that differs from frame to frame as the edge's height
    does, in every channel (the colour transform mixes them).  The grid of the blocks is not
    known once a registration has cropped the frame or an EXIF tag turned it, so ``reach``
    goes every way: a whole block (``reach = block``) for the study, which scores every
    value and found exposure times of their own 3 - 4 % off without it
    (``clblur.study.series``); a couple of pixels beyond a patch for calibration, whose
    flattest patches lie away from edges and whose curve needs the samples near the top
    (``clblur.calibration.series.ExposureSeries.coded_near_clip``).
    docs/studies/validation.md, "A JPEG's clipped blocks"."""
    import cv2

    hit = (image >= top).any(axis=2).astype(np.uint8)
    if not hit.any():
        return np.zeros(hit.shape, bool)
    closed = cv2.morphologyEx(hit, cv2.MORPH_CLOSE, np.ones((block, block), np.uint8))
    side = 2 * int(reach) + 1
    return cv2.dilate(closed, np.ones((side, side), np.uint8)).astype(bool)


# a run of one exact colour along an image edge at least this long may be padding
_PAD_RUN = 16
# ... and is, when its pixels break the order of exposures by this much (fraction of full
# scale, the median over the region): brighter than a longer exposure or darker than a
# shorter one, which light cannot be
_PAD_BREAK = 0.03
_PAD_SAMPLES = 4096


def _border_runs(image: np.ndarray) -> list[np.ndarray]:
    """Candidate padding of an H x W x C image: for each exact colour that runs along an edge
    for at least ``_PAD_RUN`` pixels, the pixels of that colour connected to the run."""
    import cv2

    h, w, c = image.shape
    seeds: dict[tuple, list[tuple[int, int]]] = {}
    for e, line in enumerate([image[0], image[-1], image[:, 0], image[:, -1]]):
        # runs of one exact colour along the edge: where the colour changes, a run ends
        change = np.flatnonzero((line[1:] != line[:-1]).any(axis=1)) + 1
        for a, b in zip(np.r_[0, change], np.r_[change, line.shape[0]], strict=True):
            if b - a >= _PAD_RUN:
                pos = ((0, a), (h - 1, a), (a, 0), (a, w - 1))[e]
                seeds.setdefault(tuple(line[a].tolist()), []).append(pos)
    if not seeds:
        return []
    # one number per pixel for its colour (exact for integer codes; float images compare
    # their channels), so that each candidate colour costs one comparison
    if image.dtype.kind == "u" and c * image.dtype.itemsize <= 8:
        key = np.zeros((h, w), np.uint64)
        for k in range(c):
            key = (key << np.uint64(8 * image.dtype.itemsize)) | image[..., k]

        def same(colour):
            return key == np.uint64(sum(int(v) << (8 * image.dtype.itemsize * (c - 1 - k))
                                        for k, v in enumerate(colour)))
    else:
        def same(colour):
            return (image == np.asarray(colour, image.dtype)).all(axis=2)
    regions = []
    for colour, points in seeds.items():
        grown = same(colour).astype(np.uint8)
        mask = np.zeros((h + 2, w + 2), np.uint8)
        for y, x in points:  # the pixels of this colour 4-connected to a run, marked 2
            if grown[y, x] == 1:
                cv2.floodFill(grown, mask, (int(x), int(y)), 2, 0, 0, 4)
        regions.append(grown == 2)
    return regions


def series_padding(images: list[np.ndarray], exposures) -> list[np.ndarray]:
    """For each frame of an exposure series, the pixels of a constant-colour border that
    holds no light of the scene (H x W bool): what a registration or a crop padded it with.

    Why: registered stacks are often padded where a frame was shifted; Memorial's frames
    carry bands of pure blue (0, 0, 255) along their edges, 0.2 to 4.4 % of each frame,
    whose zeros a study would read as the camera's darkest code and whose 255s as clipped
    light.  A candidate is one exact colour running along an edge for at least ``_PAD_RUN``
    pixels, with every pixel of that colour connected to the run.  Exact runs also occur in
    the scene (crushed blacks, a clipped sky, the flat floor of a dark frame), so a
    candidate is padding only where it breaks the order of exposures: in the median over
    its pixels, brighter than some longer frame or darker than some shorter one by
    ``_PAD_BREAK`` of full scale in some channel, the other frames read where they are not
    candidates themselves (their own padding proves nothing)."""
    ims = [im if im.ndim == 3 else im[..., None] for im in images]
    x = np.asarray(exposures, np.float64)
    out = [np.zeros(im.shape[:2], bool) for im in ims]
    if len(ims) < 2 or min(ims[0].shape[:2]) < 2:
        return out
    candidates = [_border_runs(im) for im in ims]
    loose = [np.logical_or.reduce(c) if c else np.zeros(im.shape[:2], bool)
             for c, im in zip(candidates, ims, strict=True)]
    limit = _PAD_BREAK * (imax(ims[0].dtype) if ims[0].dtype.kind == "u" else 1.0)
    for i, regions in enumerate(candidates):
        for region in regions:
            # the median over the region, from at most _PAD_SAMPLES of its pixels
            at = np.flatnonzero(region)
            at = at[np.linspace(0, at.size - 1, min(at.size, _PAD_SAMPLES)).astype(np.intp)]
            here = ims[i].reshape(-1, ims[i].shape[2])[at].astype(np.float64)
            breaks = np.zeros(at.size)
            for j, other in enumerate(ims):
                if j == i or x[j] == x[i]:
                    continue
                sign = 1.0 if x[j] < x[i] else -1.0  # darker than shorter, brighter than longer
                there = other.reshape(-1, other.shape[2])[at].astype(np.float64)
                gap = (sign * (there - here)).max(axis=1)
                breaks = np.maximum(breaks, np.where(loose[j].ravel()[at], 0.0, gap))
            if np.median(breaks) > limit:
                out[i] |= region
    return out
