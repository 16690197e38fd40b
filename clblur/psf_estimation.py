"""The blur kernel of a sharp / blurred pair: non-blind PSF estimation in linear light.

A blur pair without a measured kernel (a beam-splitter rig's sharp and shaken frames, a
tripod shot and a hand-held one registered to it) still holds its kernel: with the sharp image
``x`` known, ``y = k * x`` is linear in ``k``.  :func:`fit_psf` solves it (:func:`estimate_psf`
returns the kernel alone).

Conventions
-----------
* The model is the paper's blur in linear light (Eq. 8): both images are linearised by a
  nominal response before the fit.  The kernel is the unknown here, not the response: a
  wrong nominal curve changes the weight of bright and dark edges but not where the light
  went, so the kernel's shape survives it (the study then tests the response with the
  kernel held).  Without a given response each of ``NOMINAL`` (linear light, sRGB) is
  tried and the kernel that predicts the pair best in code values is kept.  Pixels at full
  scale in either image hold no measurement of their light and are left out.
* The fit is on image gradients (horizontal and vertical differences, every channel): a
  kernel maps gradients as it maps light, and gradients are nearly white, so the normal
  equations are well conditioned (the standard choice of kernel estimation since Cho and
  Lee, "Fast motion deblurring", SIGGRAPH Asia 2009).  It is the constrained least-squares
  problem ``min |grad y - k * grad x|^2 + smoothness |k|^2`` with ``k >= 0``, solved by
  accelerated projected gradient (FISTA: Beck and Teboulle, SIAM J. Imaging Sci. 2, 2009)
  with every product of the normal matrix an FFT convolution of the kernel with the
  gradients' autocorrelation (the Toeplitz approximation: boundary terms are neglected, a
  fraction ``size / side`` of the sum).
* The kernel is returned as ``clblur.blur`` takes a PSF: float64, unit sum, odd sides, zero
  displacement at the centre pixel (``shape // 2``), in *convolution* orientation (the light
  of a sharp pixel lands at ``p + offset`` with weight ``k[centre + offset]``).  Its
  support is found by hysteresis (:func:`_support`): pieces of weights above ``FLOOR_LOW``
  of the largest, connected, that reach ``FLOOR`` of it; the rest is set to zero (the fit's
  noise: without the cut a large window adds a haze of small positive weights), and the
  window is trimmed to the support, kept centred.
* ``size`` (odd, px): the window searched.  Default: grown from 15 px, doubling while the
  kernel's support, or any weight of ``FLOOR`` of the largest, reaches the window's edge, up
  to a quarter of the images' shorter side.
  Pairs larger than ``MAX_FIT_PIXELS`` are fitted on their central window of that size.
  A kernel whose weights above ``FLOOR`` still reach the edge of the largest window is
  refused (the pair's blur is longer than the images allow to measure); fainter ones there
  are cut.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError

__all__ = ["FLOOR", "FLOOR_LOW", "MAX_FIT_PIXELS", "NOMINAL", "PSFFit", "SMOOTHNESS",
           "estimate_psf", "fit_psf", "kernel_agreement", "predict"]

# a piece of the kernel whose weights stay below FLOOR of the largest is the fit's noise;
# a piece above it keeps its weights down to FLOOR_LOW (hysteresis, _support)
FLOOR = 0.05
FLOOR_LOW = 0.02
SMOOTHNESS = 1e-3  # Tikhonov weight, relative to the gradients' energy per pixel
# pixels fitted at most: a larger pair is fitted on its central window (a space-invariant
# kernel is measured as well there, and the fit holds under 0.5 GB)
MAX_FIT_PIXELS = 2_000_000
# the nominal responses tried when none is given: the two ends of what files hold, raw
# linear light and display-encoded (sRGB) values
NOMINAL = ("linear", "srgb")
_ITERATIONS = 400
_FIRST_SIZE = 15
_FIRST_PAD = 63  # the correlations are first computed for windows up to this side
_MIN_SIDE = 32  # px: a pair smaller than this holds too few edges to fit a kernel


def _linear(image: np.ndarray, spec) -> tuple[np.ndarray, np.ndarray]:
    """Linear light (H x W x C float64) of an image's light channels (the alpha of grey +
    alpha and of RGBA is left out) and the pixels below full scale in all of them."""
    from clblur.pixels import imax
    from clblur.responses import per_channel

    a = np.asarray(image)
    if a.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise InputError(f"PSF estimation reads uint8, uint16 or float images, got {a.dtype}")
    if a.ndim not in (2, 3):
        raise InputError(f"PSF estimation reads H x W or H x W x C images, got {a.shape}")
    v = a.astype(np.float64) / imax(a.dtype)
    if v.ndim == 2:
        v = v[..., None]
    v = v[..., :1] if v.shape[2] == 2 else v[..., :3]  # grey + alpha, RGB + alpha
    if not np.isfinite(v).all():
        raise InputError("PSF estimation: the images contain NaN or infinite values")
    unclipped = (v < 1.0).all(axis=2)
    v = np.clip(v, 0.0, 1.0)
    curves = per_channel(spec, v.shape[2])
    return np.stack([c.inverse(v[..., i]) for i, c in enumerate(curves)], axis=2), unclipped


def _gradients(lin: np.ndarray, valid: np.ndarray) -> list[np.ndarray]:
    """Horizontal and vertical forward differences of every channel, zero wherever a
    difference touches an invalid pixel (and on the last row / column)."""
    out = []
    for axis in (0, 1):
        d = np.zeros_like(lin)
        ok = np.zeros(valid.shape, bool)
        if axis == 0:
            d[:-1] = lin[1:] - lin[:-1]
            ok[:-1] = valid[1:] & valid[:-1]
        else:
            d[:, :-1] = lin[:, 1:] - lin[:, :-1]
            ok[:, :-1] = valid[:, 1:] & valid[:, :-1]
        d[~ok] = 0.0
        out.extend(np.moveaxis(d, 2, 0))
    return out


def _correlations(gx: list[np.ndarray], gy: list[np.ndarray], r: int
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """The terms of the normal equations for kernels up to ``2r + 1`` px: the sharp
    gradients' autocorrelation at lags up to ``2r`` (4r+1 square, zero lag at the centre),
    the cross-correlation of the blurred gradients with the sharp ones at lags up to ``r``
    (2r+1 square), and an upper bound of the normal matrix's norm (the sum over the
    gradient images of their spectrum's largest power).  A smaller window's terms are the
    central parts of these (:func:`_window`)."""
    from scipy import fft

    h, w = gx[0].shape
    # zero padding: no wrap-around within the lags (to sizes the FFT factors fast)
    fh, fw = fft.next_fast_len(h + 4 * r + 1, True), fft.next_fast_len(w + 4 * r + 1, True)
    auto_spectrum = np.zeros((fh, fw // 2 + 1))
    cross_spectrum = np.zeros((fh, fw // 2 + 1), complex)
    bound = 0.0
    for a, b in zip(gx, gy, strict=True):
        fa = fft.rfft2(a, (fh, fw), workers=-1)
        power = fa.real ** 2 + fa.imag ** 2
        bound += float(power.max())
        auto_spectrum += power
        # cross[l] = sum_p b(p) a(p - l): where the light of a sharp gradient at p - l lands
        cross_spectrum += fft.rfft2(b, (fh, fw), workers=-1) * np.conj(fa)
    auto = fft.irfft2(auto_spectrum, (fh, fw), workers=-1)
    cross = fft.irfft2(cross_spectrum, (fh, fw), workers=-1)
    rows, cols = np.r_[fh - 2 * r:fh, 0:2 * r + 1], np.r_[fw - 2 * r:fw, 0:2 * r + 1]
    return (auto[np.ix_(rows, cols)], cross[np.ix_(rows[r:3 * r + 1], cols[r:3 * r + 1])],
            bound)


def _window(auto: np.ndarray, cross: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations' terms (:func:`_correlations`) for a ``2r + 1`` px window."""
    big, small = auto.shape[0] // 2, cross.shape[0] // 2
    return (auto[big - 2 * r:big + 2 * r + 1, big - 2 * r:big + 2 * r + 1],
            cross[small - r:small + r + 1, small - r:small + r + 1])


