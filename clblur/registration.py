"""Registration of an exposure series: the translation between hand-held exposures.

Why: calibration and the study compare the same pixel across exposures.  A bracket shot by
hand (or on a tripod nudged by the mirror or the photographer) moves by pixels to tens of
pixels between frames, and then every comparison mixes two scene points: on the Canon 400D
bracket shrunk to 1/4, shifts of up to 6 px raised the fitted Eq. 3 rate ``k`` by 17 to 23 %
and quadrupled the held-out error (``docs/studies/memorial-calibration.md``, hand-held
brackets; ``bench/bench_registration.py``).

Conventions
-----------
* The motion between exposures is a whole-pixel translation (the hand-held case of Ward,
  "Fast, robust image registration for compositing high dynamic range photographs from
  hand-held exposures", JGT 8(2), 2003).  Rotation and parallax are not modelled; a residual
  below a pixel is what the study's ``misregistration`` effect measures.  Whole pixels keep
  the codes as stored (resampling would blend them).
* Criterion: the normalised cross-correlation of the two images' codes over the pixels
  neither clips (codes strictly inside ``(_LOW, _HIGH)`` of full scale in each image; masked
  NCC, Padfield, "Masked object registration in the Fourier domain", IEEE TIP 21(5), 2012).
  A response is monotone, so at the right shift the codes of the two exposures rise
  together; a region where one image is dark and flat (a pedestal and its noise, as in
  Memorial's shortest frames) has little variance and so little say, where the median
  threshold bitmaps of Ward's method turn its noise into structure.
* Search: all shifts up to a quarter of the side at the pyramid level whose longer side is
  at most ``_SEARCH_SIDE`` px (by FFT, every shift at once), then a 3 x 3 step at each finer
  level around the doubled shift.  A link whose best correlation is below ``MIN_NCC``, or
  whose compared pixels are fewer than ``MIN_PIXELS``, is not trusted: its shift is taken as
  zero and reported (``Registration.unregistered``).  Of shifts whose correlations lie
  within ``TIE_NCC`` of the best, the shortest is taken (a ramp or a stripe cannot say how
  far it moved along itself).
* The middle channel is compared (green in RGB and BGR).  Neighbours in exposure are
  registered to each other (they share the most unclipped pixels) and the shifts chained to
  the middle exposure.
* The aligned series is every image cropped to the window all of them cover (views, no
  copy); with no shift the images are returned as they are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clblur.pixels import imax

__all__ = ["MIN_NCC", "MIN_PIXELS", "TIE_NCC", "Registration", "align_series", "describe",
           "pair_shift", "summary"]

MIN_NCC = 0.3  # least correlation of a trusted link
MIN_PIXELS = 256  # least compared pixels (at the search level) of a trusted link
TIE_NCC = 1e-3  # correlations this close cannot choose between shifts
_LOW, _HIGH = 0.02, 0.98  # clipped: at or beyond these fractions of full scale
_SEARCH_SIDE = 512  # px: the longer side of the level searched whole


@dataclass(frozen=True)
class Registration:
    """Where each image of a series lies against the middle exposure, and the common window.

    ``shifts``: n x 2 int, (rows, cols): the scene point at ``(y, x)`` of the reference is at
    ``(y + dy, x + dx)`` of image ``i``; ``window``: (row slice, col slice) of the reference
    covered by every image; ``reference``: the index of the middle exposure;
    ``unregistered``: indices of the images whose link to their longer neighbour could not be
    trusted (module Conventions; taken as zero)."""

    shifts: np.ndarray
    window: tuple[slice, slice]
    reference: int = 0
    unregistered: tuple[int, ...] = ()

    @property
    def moved(self) -> bool:
        return bool(np.any(self.shifts))

    def crop(self, image: np.ndarray, index: int) -> np.ndarray:
        """Image ``index`` cut to the common window (a view)."""
        (dy, dx), (rows, cols) = self.shifts[index], self.window
        return image[rows.start + dy:rows.stop + dy, cols.start + dx:cols.stop + dx]


def _plane(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The compared channel, float32 in [0, 1] of full scale, and its unclipped mask."""
    im = image if image.ndim == 2 else image[..., min(image.shape[2], 3) // 2]
    g = im.astype(np.float32) / np.float32(imax(image.dtype))
    return g, (g > _LOW) & (g < _HIGH)


def _half(g: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The next pyramid level: 2 x 2 means, a pixel compared when all four were."""
    import cv2

    size = (g.shape[1] // 2, g.shape[0] // 2)
    return (cv2.resize(g, size, interpolation=cv2.INTER_AREA),
            cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999)


def _moments(a, ma, b, mb) -> np.ndarray:
    """Masked NCC and pixel count of ``a`` against ``b`` read at the same pixels (same
    shape), as an array (ncc, n)."""
    m = ma & mb
    n = int(np.count_nonzero(m))
    if n < 2:
        return np.array([-np.inf, n])
    x, y = a[m].astype(np.float64), b[m].astype(np.float64)
    x -= x.mean()
    y -= y.mean()
    den = np.sqrt(np.dot(x, x) * np.dot(y, y))
    return np.array([np.dot(x, y) / den if den > 0 else -np.inf, n])


def _overlap(shape, dy: int, dx: int):
    h, w = shape
    return ((slice(max(0, -dy), min(h, h - dy)), slice(max(0, -dx), min(w, w - dx))),
            (slice(max(0, dy), min(h, h + dy)), slice(max(0, dx), min(w, w + dx))))


def _at_shift(a, ma, b, mb, dy: int, dx: int) -> np.ndarray:
    (ya, xa), (yb, xb) = _overlap(a.shape, dy, dx)
    return _moments(a[ya, xa], ma[ya, xa], b[yb, xb], mb[yb, xb])


def _all_shifts(a, ma, b, mb, span: int) -> tuple[np.ndarray, np.ndarray]:
    """Masked NCC and counts of ``b`` read at ``(y + dy, x + dx)`` against ``a`` for every
    ``|dy|, |dx| <= span`` ((2 span + 1)^2 arrays, index ``span + d``), by FFT (Padfield)."""
    h, w = a.shape
    fh, fw = h + span, w + span  # no wrap-around within the span

    def spec(f):
        return np.fft.rfft2(f, (fh, fw))

    def corr(fa, fb):  # sum_y f(y) g(y + d) for every d
        c = np.fft.irfft2(np.conj(fa) * fb, (fh, fw))
        idx_y = np.arange(-span, span + 1) % fh
        idx_x = np.arange(-span, span + 1) % fw
        return c[np.ix_(idx_y, idx_x)]

    ma, mb = ma.astype(np.float64), mb.astype(np.float64)
    a, b = a.astype(np.float64) * ma, b.astype(np.float64) * mb
    fma, fmb, fa, fb = spec(ma), spec(mb), spec(a), spec(b)
    n = np.rint(corr(fma, fmb))
    sa, sb = corr(fa, fmb), corr(fma, fb)
    saa, sbb = corr(spec(a * a), fmb), corr(fma, spec(b * b))
    sab = corr(fa, fb)
    safe = np.maximum(n, 1)
    cov = sab - sa * sb / safe
    var = np.maximum(saa - sa * sa / safe, 0) * np.maximum(sbb - sb * sb / safe, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = np.where((n >= 2) & (var > 0), cov / np.sqrt(var), -np.inf)
    return ncc, n


def _least_move(ncc: np.ndarray, dy: np.ndarray, dx: np.ndarray) -> tuple[int, int]:
    """The shift of the smallest length whose correlation is within ``TIE_NCC`` of the best:
    where the scene cannot tell shifts apart (a ramp, a stripe: the aperture problem), no
    move is made up."""
    near = ncc >= ncc.max() - TIE_NCC
    length = np.where(near, np.abs(dy) + np.abs(dx), np.iinfo(np.int64).max)
    i = np.unravel_index(np.argmin(length), length.shape)
    return int(dy[i]), int(dx[i])


def pair_shift(longer: np.ndarray, shorter: np.ndarray) -> tuple[tuple[int, int], float] | None:
    """The whole-pixel shift ``(dy, dx)`` at which ``shorter`` shows what ``longer`` shows at
    ``(y, x)``: ``shorter[y + dy, x + dx]``, with its correlation (module Conventions); None
    when the link cannot be trusted."""
    a, ma = _plane(longer)
    b, mb = _plane(shorter)
    if a.shape != b.shape:
        raise ValueError(f"images differ in size: {a.shape} and {b.shape}")
    levels = [(a, ma, b, mb)]
    while max(levels[-1][0].shape) > _SEARCH_SIDE and min(levels[-1][0].shape) >= 32:
        la, lma, lb, lmb = levels[-1]
        levels.append((*_half(la, lma), *_half(lb, lmb)))
    top = levels[-1]
    span = max(1, min(top[0].shape) // 4)
    ncc, n = _all_shifts(*top, span)
    # a shift must compare at least a quarter of the pixels the zero shift does
    ncc = np.where(n >= max(MIN_PIXELS, 0.25 * n[span, span]), ncc, -np.inf)
    if not ncc.max() >= MIN_NCC:
        return None
    dy, dx = _least_move(ncc, *np.mgrid[-span:span + 1, -span:span + 1])
    score = float(ncc[dy + span, dx + span])
    for level in reversed(levels[:-1]):
        dy, dx = 2 * dy, 2 * dx
        ys, xs = np.mgrid[dy - 1:dy + 2, dx - 1:dx + 2]
        trials = np.array([_at_shift(*level, y, x)[0] for y, x in zip(ys.ravel(), xs.ravel(),
                                                                      strict=True)])
        dy, dx = _least_move(trials.reshape(3, 3), ys, xs)
        score = float(trials.max())
    return (dy, dx), float(score)


def align_series(images: list[np.ndarray], exposures) -> Registration:
    """Register the images of an exposure series (``exposures``: their relative exposures,
    any consistent unit) to the middle exposure (module Conventions).

    Returns a :class:`Registration`; crop each image with ``Registration.crop``."""
    n = len(images)
    order = np.argsort(np.asarray(exposures, np.float64))[::-1]  # longest first
    step = np.zeros((n, 2), np.int64)  # shift of order[k] against order[k - 1]
    unregistered = []
    for k in range(1, n):
        found = pair_shift(images[order[k - 1]], images[order[k]])
        if found is None:
            unregistered.append(int(order[k]))
        else:
            step[k] = found[0]
    chained = np.cumsum(step, axis=0)
    chained -= chained[n // 2]  # against the middle exposure
    shifts = np.zeros((n, 2), np.int64)
    shifts[order] = chained
    h, w = images[0].shape[:2]
    lo = np.maximum(-shifts.min(axis=0), 0)
    hi = np.array([h, w]) - np.maximum(shifts.max(axis=0), 0)
    if shifts.any() and np.any(hi - lo < min(16, h, w)):
        raise ValueError(f"exposure series: the images overlap by less than 16 px after "
                         f"registration (shifts {shifts.tolist()}); are they of one scene?")
    window = (slice(int(lo[0]), int(hi[0])), slice(int(lo[1]), int(hi[1])))
    return Registration(shifts, window, int(order[n // 2]), tuple(sorted(unregistered)))


def describe(registration: Registration, names: list[str]) -> dict:
    """The registration as a report records it: each image's shift (rows, cols) against the
    reference, the common window the images were cropped to, the links not trusted and
    :func:`summary`'s line."""
    zero = [n for n, s in zip(names, registration.shifts, strict=True) if not s.any()]
    rows, cols = registration.window
    return {"reference": names[registration.reference],
            "shifts": {n: [int(v) for v in s]
                       for n, s in zip(names, registration.shifts, strict=True)},
            "unshifted": zero,
            "window": {"rows": [rows.start, rows.stop], "cols": [cols.start, cols.stop]},
            "unregistered": [names[i] for i in registration.unregistered],
            "summary": summary(registration, names)}


def summary(registration: Registration, names: list[str]) -> str:
    """One line for a terminal or a report: what moved, the window kept, what could not be
    registered."""
    moved = [f"{n} ({int(s[0])}, {int(s[1])})"
             for n, s in zip(names, registration.shifts, strict=True) if s.any()]
    rows, cols = registration.window
    found = (f"{', '.join(moved)} px (rows, cols) against "
             f"{names[registration.reference]}")
    if not moved:
        text = "registered: no shift between the images"
    else:
        text = (f"registered: {found}; cropped to {cols.stop - cols.start} x "
                f"{rows.stop - rows.start} (W x H)")
    if registration.unregistered:
        text += ("; not registered (too little unclipped overlap with the next longer "
                 f"exposure, taken as unshifted): "
                 f"{', '.join(names[i] for i in registration.unregistered)}")
    return text
