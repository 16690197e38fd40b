"""A virtual camera: renders "measurements" of a radiance map with exact, documented physics.

It is the ground truth of the study's tests: every effect the study looks for can be switched
on here at a known magnitude.

Conventions
-----------
* ``radiance`` is an H x W x C (or H x W) float array of scene radiance, >= 0, arbitrary units.
* Linear sensor exposure ``y = radiance * exposure * gain * channel_gain_c * V(p)``; ``y = 1``
  is the full well when ``full_well`` is finite (units of the full well).
* Motion blur is integrated in the linear domain through ``clblur.blur`` with the *linear*
  response (so it runs the project's own kernels, numpy or OpenCL): the blurred exposure at
  pixel ``p`` is the time average of the scene exposure along the motion, with optional time
  weights (non-uniform velocity) and the anchor convention of ``clblur.motion``.
* Vignetting is fixed to the sensor: ``V(p) = cos^4(atan(r / f)) = (1 + c (r/R)^2)^-2``
  (the paper's Eq. 1 falloff) with ``r`` the distance from the image centre, ``R`` the
  half-diagonal and ``c = (R / f)^2``.  The scene moves, the falloff does not, so the blurred
  exposure is ``V(p) * mean(L along the path)``.
* Full-well clipping acts on the accumulated exposure of each pixel: ``y <- min(y, 1)``.
* Noise (Foi et al. 2008): ``y_noisy = a * Poisson(y / a) + N(0, b)`` (variance ``a y + b``),
  added in the linear domain before clipping and the response; pixels at or above the full
  well are clipped and carry no noise.
* The response (one, or one per channel) maps ``y`` to a normalised value; a black level
  ``beta`` (one, or one per channel) lifts it: ``v = beta + (1 - beta) * I(y)``; then
  ``clblur.pixels.quantise`` (round half to even), or, with ``storage="floor"``,
  truncation ``floor(v * full)`` (a -0.5 code bias), and with ``code_offset`` a constant
  offset of that many codes added before quantising.
* ``shift=(sx, sy)`` (``capture``): the sensor image is displaced by a sub-pixel amount after
  the blur, ``y(p) <- y(p - s)`` (bilinear, edge clamped), i.e. a misregistration between
  this capture and another.
* Deterministic: all randomness comes from the ``rng`` passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clblur.blur import blur
from clblur.errors import InputError, InputTypeError
from clblur.pixels import quantise
from clblur.responses import Exp, Response, response

__all__ = ["Camera", "accelerating_weights", "local_tone", "normalised_radius2", "random_scene",
           "shift_image", "vignette"]


@dataclass(frozen=True)
class Camera:
    """Sensor and processing of one camera (see the module docstring for the physics)."""

    response: Response | str | tuple[Response | str, ...] = Exp(3.0)  # or one per channel
    black_level: float | tuple[float, ...] = 0.0  # normalised value of zero exposure
    noise_a: float = 0.0  # Poisson part of the variance, full-well units
    noise_b: float = 0.0  # Gaussian part of the variance, full-well units squared
    full_well: bool = False  # clip the linear exposure at 1
    vignetting: float = 0.0  # c = (half-diagonal / focal length)^2; 0 = none
    channel_gains: tuple[float, ...] | None = None  # white-balance gains before the response
    storage: str = "round"  # integer outputs: "round" (half to even) or "floor" (truncation)
    code_offset: float = 0.0  # codes added before quantising (a storage bias)

    def __post_init__(self):
        object.__setattr__(self, "response",
                           tuple(map(response, self.response))
                           if isinstance(self.response, (tuple, list))
                           else response(self.response))
        if self.storage not in ("round", "floor"):
            raise InputError(f"storage must be 'round' or 'floor', got {self.storage!r}")
        if not (math.isfinite(self.code_offset) and abs(self.code_offset) <= 8):
            raise InputError(f"code_offset must be within +-8 codes, got {self.code_offset}")
        levels = np.atleast_1d(np.asarray(self.black_level, dtype=np.float64))
        if levels.ndim != 1 or not np.all((levels >= 0.0) & (levels < 1.0)):
            raise InputError(f"black_level must be in [0, 1) (one, or one per channel), "
                             f"got {self.black_level}")
        for name in ("noise_a", "noise_b", "vignetting"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {v}")
        if self.channel_gains is not None and any(g <= 0 for g in self.channel_gains):
            raise InputError(f"channel_gains must be positive, got {self.channel_gains}")

    def capture(self, radiance: np.ndarray, exposure: float = 1.0, *, motion=None,
                weights=None, anchor: str = "center", gain: float = 1.0,
                channel_gains: tuple[float, ...] | None = None,
                rng: np.random.Generator | None = None, dtype=np.uint8,
                backend: str = "numpy", shift: tuple[float, float] | None = None,
                optical_variance: float = 0.0) -> np.ndarray:
        """Render one capture of ``radiance``.

        ``motion``/``weights``/``anchor`` as in ``clblur.blur`` (None: a static capture).
        ``gain`` and ``channel_gains`` multiply the exposure of this capture only (they model
        a gain or white-balance mismatch between two captures); ``channel_gains`` here
        overrides the camera's.  ``rng`` is required when the camera has noise.
        ``shift``: the image moved by (sx, sy) px (bilinear); ``optical_variance``: a
        Gaussian blur of that variance (px^2 per axis) of the light after the motion (a
        defocused or softer lens, for this capture only).
        """
        rad = _check_radiance(radiance)
        if not (math.isfinite(exposure) and exposure > 0 and math.isfinite(gain) and gain > 0):
            raise InputError(f"exposure and gain must be positive, got {exposure}, {gain}")
        if not (math.isfinite(optical_variance) and optical_variance >= 0):
            raise InputError(f"optical_variance must be >= 0, got {optical_variance}")
        y = rad * (exposure * gain)
        gains = channel_gains if channel_gains is not None else self.channel_gains
        if gains is not None:
            if len(gains) != y.shape[2]:
                raise InputError(f"{len(gains)} channel gains for {y.shape[2]} channel(s)")
            y = y * np.asarray(gains, dtype=np.float64)
        if motion is not None:
            y = blur(y, motion, "linear", anchor=anchor, weights=weights, backend=backend)
        if optical_variance > 0:
            from scipy.ndimage import gaussian_filter

            sd = math.sqrt(optical_variance)
            y = gaussian_filter(y, sigma=(sd, sd, 0.0), mode="nearest")
        if shift is not None:
            y = shift_image(y, float(shift[0]), float(shift[1]))
        y = y * vignette(y.shape[:2], self.vignetting)[..., None]
        clipped = y >= 1.0 if self.full_well else np.zeros(y.shape, bool)
        if self.noise_a > 0 or self.noise_b > 0:
            if rng is None:
                raise InputError("a noisy camera needs rng (a numpy Generator)")
            y = np.where(clipped, y, _poisson_gaussian(y, self.noise_a, self.noise_b, rng))
        if self.full_well:
            y = np.minimum(y, 1.0)
        y = np.maximum(y, 0.0)
        if isinstance(self.response, tuple):
            if len(self.response) != y.shape[2]:
                raise InputError(f"{len(self.response)} responses for {y.shape[2]} channel(s)")
            v = np.stack([r.forward(y[..., c]) for c, r in enumerate(self.response)], axis=-1)
        else:
            v = self.response.forward(y)
        beta = np.asarray(self.black_level, dtype=np.float64)
        if beta.ndim and beta.size != v.shape[2]:
            raise InputError(f"{beta.size} black levels for {v.shape[2]} channel(s)")
        v = beta + (1.0 - beta) * v
        out = self._store(v, dtype)
        return out[..., 0] if np.ndim(radiance) == 2 else out

    def _store(self, v: np.ndarray, dtype) -> np.ndarray:
        """Normalised values -> stored values (rounding or truncation, plus the offset)."""
        dtype = np.dtype(dtype)
        if dtype.kind == "f" or (self.storage == "round" and self.code_offset == 0.0):
            return quantise(v, dtype)
        full = float(np.iinfo(dtype).max)
        x = np.clip(v, 0.0, 1.0) * full + self.code_offset
        x = np.floor(x) if self.storage == "floor" else np.rint(x)
        return np.clip(x, 0.0, full).astype(dtype)


def shift_image(y: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``out(p) = y(p - s)`` with bilinear interpolation and clamp to edge (H x W x C)."""
    h, w = y.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x = np.clip(xx - sx, 0.0, w - 1.0)
    r = np.clip(yy - sy, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 1)
    y0 = np.minimum(np.floor(r).astype(np.intp), h - 1)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[..., None], (r - y0)[..., None]
    return ((1 - fy) * ((1 - fx) * y[y0, x0] + fx * y[y0, x1])
            + fy * ((1 - fx) * y[y1, x0] + fx * y[y1, x1]))