def _solve(auto: np.ndarray, rhs: np.ndarray, bound: float, smoothness: float) -> np.ndarray:
    """min 0.5 k'Qk - rhs'k + 0.5 lam |k|^2 over k >= 0 (FISTA), Q k = auto conv k."""
    from scipy.signal import fftconvolve

    n = rhs.shape[0]
    lam = smoothness * float(auto[auto.shape[0] // 2, auto.shape[1] // 2])
    step = 1.0 / (bound + lam)
    k = np.zeros_like(rhs)
    k[n // 2, n // 2] = 1.0
    z, t = k.copy(), 1.0
    for _ in range(_ITERATIONS):
        grad = fftconvolve(z, auto, mode="same") - rhs + lam * z
        k_next = np.maximum(z - step * grad, 0.0)
        t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
        z = k_next + ((t - 1.0) / t_next) * (k_next - k)
        k, t = k_next, t_next
    return k


def _support(k: np.ndarray, low: float = FLOOR_LOW) -> np.ndarray:
    """The kernel's support, by hysteresis: the 8-connected pieces of weights at or above
    ``low`` of the largest that hold a weight at or above ``FLOOR`` of it and at least
    ``FLOOR`` of the total weight so kept.  A path of light is connected, and its faint
    stretches (where the camera moved fast) join the bright ones; isolated specks are the
    fit's noise."""
    from scipy import ndimage

    top = k.max()
    pieces, n = ndimage.label(k >= low * top, np.ones((3, 3), bool))
    index = np.arange(1, n + 1)
    peak = ndimage.maximum(k, pieces, index)
    mass = np.where(peak >= FLOOR * top, ndimage.sum(k, pieces, index), 0.0)
    keep = index[mass >= FLOOR * mass.sum()]
    return np.isin(pieces, keep)


def _at_edge(support: np.ndarray) -> bool:
    return bool(support[0].any() or support[-1].any() or support[:, 0].any()
                or support[:, -1].any())


def _trim(k: np.ndarray) -> np.ndarray:
    """``k`` on its support (:func:`_support`), trimmed to it (kept centred), unit sum."""
    k = np.where(_support(k), k, 0.0)
    n = k.shape[0]
    c = n // 2
    rows, cols = np.nonzero(k)
    a = int(max(abs(rows - c).max(), 0))
    b = int(max(abs(cols - c).max(), 0))
    k = k[c - a:c + a + 1, c - b:c + b + 1]
    return k / k.sum()


@dataclass(frozen=True)
class PSFFit:
    """A measured kernel (``clblur.blur``'s PSF form, unit sum), the nominal response it was
    measured in, the exposure ``gain`` of the blurred image over the sharp one in that light
    (least squares on the light, where nothing clips: a blurred frame taken with a shorter
    shutter or another ISO), and how well the two predict the pair: RMSE in 8-bit codes
    of the blurred image predicted from the sharp one (:func:`predict` with the kernel times
    ``gain``) over the pixels fitted (inside the kernel's reach of the border, below full
    scale)."""

    kernel: np.ndarray
    response: object
    gain: float
    rmse: float


def predict(static: np.ndarray, kernel: np.ndarray, response="srgb") -> np.ndarray:
    """The blurred image's normalised values (H x W x C float64, light channels) that
    ``kernel`` makes of ``static`` in the linear light of ``response``: the paper's Eq. 8
    with a PSF, as ``clblur.blur`` computes it (without its rounding)."""
    from scipy.signal import fftconvolve

    from clblur.responses import per_channel

    lin, _ = _linear(np.asarray(static), response)
    curves = per_channel(response, lin.shape[2])
    return np.stack([curves[c].forward(np.clip(fftconvolve(lin[..., c], kernel, mode="same"),
                                                0.0, None))
                     for c in range(lin.shape[2])], axis=2)


def fit_psf(static: np.ndarray, blurred: np.ndarray, size: int | None = None, *,
            response=None, smoothness: float = SMOOTHNESS) -> PSFFit:
    """The blur kernel that takes ``static`` to ``blurred`` (module Conventions).

    Args:
        static: the sharp image, H x W or H x W x C (uint8, uint16 or float in [0, 1]).
        blurred: the blurred image, registered to ``static``: same shape.
        size: odd side of the window searched (px); None grows it (Conventions).
        response: the nominal response that linearises both images (a spec as
            ``clblur.blur`` takes it: a name, a calibrated JSON, per-channel curves);
            None tries each of ``NOMINAL`` and keeps the kernel that predicts the pair best.
        smoothness: Tikhonov weight relative to the gradients' energy.

    Returns:
        :class:`PSFFit`: the kernel (float64, unit sum, odd sides, centred), the response
        it was measured in, the exposure gain, and the RMSE of the two on the pair.

    Raises:
        InputError: images of different shapes, too small, without edges, or a kernel
            that reaches the edge of the largest window.
    """
    static, blurred = np.asarray(static), np.asarray(blurred)
    if static.shape != blurred.shape:
        raise InputError(f"PSF estimation: sharp {static.shape} and blurred {blurred.shape} "
                         "images differ in shape")
    static, blurred = _central(static), _central(blurred)
    side = min(static.shape[:2])
    if side < _MIN_SIDE:
        raise InputError(f"PSF estimation needs images at least {_MIN_SIDE} px on a side, got "
                         f"{static.shape[:2]}")
    largest = max(_FIRST_SIZE, (side // 4) | 1)
    if size is not None:
        if int(size) != size or size < 3 or size % 2 == 0:
            raise InputError(f"PSF size must be an odd integer >= 3, got {size!r}")
        if size > largest:
            raise InputError(f"PSF size {size} is more than a quarter of the images' shorter "
                             f"side ({side} px)")
    fits = [_fit_in(static, blurred, size, largest, spec, smoothness)
            for spec in (NOMINAL if response is None else (response,))]
    return min(fits, key=lambda f: f.rmse)


def _central(image: np.ndarray) -> np.ndarray:
    """The central window of at most ``MAX_FIT_PIXELS`` of an image, of its aspect."""
    h, w = image.shape[:2]
    if h * w <= MAX_FIT_PIXELS:
        return image
    f = (MAX_FIT_PIXELS / (h * w)) ** 0.5
    ch, cw = int(h * f), int(w * f)
    return image[(h - ch) // 2:(h - ch) // 2 + ch, (w - cw) // 2:(w - cw) // 2 + cw]


def estimate_psf(static: np.ndarray, blurred: np.ndarray, size: int | None = None, *,
                 response=None, smoothness: float = SMOOTHNESS) -> np.ndarray:
    """The kernel of :func:`fit_psf` (same arguments): float64, unit sum, odd sides, zero
    displacement at the centre pixel, the orientation ``clblur.blur`` takes."""
    return fit_psf(static, blurred, size, response=response, smoothness=smoothness).kernel


def _fit_in(static: np.ndarray, blurred: np.ndarray, size: int | None, largest: int,
            spec, smoothness: float) -> PSFFit:
    """:func:`fit_psf` in the linear light of one response ``spec``."""
    x, x_ok = _linear(static, spec)
    y, y_ok = _linear(blurred, spec)
    valid = x_ok & y_ok
    gx, gy = _gradients(x, valid), _gradients(y, valid)
    if not any(float(np.abs(g).max()) > 0 for g in gx):
        raise InputError("PSF estimation: the sharp image has no edges below full scale")
    side = min(static.shape[:2])
    n = size if size is not None else _FIRST_SIZE
    pad = -1  # the largest window the correlations hold (half side)
    while True:
        if n // 2 > pad:  # the first ones serve windows up to _FIRST_PAD (the common case)
            pad = max(n // 2, min(largest, _FIRST_PAD) // 2)
            auto_all, cross_all, bound = _correlations(gx, gy, pad)
        auto, rhs = _window(auto_all, cross_all, n // 2)
        k = _solve(auto, rhs, bound, smoothness)
        if k.max() <= 0:
            raise InputError("PSF estimation: no kernel maps the sharp image's edges onto the "
                             "blurred image's (are the two images of one scene, registered?)")
        # grown while the support reaches the window's edge, or any weight of FLOOR or more
        # lies on it: a path that leaves the window leaves a cut-off piece at the border
        # that hysteresis drops as a speck (Levin's kernel 6 came out 13 x 11 px of its
        # 25 x 21, predicting its pairs to 5 - 6 codes instead of 1)
        if not (_at_edge(_support(k)) or _at_edge(k >= FLOOR * k.max())):
            break
        if size is None and n >= largest and not _at_edge(_support(k, FLOOR)):
            break  # only faint weights reach the largest window's edge: cut there
        if size is not None or n >= largest:
            raise InputError(f"PSF estimation: the kernel reaches the edge of the {n} px "
                             "window" + ("; pass a larger size" if size is not None and
                                         n < largest else
                                         f" (at most a quarter of the images' {side} px)"))
        n = min(2 * n + 1, largest)
    kernel = _trim(k)
    # the gain and the prediction's error where the whole kernel lies inside the image and
    # nothing clips.  The gain is fitted to the light itself: gradients hardly constrain a
    # kernel's sum (their spectrum vanishes at zero frequency), so the regularised fit's
    # sum is biased low.
    from scipy.signal import fftconvolve

    from clblur.pixels import imax

    reach = max(kernel.shape) // 2
    inner = np.zeros(valid.shape, bool)
    inner[reach:valid.shape[0] - reach, reach:valid.shape[1] - reach] = True
    inner &= valid
    blurred_light = np.stack([fftconvolve(x[..., c], kernel, mode="same")
                              for c in range(x.shape[2])], axis=2)[inner]
    power = float((blurred_light * blurred_light).sum())
    gain = float((blurred_light * y[inner]).sum()) / power if power > 0 else 1.0
    target = blurred.astype(np.float64) / imax(blurred.dtype)
    target = target[..., None] if target.ndim == 2 else target
    target = target[..., :1] if target.shape[2] == 2 else target[..., :3]
    d = (predict(static, kernel * gain, spec) - target)[inner] * 255.0
    rmse = float(np.sqrt(np.mean(d * d))) if d.size else float("inf")
    return PSFFit(kernel, spec, gain, rmse)


def kernel_agreement(a: np.ndarray, b: np.ndarray, search: int = 4) -> float:
    """Normalised correlation of two kernels at their best relative whole-pixel shift
    (within ``search`` px): 1 for the same kernel anywhere in the window, about 0 for
    unrelated ones (kernels are non-negative, so never far below)."""
    n0 = max(a.shape[0], b.shape[0]) + 2 * search
    n1 = max(a.shape[1], b.shape[1]) + 2 * search

    def placed(k):
        out = np.zeros((n0, n1))
        r0, c0 = (n0 - k.shape[0]) // 2, (n1 - k.shape[1]) // 2
        out[r0:r0 + k.shape[0], c0:c0 + k.shape[1]] = k
        return out / np.sqrt((k * k).sum())

    pa, pb = placed(np.asarray(a, float)), placed(np.asarray(b, float))
    return max(float((pa * np.roll(pb, (dy, dx), (0, 1))).sum())
               for dy in range(-search, search + 1) for dx in range(-search, search + 1))
