"""Choosing calibration samples from an exposure series.

Conventions
-----------
* A sample is one channel of one small flat patch (``patch`` x ``patch`` pixels, averaged),
  observed in every image of the series: a row of normalised values, one per exposure.
* A value is *valid* when ``low < v < high`` (defaults 0.02 and 0.98 of full scale, i.e.
  codes 6..249 in uint8): clipped highlights and the noisy, black-level-dominated bottom carry
  no usable response information and are masked, never fitted.
* Patches are spread over the value range by stratifying on the pixel's mean value across the
  stack, which increases with scene radiance for *any* monotone response; within a stratum the
  flattest patches win (lowest local standard deviation), so a little misalignment between the
  exposures or sensor noise barely changes the sample.
* A patch is valid in an image only if all its pixels are; a patch whose valid values fall by
  more than ``monotone_tolerance`` while the exposure grows is rejected (corrupt or moving).
* ``pixels``: besides the patches, ``n_pixels`` single pixels drawn uniformly at random (edges,
  textures and dark pixels included, outside the patches) for fits that minimise the
  cross-exposure prediction error on the kind of pixels the evaluation scores.  Both are in
  the ``footprint``, so the evaluation never scores a pixel any fit has seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError

__all__ = ["MONOTONE_TOLERANCE", "N_PIXELS", "VALID_HIGH", "VALID_LOW", "SampleSet", "Sampling",
           "sample_series", "valid_mask"]

VALID_LOW = 0.02
VALID_HIGH = 0.98
# A patch whose value drops by more than this (normalised) while the exposure grows is not a
# static, noise-limited observation (a moving object, a misaligned edge, a corrupt pixel).
MONOTONE_TOLERANCE = 0.03
# Random single pixels per channel for the cross-exposure fit (pooled by value, so the fit's
# cost does not grow with it; the held-out pixels are all the others).
N_PIXELS = 20000


@dataclass(frozen=True)
class SampleSet:
    """Samples of one fit: ``values`` (P, n) normalised, ``valid`` (P, n), ``channel`` (P,)."""

    values: np.ndarray
    valid: np.ndarray
    channel: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    lowest: np.ndarray  # (P, n) darkest pixel of each patch, to re-apply another valid range
    highest: np.ndarray  # (P, n) brightest pixel of each patch

    FIELDS = ("values", "valid", "channel", "rows", "cols", "lowest", "highest")

    def __len__(self) -> int:
        return self.values.shape[0]

    def _rows(self, mask) -> SampleSet:
        return SampleSet(*(getattr(self, f)[mask] for f in self.FIELDS))

    def drop_exposure(self, index: int) -> SampleSet:
        keep = np.arange(self.values.shape[1]) != index
        cut = SampleSet(self.values[:, keep], self.valid[:, keep], self.channel, self.rows,
                        self.cols, self.lowest[:, keep], self.highest[:, keep])
        return cut._rows(cut.valid.sum(axis=1) >= 2)

    def with_range(self, low: float, high: float) -> SampleSet:
        """The same patches with validity re-judged for ``low < v < high`` (>= 2 valid)."""
        valid = self.valid & (self.lowest > low) & (self.highest < high)
        cut = SampleSet(self.values, valid, self.channel, self.rows, self.cols, self.lowest,
                        self.highest)
        return cut._rows(valid.sum(axis=1) >= 2)

    @staticmethod
    def concat(sets: list[SampleSet]) -> SampleSet:
        return SampleSet(*(np.concatenate([getattr(s, f) for s in sets])
                           for f in SampleSet.FIELDS))


@dataclass(frozen=True)
class Sampling:
    """Per-channel sample sets and the pixels they cover (excluded from evaluation)."""

    per_channel: list[SampleSet]
    footprint: np.ndarray  # H x W bool: pixels inside any sampled patch or pixel sample
    patch: int
    low: float
    high: float
    pixels: list[SampleSet] | None = None  # per channel: random single pixels (all values)

    def with_range(self, low: float, high: float) -> Sampling:
        """Same patches (and footprint), validity re-judged; only narrower ranges make sense."""
        if low < self.low or high > self.high:
            raise InputError(f"valid range ({low}, {high}) is wider than the sampling's "
                             f"({self.low}, {self.high}); resample instead")
        sets = [s.with_range(low, high) for s in self.per_channel]
        empty = [i for i, s in enumerate(sets) if len(s) == 0]
        if empty:
            raise InputError(f"channel(s) {empty} keep no sample valid in two exposures within "
                             f"({low}, {high})")
        return Sampling(sets, self.footprint, self.patch, low, high, self.pixels)

    def drop_exposure(self, index: int) -> Sampling:
        """The same samples without exposure ``index`` (leave-one-exposure-out)."""
        pix = None if self.pixels is None else [p.drop_exposure(index) for p in self.pixels]
        sets = [c.drop_exposure(index) for c in self.per_channel]
        # a fit of no samples fails inside the solver with a message about its arrays: name
        # what is missing instead (a small image's few patches, all valid in two exposures)
        empty = [i for i, c in enumerate(sets) if len(c) == 0]
        if empty or (pix is not None and any(len(c) == 0 for c in pix)):
            raise InputError(f"without exposure {index} (held out), channel(s) {empty or '*'} "
                             "keep no sample valid in two exposures: too few usable pixels "
                             "to fit and evaluate a response")
        return Sampling(sets, self.footprint, self.patch, self.low, self.high, pix)


def valid_mask(values: np.ndarray, low: float = VALID_LOW, high: float = VALID_HIGH):
    return (values > low) & (values < high)


def _box_mean(img: np.ndarray, patch: int) -> np.ndarray:
    import cv2

    if patch == 1:
        return img
    return cv2.blur(img, (patch, patch), borderType=cv2.BORDER_REFLECT)


def _box_min(img: np.ndarray, patch: int) -> np.ndarray:
    import cv2

    return img if patch == 1 else cv2.erode(img, np.ones((patch, patch), np.uint8),
                                            borderType=cv2.BORDER_REFLECT)


def _box_max(img: np.ndarray, patch: int) -> np.ndarray:
    import cv2

    return img if patch == 1 else cv2.dilate(img, np.ones((patch, patch), np.uint8),
                                             borderType=cv2.BORDER_REFLECT)


def _monotone(means: np.ndarray, ok: np.ndarray, order: np.ndarray, tol: float) -> np.ndarray:
    """True where the valid values never fall by more than ``tol`` as the exposure grows.

    ``means`` and ``ok``: (n, ...) over the exposures; walked in exposure ``order`` one
    exposure at a time, so the memory is one exposure's, not the stack's."""
    best = np.full(means.shape[1:], -np.inf, means.dtype)  # the largest valid value so far
    worst = np.zeros(means.shape[1:], means.dtype)  # the largest fall below it
    with np.errstate(invalid="ignore"):  # -inf - -inf where nothing is valid yet: not used
        for i in order:
            v = np.where(ok[i], means[i], -np.inf)
            np.fmax(best, v, out=best)
            np.fmax(worst, np.where(ok[i], best - v, 0.0), out=worst)
    return worst <= tol


def _normalised(channel: np.ndarray, full_scale: float) -> np.ndarray:
    """Codes of one channel as float32 in [0, 1], as ``ExposureSeries.values`` makes them."""
    return channel.astype(np.float32) / np.float32(full_scale)


def sample_series(series, n_samples: int = 1000, *, patch: int = 3, low: float = VALID_LOW,
                  high: float | None = None, seed: int = 0,
                  monotone_tolerance: float = MONOTONE_TOLERANCE,
                  n_pixels: int = N_PIXELS) -> Sampling:
    """Choose up to ``n_samples`` flat patches per channel, spread over the value range, and
    ``n_pixels`` random single pixels (see the module doc).  ``high``: default
    ``VALID_HIGH`` times the series' ``white_level``."""
    if high is None:
        high = VALID_HIGH * series.white_level
    if not isinstance(n_samples, (int, np.integer)) or n_samples < 8:
        raise InputError(f"n_samples must be an integer >= 8, got {n_samples!r}")
    if not isinstance(patch, (int, np.integer)) or patch < 1 or patch % 2 == 0:
        raise InputError(f"patch must be an odd positive integer, got {patch!r}")
    if not 0.0 <= low < high <= 1.0:
        raise InputError(f"valid range needs 0 <= low < high <= 1, got {low}, {high}")
    rng = np.random.default_rng(seed)
    tau_order = np.argsort(series.relative_exposures())
    # One channel of one image at a time: a stack of float copies of the whole series (and
    # its temporaries) took 15 times the images' own size, 3.3 GB for seven 10 MP JPEGs.
    images, fs = series.images, series.full_scale
    n, (h, w), channels = len(images), series.shape, series.channels
    r = patch // 2
    if h <= 2 * r or w <= 2 * r:
        raise InputError(f"images of {h} x {w} are too small for {patch} x {patch} patches")
    footprint = np.zeros((h, w), dtype=bool)
    # pixels that do not show one static scene (clblur.calibration.ghosts) are no samples
    moving = series.moving
    still_spoiled = _box_max(moving.astype(np.uint8), patch).astype(bool) if moving.any() \
        else moving
    # in a JPEG no patch reaches into a clipped region as the codec left it, whose ringing
    # pulls part of it below the clip (``ExposureSeries.coded_near_clip``; None: lossless)
    spoiled = [series.coded_near_clip(i, r) for i in range(n)]
    sets = []
    seen = falling = 0  # patches valid in two exposures, and those that darken on the way
    for c in range(channels):
        means = np.empty((n, h, w), np.float32)
        # a patch is valid only if every pixel in it is: one clipped pixel biases the mean
        # (its least and largest codes are kept as codes: a byte a pixel for 8-bit series)
        lowest = np.empty((n, h, w), series.dtype)
        highest = np.empty((n, h, w), series.dtype)
        ok = np.empty((n, h, w), bool)
        for i, image in enumerate(images):
            codes = np.ascontiguousarray(image[..., c])
            means[i] = _box_mean(_normalised(codes, fs), patch)
            lowest[i] = _box_min(codes, patch)
            highest[i] = _box_max(codes, patch)
            ok[i] = (_normalised(lowest[i], fs) > low) & (_normalised(highest[i], fs) < high)
            if spoiled[i] is not None:
                ok[i] &= ~spoiled[i]
        # flatness judged on the image with most valid pixels (best exposed overall)
        ref = int(np.argmax(ok.reshape(n, -1).sum(axis=1)))
        var = _box_mean(_normalised(images[ref][..., c], fs) ** 2, patch) - means[ref] ** 2
        std = np.sqrt(np.maximum(var, 0.0))
        usable = ok.sum(axis=0) >= 2
        usable[:r, :] = usable[h - r:, :] = False
        usable[:, :r] = usable[:, w - r:] = False
        usable &= ~still_spoiled  # a patch touching a pixel that moved
        valid = int(usable.sum())
        usable &= _monotone(means, ok, tau_order, monotone_tolerance)
        seen += valid
        falling += valid - int(usable.sum())
        rows, cols = _stratified_pick(means.mean(axis=0), std, usable, n_samples, rng)
        if rows.size == 0:
            continue
        v = means[:, rows, cols].T.astype(np.float64)
        sets.append(SampleSet(v, ok[:, rows, cols].T, np.full(rows.size, c), rows, cols,
                              _normalised(lowest[:, rows, cols].T, fs).astype(np.float64),
                              _normalised(highest[:, rows, cols].T, fs).astype(np.float64)))
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                footprint[rows + dy, cols + dx] = True
    if (not sets or sum(len(s) for s in sets) < 8) and falling > seen // 2:
        # most patches darken as the exposure grows: the times do not belong to the images.
        # The series check names the pair where it can judge one (calibrate runs it first)
        from clblur.calibration.series import check_brightening

        check_brightening(series.images, series.relative_exposures(), series.names,
                          series.white_level)
        raise InputError("no usable calibration samples: the images do not brighten with "
                         f"their exposure times ({falling} of {seen} patches valid in two "
                         "exposures get darker with a longer one); check the times (their "
                         "order, their units)")
    if not sets or sum(len(s) for s in sets) < 8:
        raise InputError("no usable calibration samples: every pixel is saturated (>= "
                         f"{high:g} of full scale) or under-exposed (<= {low:g}) in all but at "
                         "most one exposure")
    if len(sets) < channels:
        missing = sorted(set(range(channels)) - {int(s.channel[0]) for s in sets})
        raise InputError(f"channel(s) {missing} have no usable samples (saturated or "
                         "under-exposed everywhere)")
    pixels = _random_pixels(images, fs, footprint, n_pixels, rng, tau_order,
                            monotone_tolerance, moving, spoiled)
    return Sampling(sets, footprint, patch, low, high, pixels)


