"""Virtual-camera data with hidden effects: the ground truth of the study's tests and limits.

Each effect is rendered in a data kind where it is observable, at a magnitude drawn from a
realistic range (``RANGES``) unless given.  Scenes are small random radiance maps
(``clblur.camera.random_scene``); the camera's response is the paper's ``Exp(3)`` unless the
effect is ``response_shape`` (a power law), ``response_imax`` (Eq. 3 with ``Imax`` above
the top code) or ``channel_shape`` (Eq. 3 with another exponent in R and in B).
``exposure_times`` renders a five-image series whose three inner images were each exposed
``exp(+-m)`` times their stated time; ``white_balance`` the same series with each inner
image's R gain ``exp(+-m)`` and B gain its inverse.

Why these kinds: with the paper's exponential a black offset cancels in an equal-exposure pair
(``1 - g = prod (1 - f)^w`` just scales by ``1 - beta``), so ``black_level`` is hidden in an
exposure series; a vignetting falloff fixed to the sensor only shows where the path is not
centred on the pixel, so ``vignetting`` uses ``anchor="start"``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from clblur.camera import Camera, accelerating_weights, random_scene
from clblur.errors import InputError
from clblur.responses import Exp, ExpShape, Gamma
from clblur.study.model import Group
from clblur.study.pairs import pair_group
from clblur.study.series import series_groups
from clblur.study.stacks import stack_group

__all__ = ["CLIP", "RANGES", "Scenario", "null_series", "null_stack", "random_psf", "scenario"]

# effect: (low, high) of the hidden magnitude, in the units of ``magnitude`` below
RANGES = {
    "black_level": (0.02, 0.08),  # normalised black offset (5 to 20 codes)
    "response_shape": (1.6, 2.4),  # camera gamma (power-law response)
    "saturation": (2.0, 8.0),  # highlight exposure / least exposure that clips
    "noise": (2e-4, 2e-3),  # Poisson coefficient a (full-well units); b = a / 100
    "vignetting": (0.3, 0.8),  # c: corner falloff 1 - (1 + c)^-2 = 31 % to 69 %
    "nonuniform_motion": (2.0, 4.0),  # end / start speed (or its inverse)
    "channel_gain": (0.05, 0.15),  # |log| of the R and B gain change (G fixed)
    "exposure_gain": (0.08, 0.25),  # |log| of the gain change
    "quantisation": (0.3, 0.7),  # |offset| of the stored blurred codes (negative: truncation)
    "misregistration": (0.3, 0.8),  # length of the blurred image's shift, pixels
    "psf_orientation": (1.0, 1.0),  # the blurred image made with the PSF turned by 180 deg
    "psf_scale": (1.1, 1.25),  # true / stated motion length (or its inverse)
    "response_imax": (0.2, 0.6),  # rho = full scale / Imax of the camera's Eq. 3
    "channel_shape": (0.1, 0.25),  # |log| of the R and B factor on Eq. 3's exponent (G fixed)
    "exposure_times": (0.04, 0.12),  # |log| of each inner image's factor on its nominal time
    "white_balance": (0.04, 0.12),  # |log| of each inner image's R and B gain (G fixed)
    "optical_blur": (0.4, 1.5),  # variance (px^2 per axis) of a Gaussian blur of the target
}
CLIP = 6.2 / 3.0  # exposure at which Exp(3) reaches code 255


@dataclass
class Scenario:
    kind: str
    groups: list[Group]
    truth: dict[str, float] = field(default_factory=dict)


def scenario(effects: dict[str, float | None], rng: np.random.Generator,
             shape: tuple[int, int] = (48, 64), psf: bool = False) -> Scenario:
    """Render data with the given hidden effects (``None`` magnitude: drawn from ``RANGES``);
    an empty dict renders null data (the paper's model exactly true).  ``psf``: a blur pair
    with a random asymmetric PSF instead of a vector (always so for ``psf_orientation``).

    ``quantisation`` stores the blurred image with an offset of ``-m`` codes (truncation of
    ``v + 0.5 - m``) or ``+m`` (rounding of ``v + m``); ``misregistration`` shifts the blurred
    image by ``m`` pixels in a random direction; ``psf_scale`` renders a motion ``m`` (or
    ``1 / m``) times as long as the one the study is told; ``optical_blur`` blurs the blurred
    image's light by a Gaussian of variance ``m`` px^2 (a softer lens)."""
    unknown = set(effects) - set(RANGES)
    if unknown:
        raise InputError(f"unknown effect(s) {sorted(unknown)}; use {', '.join(RANGES)}")
    mag = {e: (float(rng.uniform(*RANGES[e])) if m is None else float(m))
           for e, m in effects.items()}
    sign = float(rng.choice([-1.0, 1.0]))
    cam = {"response": Gamma(mag["response_shape"]) if "response_shape" in mag else Exp(3.0)}
    if "response_imax" in mag:  # Eq. 3 saturating above the top code, exposures as Exp(3)'s
        cam["response"] = ExpShape(0.0, 1.0, mag["response_imax"])
    if "channel_shape" in mag:  # Eq. 3 with the exponent of R and B turned apart (a film)
        f = math.exp(sign * mag["channel_shape"])
        cam["response"] = tuple(ExpShape(0.0, g, 1.0) for g in (f, 1.0, 1.0 / f))
    if "black_level" in mag:
        cam["black_level"] = mag["black_level"]
    if "noise" in mag:
        cam["noise_a"], cam["noise_b"] = mag["noise"], mag["noise"] / 100.0
    if "vignetting" in mag:
        cam["vignetting"] = mag["vignetting"]
    camera = Camera(**cam)
    high = 0.35 if "response_shape" not in mag else 0.8
    scene = random_scene(rng, shape, 3, low=0.03, high=high)
    if "response_imax" in mag:
        scene = 3.0 * scene
    if "saturation" in mag:
        _add_highlights(scene, rng, mag["saturation"] * CLIP)
    if "black_level" in mag or "channel_shape" in mag:
        # exposure series: a black offset cancels in an equal pair, and the exponents show
        # across exposures, as on a film scanned stop by stop
        times = [4.0, 2.0, 1.0, 0.5]
        imgs = [camera.capture(scene * 0.25, t, rng=rng) for t in times]
        return Scenario("exposure-series", series_groups(imgs, times), mag)
    if "exposure_times" in mag or "white_balance" in mag:
        # five stops told; each inner image exposed a factor exp(+-m) off its time, or with
        # its R and B gains turned apart by exp(+-m) (the longest and the shortest are the
        # reference: effects, lt:I and lw:I:c)
        # (both hidden together: each its own signs, the exposures' drawn first)
        times = [8.0, 4.0, 2.0, 1.0, 0.5]

        def offsets(effect: str) -> list[float]:
            if effect not in mag:
                return [0.0] * len(times)
            return [0.0, *(mag[effect] * rng.choice([-1.0, 1.0], 3)), 0.0]

        off, bal = offsets("exposure_times"), offsets("white_balance")
        imgs = [camera.capture(scene * 0.125, t * math.exp(d), rng=rng,
                               channel_gains=((math.exp(b), 1.0, math.exp(-b))
                                              if "white_balance" in mag else None))
                for t, d, b in zip(times, off, bal, strict=True)]
        return Scenario("exposure-series", series_groups(imgs, times), mag)
    length = float(rng.uniform(12, 16) if "vignetting" in mag else rng.uniform(6, 12))
    angle = float(rng.uniform(-0.4, 0.4)) + (math.pi if rng.random() < 0.5 else 0.0)
    motion = (length * math.cos(angle), length * math.sin(angle))
    told = motion
    kw: dict = {"anchor": "start" if "vignetting" in mag else "center"}
    if (psf or "psf_orientation" in mag) and "psf_scale" not in mag:
        told = random_psf(rng)
        motion = told[::-1, ::-1] if "psf_orientation" in mag else told
    if "psf_scale" in mag:
        f = mag["psf_scale"] ** sign
        motion = (told[0] * f, told[1] * f)  # a vector: the camera renders it exactly
    target_cam = camera
    if "quantisation" in mag:
        q = mag["quantisation"]
        target_cam = dataclasses.replace(
            camera, storage="floor" if sign < 0 else "round",
            code_offset=0.5 - q if sign < 0 else q)
    if "optical_blur" in mag:
        kw["optical_variance"] = mag["optical_blur"]
    if "misregistration" in mag:
        a = float(rng.uniform(0, 2 * math.pi))
        kw["shift"] = (mag["misregistration"] * math.cos(a), mag["misregistration"] * math.sin(a))
    if "nonuniform_motion" in mag:
        n = int(math.ceil(math.hypot(*motion))) + 1
        kw["weights"] = accelerating_weights(n, mag["nonuniform_motion"] ** sign)
    if "exposure_gain" in mag:
        kw["gain"] = math.exp(sign * mag["exposure_gain"])
    if "channel_gain" in mag:
        lg = sign * mag["channel_gain"]
        kw["channel_gains"] = (math.exp(lg), 1.0, math.exp(-lg))
    static = camera.capture(scene, rng=rng)
    blurred = target_cam.capture(scene, motion=motion, rng=rng, **kw)
    return Scenario("blur-pair", [pair_group(static, blurred, told, anchor=kw["anchor"])], mag)


def random_psf(rng: np.random.Generator, size: int = 11) -> np.ndarray:
    """A camera-shake-like kernel: a random walk with momentum (asymmetric, unit sum)."""
    k = np.zeros((size, size))
    pos = np.array([size / 2.0, size / 2.0])
    vel = rng.normal(0, 1, 2)
    vel /= np.linalg.norm(vel)
    for _ in range(40):
        vel = vel + rng.normal(0, 0.35, 2)
        vel /= np.linalg.norm(vel)
        pos = np.clip(pos + 0.25 * vel, 0, size - 1)
        k[int(round(pos[0])), int(round(pos[1]))] += rng.uniform(0.5, 1.5)
    # a heavier tail at one end makes the 180-degree turn distinguishable
    k[int(round(pos[0])), int(round(pos[1]))] += 6.0
    return k / k.sum()


def null_stack(rng: np.random.Generator, shape=(48, 64), frames: int = 6,
               gamma: float | None = None, storage: str = "round") -> Scenario:
    """A frame stack of a moving scene: ``frames`` short captures and the long one spanning
    them, rendered as the exact temporal Eq. 8 (``gamma``: a power-law camera instead;
    ``storage="floor"``: the long one truncated, a -0.5 code bias).

    The long capture's total exposure equals the frames' mean exposure (as when frames are
    averaged into a longer exposure, or the long one is taken through an ND filter)."""
    camera = Camera(response=Gamma(gamma) if gamma else Exp(3.0))
    scene = random_scene(rng, (shape[0], shape[1] + 3 * frames), 3, low=0.03, high=0.35)
    shots = [scene[:, 3 * t:3 * t + shape[1]] for t in range(frames)]
    short = [camera.capture(s, rng=rng) for s in shots]
    long = dataclasses.replace(camera, storage=storage).capture(sum(shots) / frames, rng=rng)
    truth = {"response_shape": gamma} if gamma else {}
    if storage == "floor":
        truth["quantisation"] = 0.5
    return Scenario("frame-stack", [stack_group(short, long)], truth)


def null_series(rng: np.random.Generator, shape=(48, 64), noise: float = 0.0) -> Scenario:
    """An exposure series of the paper's Eq. 3 camera, one stop apart (4, 2, 1, 1/2),
    nothing hidden; ``noise``: the camera's Poisson coefficient ``a`` (``b = a / 100``),
    then ``noise`` is the one true finding."""
    camera = Camera(noise_a=noise, noise_b=noise / 100.0)
    scene = random_scene(rng, shape, 3, low=0.03, high=0.35)
    times = [4.0, 2.0, 1.0, 0.5]
    images = [camera.capture(scene * 0.25, t, rng=rng) for t in times]
    return Scenario("exposure-series", series_groups(images, times),
                    {"noise": noise} if noise else {})


def _add_highlights(scene: np.ndarray, rng: np.random.Generator, level: float) -> None:
    h, w = scene.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    for _ in range(3):
        y0, x0 = rng.uniform(0.25 * h, 0.75 * h), rng.uniform(0.25 * w, 0.75 * w)
        r = rng.uniform(1.5, 3.0)
        scene[(yy - y0) ** 2 + (xx - x0) ** 2 < r * r] = level