def _check_radiance(radiance) -> np.ndarray:
    if not isinstance(radiance, np.ndarray) or radiance.ndim not in (2, 3):
        raise InputTypeError("radiance must be an H x W or H x W x C numpy array")
    rad = np.asarray(radiance, dtype=np.float64)
    if not np.isfinite(rad).all() or (rad < 0).any():
        raise InputError("radiance must be finite and >= 0")
    return rad if rad.ndim == 3 else rad[..., None]


def _poisson_gaussian(y: np.ndarray, a: float, b: float, rng: np.random.Generator):
    out = y.copy()
    if a > 0:
        out = a * rng.poisson(np.maximum(y, 0.0) / a)
    if b > 0:
        out = out + rng.normal(0.0, math.sqrt(b), size=y.shape)
    return out


def local_tone(light: np.ndarray, strength: float, sigma: float,
               mid: float = 0.18) -> np.ndarray:
    """Local tone mapping of one capture's light (H x W x C, the exposure already applied):
    each pixel's light times ``exp(strength tanh(ln(mid) - L))``, ``L`` the log of the
    light's mean over the channels, Gaussian-blurred by ``sigma`` px.  A region darker than
    ``mid`` is lifted, one brighter held down (by up to ``exp(strength)``), as a camera's
    shadow and highlight correction (Canon's Auto Lighting Optimizer, Nikon's Active
    D-Lighting) and a phone's HDR rendering do: one light gets two codes in two surrounds,
    which no response curve holds (``clblur.study.leftover``'s alternative by surround).
    Not a vocabulary effect: a cause the study must report as structure left."""
    from scipy.ndimage import gaussian_filter

    x = _check_radiance(light)
    if not (math.isfinite(strength) and math.isfinite(sigma) and sigma >= 0 and mid > 0):
        raise InputError(f"local_tone needs a finite strength, sigma >= 0 and mid > 0, got "
                         f"{strength}, {sigma}, {mid}")
    level = np.log(np.maximum(x.mean(axis=2), 1e-12))
    surround = gaussian_filter(level, sigma) if sigma > 0 else level
    return x * np.exp(strength * np.tanh(np.log(mid) - surround))[..., None]


