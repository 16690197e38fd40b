"""What a scene is: textures, object shapes, moving objects, the background, example scenes.

Objects follow ``c(t) = c0 + v t + a t^2 / 2`` and turn at ``w`` radians per exposure; the
renderer (``clblur.scenes.renderer``) evaluates them.  ``frame_displacements`` gives the
per-frame vectors a renderer stores for a scene.

Conventions
-----------
The package's (``clblur.scenes``): pixel centres at integer ``x = col``, ``y = row``; time in
exposures with the shutter open over ``[-1/2, 1/2]``; depth smaller is nearer; radiance linear.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError

__all__ = ["Texture", "wave_texture", "flat_texture", "Disc", "Rect", "MaskShape", "star_mask",
           "SceneObject", "Background", "Scene", "frame_displacements", "example_scenes"]


Texture = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""A texture maps local coordinates ``(u, v)`` (arrays of one shape ``S``, pixels) to linear
radiance of shape ``S + (C,)``."""


def wave_texture(seed: int, base: Sequence[float], contrast: float = 0.5, waves: int = 6,
                 periods: tuple[float, float] = (7.0, 40.0)) -> Texture:
    """A band-limited random texture: ``base * (1 + contrast * sum of plane waves)``.

    Periods lie in ``periods`` (pixels), so the texture is smooth at the pixel scale (a vector
    blur's bilinear interpolation is then not what is scored); the wave sum is normalised to
    [-1, 1], so radiance stays within ``base * (1 +- contrast)``.
    """
    rng = np.random.default_rng(seed)
    base = np.asarray(base, np.float64)
    period = rng.uniform(*periods, waves)
    theta = rng.uniform(0, np.pi, waves)
    k = np.stack([np.cos(theta), np.sin(theta)], axis=1) * (2 * np.pi / period)[:, None]
    phase = rng.uniform(0, 2 * np.pi, waves)
    # each wave tints the channels differently, so colour edges exist too
    tint = rng.uniform(0.3, 1.0, (waves, base.size))
    norm = tint.sum(axis=0)

    def tex(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        s = np.zeros(u.shape + (base.size,))
        for i in range(waves):
            s += np.sin(k[i, 0] * u + k[i, 1] * v + phase[i])[..., None] * tint[i]
        return base * (1.0 + contrast * s / norm)

    return tex


def flat_texture(colour: Sequence[float]) -> Texture:
    """A constant linear radiance."""
    c = np.asarray(colour, np.float64)
    return lambda u, v: np.broadcast_to(c, u.shape + (c.size,)).copy()


@dataclass(frozen=True)
class Disc:
    """A disc of ``radius`` pixels centred on the object's origin."""

    radius: float

    @property
    def extent(self) -> float:
        return self.radius

    def inside(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return u * u + v * v <= self.radius ** 2


@dataclass(frozen=True)
class Rect:
    """A ``width x height`` rectangle centred on the object's origin (before rotation)."""

    width: float
    height: float

    @property
    def extent(self) -> float:
        return math.hypot(self.width, self.height) / 2

    def inside(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return (np.abs(u) <= self.width / 2) & (np.abs(v) <= self.height / 2)


@dataclass(frozen=True, eq=False)
class MaskShape:
    """An arbitrary shape: a 2-D mask (truthy = inside), one cell per ``scale`` pixels, its
    centre on the object's origin; sampled nearest-cell."""

    mask: np.ndarray
    scale: float = 1.0

    @property
    def extent(self) -> float:
        h, w = np.shape(self.mask)
        return math.hypot(h, w) * self.scale / 2 + self.scale

    def inside(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        m = np.asarray(self.mask, bool)
        h, w = m.shape
        col = np.floor(u / self.scale + w / 2).astype(np.int64)
        row = np.floor(v / self.scale + h / 2).astype(np.int64)
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        out = np.zeros(u.shape, bool)
        out[ok] = m[row[ok], col[ok]]
        return out


def star_mask(outer: float, inner: float, points: int = 5, cells: int | None = None) -> np.ndarray:
    """A star-shaped boolean mask (``points`` tips at ``outer``, notches at ``inner`` pixels),
    sampled at 4 x 4 points per cell so its rim is not a pixel staircase of the polar form."""
    n = cells or int(math.ceil(2 * outer)) + 2
    sub = (np.arange(4 * n) + 0.5) / 4 - n / 2
    yy, xx = np.meshgrid(sub, sub, indexing="ij")
    r = np.hypot(xx, yy)
    a = np.arctan2(yy, xx)
    edge = inner + (outer - inner) * (0.5 + 0.5 * np.cos(points * a))
    fine = r <= edge
    return fine.reshape(n, 4, n, 4).mean(axis=(1, 3)) >= 0.5


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One rigid textured object.

    ``center`` (x, y) at t = 0; ``velocity`` displacement of the centre over the exposure;
    ``acceleration`` (pixels per exposure^2); ``angle`` at t = 0 and ``spin`` over the
    exposure, radians; ``depth`` smaller = nearer.  The texture is attached to the object (it
    turns with it).
    """

    shape: Disc | Rect | MaskShape
    texture: Texture
    center: tuple[float, float]
    velocity: tuple[float, float] = (0.0, 0.0)
    depth: float = 1.0
    angle: float = 0.0
    spin: float = 0.0
    acceleration: tuple[float, float] = (0.0, 0.0)
    name: str = ""

    def position(self, t: float) -> np.ndarray:
        c, v, a = (np.asarray(x, np.float64) for x in (self.center, self.velocity,
                                                         self.acceleration))
        return c + v * t + 0.5 * a * t * t

    def angle_at(self, t: float) -> float:
        return self.angle + self.spin * t

    def to_local(self, x: np.ndarray, y: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Screen points -> the object's local coordinates at time ``t``."""
        cx, cy = self.position(t)
        c, s = math.cos(self.angle_at(t)), math.sin(self.angle_at(t))
        dx, dy = x - cx, y - cy
        return c * dx + s * dy, -s * dx + c * dy

    def to_screen(self, u: np.ndarray, v: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Local coordinates -> screen points at time ``t``."""
        cx, cy = self.position(t)
        c, s = math.cos(self.angle_at(t)), math.sin(self.angle_at(t))
        return cx + c * u - s * v, cy + s * u + c * v


@dataclass(frozen=True, eq=False)
class Background:
    """An infinite textured plane behind every object, translating by ``velocity`` over the
    exposure (a camera pan); ``depth`` is what the depth pass says where no object is."""

    texture: Texture
    velocity: tuple[float, float] = (0.0, 0.0)
    depth: float = 1000.0

    def moves(self) -> bool:
        return any(float(c) != 0.0 for c in self.velocity)


@dataclass(frozen=True, eq=False)
class Scene:
    width: int
    height: int
    background: Background
    objects: tuple[SceneObject, ...] = ()
    name: str = ""
    description: str = ""



def frame_displacements(scene: Scene, shutter: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame displacements a renderer would store at ``t = 0`` for a shutter fraction
    ``shutter`` (exposure / frame interval, 0 < shutter <= 1): ``(prev_to_current,
    current_to_next)``, each H x W x 2 float32 in clblur's axes (x right, y down, pixels per
    frame), of the material point at each pixel centre: ``P(0) - P(-1/s)`` and
    ``P(1/s) - P(0)``.  Feed them to ``clblur.vectors.to_blender`` / ``to_nuke`` to build a
    renderer's vector pass."""
    if not 0 < shutter <= 1:
        raise InputError(f"shutter must be a fraction of the frame in (0, 1], got {shutter}")
    h, w = scene.height, scene.width
    span = 1.0 / shutter
    yc, xc = np.mgrid[0:h, 0:w].astype(np.float64)
    bg = np.asarray(scene.background.velocity, np.float64) * span
    prev = np.empty((h, w, 2))
    nxt = np.empty((h, w, 2))
    prev[...] = bg
    nxt[...] = bg
    for i in sorted(range(len(scene.objects)), key=lambda i: -scene.objects[i].depth):
        obj = scene.objects[i]
        u, v = obj.to_local(xc, yc, 0.0)
        m = obj.shape.inside(u, v)
        if not m.any():
            continue
        p = {t: np.stack(obj.to_screen(u[m], v[m], t), axis=-1) for t in (-span, 0.0, span)}
        prev[m] = p[0.0] - p[-span]
        nxt[m] = p[span] - p[0.0]
    return prev.astype(np.float32), nxt.astype(np.float32)


def example_scenes(width: int = 240, height: int = 160,
                   background_contrast: float = 0.6) -> dict[str, Scene]:
    """The scored scenes of ``docs/studies/occlusion.md`` (a pan with no objects; a disc; a
    spinning rectangle; two crossings, the fast object behind and in front; a crossing whose
    fast far object is almost hidden at the frame time; a star leaving the frame; a pan with an
    object moving against it).  ``background_contrast`` scales the
    background texture's modulation (0.6: busy; 0.15: gentle).  Radiance stays below 0.85."""
    w, h = width, height
    bg = Background(wave_texture(1, (0.16, 0.14, 0.10), background_contrast))
    t_ball = wave_texture(2, (0.62, 0.35, 0.18), 0.5, periods=(5.0, 16.0))
    t_box = wave_texture(3, (0.20, 0.42, 0.55), 0.55, periods=(6.0, 20.0))
    t_star = wave_texture(4, (0.70, 0.66, 0.30), 0.3, periods=(5.0, 12.0))
    cx, cy = w / 2, h / 2
    scenes = [
        Scene(w, h, Background(bg.texture, velocity=(14.0, -5.0)), (), "pan",
              "the camera pans 14 px right, 5 up; no object (no occlusion)"),
        Scene(w, h, bg, (SceneObject(Disc(18), t_ball, (cx, cy), (36.0, 0.0), 1.0,
                                     name="ball"),), "disc",
              "a textured disc moves 36 px right over a static background"),
        Scene(w, h, bg, (SceneObject(Rect(56, 26), t_box, (cx, cy), (22.0, 10.0), 1.0,
                                     angle=0.3, spin=0.45, name="box"),), "spinning_rect",
              "a rectangle moves 22 px right, 10 down and turns 26 degrees"),
        # the fast disc is beside the slow one at the frame time and passes behind (or in
        # front of) it during the second half of the shutter
        Scene(w, h, bg, (SceneObject(Disc(20), t_ball, (cx - 8, cy), (8.0, 0.0), 1.0,
                                     name="slow, near"),
                         SceneObject(Disc(13), t_box, (cx + 20, cy + 6), (-44.0, -6.0), 2.0,
                                     name="fast, far")), "crossing_fast_behind",
              "a slow near disc (8 px) and a fast far disc (44 px) cross during the shutter; "
              "the fast one is behind"),
        Scene(w, h, bg, (SceneObject(Disc(20), t_ball, (cx - 8, cy), (8.0, 0.0), 2.0,
                                     name="slow, far"),
                         SceneObject(Disc(13), t_box, (cx + 20, cy + 6), (-44.0, -6.0), 1.0,
                                     name="fast, near")), "crossing_fast_front",
              "the same crossing with the fast disc in front"),
        # worst case: at the frame time the fast disc is almost entirely behind the slow one,
        # so the sharp frame hardly shows the object whose streak the truth contains
        Scene(w, h, bg, (SceneObject(Disc(20), t_ball, (cx - 8, cy), (8.0, 0.0), 1.0,
                                     name="slow, near"),
                         SceneObject(Disc(13), t_box, (cx + 4, cy + 6), (-44.0, -6.0), 2.0,
                                     name="fast, far")), "crossing_hidden_behind",
              "the fast far disc is almost hidden by the slow near one at the frame time"),
        Scene(w, h, bg, (SceneObject(MaskShape(star_mask(24, 12)), t_star, (w - 14, cy - 10),
                                     (30.0, 12.0), 1.0, spin=-0.6, acceleration=(20.0, 0.0),
                                     name="star"),), "star_leaving",
              "a spinning, accelerating star leaves the frame on the right"),
        Scene(w, h, Background(bg.texture, velocity=(-12.0, 0.0)),
              (SceneObject(Rect(30, 60), t_box, (cx, cy), (26.0, 3.0), 1.0, angle=0.1,
                           name="player"),), "pan_and_object",
              "the camera pans 12 px left while a tall box moves 26 px right"),
    ]
    return {s.name: s for s in scenes}