def _random_pixels(images: list[np.ndarray], full_scale: float, footprint: np.ndarray,
                   n_pixels: int, rng: np.random.Generator, tau_order: np.ndarray,
                   monotone_tolerance: float, moving: np.ndarray,
                   spoiled: list[np.ndarray | None] | None = None) -> list[SampleSet]:
    """``n_pixels`` random pixels outside ``footprint`` (then added to it) and ``moving``,
    every channel; a pixel whose value falls by more than ``monotone_tolerance`` while the
    exposure grows is invalid in that channel, as a patch would be rejected (corrupt or
    moving: no response curve predicts it, and in a least-squares fit a few such values
    bend the curve).  ``spoiled[i]``: H x W, the pixels invalid in image ``i`` besides
    (a JPEG's clipped region, ``ExposureSeries.coded_near_clip``), or None."""
    if not isinstance(n_pixels, (int, np.integer)) or n_pixels < 0:
        raise InputError(f"n_pixels must be a non-negative integer, got {n_pixels!r}")
    free = np.flatnonzero(~(footprint | moving).ravel())
    # at most half the free pixels: the other half is left for held-out scoring
    idx = np.sort(rng.choice(free, min(int(n_pixels), free.size // 2), replace=False))
    rows, cols = np.unravel_index(idx, footprint.shape)
    footprint[rows, cols] = True
    out = []
    for c in range(images[0].shape[2]):
        v = np.stack([_normalised(im[rows, cols, c], full_scale)
                      for im in images]).T.astype(np.float64)
        valid = (v > 0.0) & (v < 1.0)
        for i, mask in enumerate(spoiled or ()):
            if mask is not None:
                valid[:, i] &= ~mask[rows, cols]
        valid &= _monotone(v.T, valid.T, tau_order, monotone_tolerance)[:, None]
        out.append(SampleSet(v, valid, np.full(rows.size, c), rows, cols, v, v))
    return out


def _stratified_pick(level: np.ndarray, std: np.ndarray, usable: np.ndarray, n_samples: int,
                     rng: np.random.Generator, per_bin: int = 4):
    """Up to ``per_bin`` flattest usable pixels in each of ``n_samples/per_bin`` level bins."""
    idx = np.flatnonzero(usable.ravel())
    if idx.size == 0:
        return np.empty(0, int), np.empty(0, int)
    lev, sd = level.ravel()[idx], std.ravel()[idx]
    bins = max(1, n_samples // per_bin)
    edges = np.linspace(lev.min(), lev.max(), bins + 1)
    which = np.clip(np.searchsorted(edges, lev, side="right") - 1, 0, bins - 1)
    # random tie-break so equal-std pixels (e.g. a synthetic flat scene) spread over the image
    order = np.lexsort((rng.random(idx.size), sd, which))
    which_sorted = which[order]
    first = np.searchsorted(which_sorted, np.arange(bins))
    rank = np.arange(idx.size) - first[which_sorted]
    chosen = idx[order[rank < per_bin]]
    return np.unravel_index(chosen, level.shape)