def vignette(shape: tuple[int, int], c: float) -> np.ndarray:
    """``V(p) = (1 + c (r/R)^2)^-2``: cos^4 falloff, ``R`` the half-diagonal (H x W)."""
    return 1.0 / (1.0 + c * normalised_radius2(shape)) ** 2


def normalised_radius2(shape: tuple[int, int]) -> np.ndarray:
    """``(r / R)^2`` from the image centre, ``R`` the half-diagonal (1 in the corners)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    cy, cx = (h - 1) / 2.0, (w - 1) / 2.0
    return ((yy - cy) ** 2 + (xx - cx) ** 2) / max(cy * cy + cx * cx, 1e-12)


def accelerating_weights(n: int, speed_ratio: float) -> np.ndarray:
    """Time weights for ``n`` equally spaced positions of a constantly accelerating motion.

    The speed goes from ``v0`` to ``v1 = speed_ratio * v0`` (ratio < 1: decelerating); the
    time spent near position ``s`` is ``1 / speed(s)`` with ``speed(s)^2 = v0^2 +
    (v1^2 - v0^2) s``.
    """
    if n < 2 or not (math.isfinite(speed_ratio) and speed_ratio > 0):
        raise InputError(f"need n >= 2 and a positive speed ratio, got {n}, {speed_ratio}")
    s = np.linspace(0.0, 1.0, n)
    w = 1.0 / np.sqrt(1.0 + (speed_ratio ** 2 - 1.0) * s)
    return w / w.sum()


def random_scene(rng: np.random.Generator, shape: tuple[int, int] = (48, 64),
                 channels: int = 3, low: float = 0.03, high: float = 1.0,
                 highlights: int = 0, highlight_gain: float = 4.0) -> np.ndarray:
    """A procedural radiance map (H x W x C float64): a smooth gradient, random rectangles
    and discs with sharp edges, fine texture; values in [low, high].  ``highlights`` adds
    small discs ``highlight_gain`` times brighter than ``high`` (specular highlights that
    clip in a capture)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = rng.uniform(0.2, 0.5) + 0.3 * (xx / w - 0.5) * rng.uniform(-1, 1) \
        + 0.3 * (yy / h - 0.5) * rng.uniform(-1, 1)
    img = np.repeat(base[..., None], channels, axis=2)
    for _ in range(int(rng.integers(6, 11))):
        level = rng.uniform(0.0, 1.0, size=channels)
        y0, x0 = rng.uniform(0, h), rng.uniform(0, w)
        ry, rx = rng.uniform(2, max(3, h / 3)), rng.uniform(2, max(3, w / 3))
        if rng.random() < 0.5:
            mask = (np.abs(yy - y0) < ry) & (np.abs(xx - x0) < rx)
        else:
            mask = ((yy - y0) / ry) ** 2 + ((xx - x0) / rx) ** 2 < 1
        img[mask] = level
    fx, fy = rng.uniform(0.2, 0.9, size=2)
    img += 0.08 * np.sin(fx * xx + rng.uniform(0, 6))[..., None] * np.cos(fy * yy)[..., None]
    img = low + (high - low) * np.clip(img, 0.0, 1.0)
    for _ in range(highlights):
        y0, x0 = rng.uniform(0.2 * h, 0.8 * h), rng.uniform(0.2 * w, 0.8 * w)
        r = rng.uniform(1.5, 3.5)
        img[(yy - y0) ** 2 + (xx - x0) ** 2 < r * r] = high * highlight_gain
    return img
