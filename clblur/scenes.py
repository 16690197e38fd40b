"""Sub-frame ground truth: layered scenes rendered at many shutter instants with exact occlusion.

A camera integrates light over the exposure.  ``render`` evaluates a scene of textured,
depth-ordered objects (translating, accelerating and rotating over a textured, possibly
panning background) at ``samples`` instants of the shutter, resolves occlusion exactly at
every instant and sub-pixel (nearest object wins), averages the radiance in the *linear*
domain, and only then applies the camera response and quantises, with
``clblur.responses`` and ``clblur.pixels`` (the same curves and rounding the blur uses).  That
average is the exposure a camera records, the truth every vector blur is scored against.

Alongside it, ``render`` returns what a renderer hands a compositor at the shutter's centre
time: the sharp frame, per-pixel motion vectors in clblur's convention, depth, coverage (alpha)
and object IDs, plus the *swept region* (pixels any moving layer covers during the shutter).

Conventions
-----------
* Pixel ``(row, col)`` has its centre at ``x = col``, ``y = row`` (x right, y down, pixels),
  as in ``clblur.motion``.
* Time ``t`` is in units of the exposure, ``t = 0`` at the shutter's centre: the shutter is
  open over ``[-1/2, 1/2]``.  Instants are the midpoints ``t_k = (k + 1/2)/K - 1/2``
  (midpoint rule, ``K = samples``).  A frame interval is ``1/shutter`` exposures, so the
  previous and next frames are at ``t = -1/s`` and ``t = +1/s`` for a shutter fraction ``s``.
* An object's centre follows ``c(t) = c0 + v t + a t^2 / 2`` and its angle
  ``theta(t) = theta0 + w t`` (radians, positive turns +x towards +y, i.e. clockwise on
  screen).  A material point with local coordinates ``q`` (pixels, in the object's frame) is
  at ``c(t) + R(theta(t)) q``.  ``v`` is the centre's displacement over the exposure.
* Motion vectors (``Render.flow``): content displacement over the exposure, clblur's
  convention: the chord ``P(+1/2) - P(-1/2)`` of the material point ``P`` seen at the pixel
  centre at ``t = 0`` (the background's velocity where no object is).  ``flow_first`` /
  ``flow_second`` are the halves ``P(0) - P(-1/2)`` and ``P(1/2) - P(0)`` (a bent path, as
  ``clblur.video.half_paths`` gives).  Vectors, depth and IDs are point samples at the pixel
  centre, not anti-aliased (as renderers write Z, index and vector passes).
* Depth: smaller is nearer.  Each object has one constant depth; the background has
  ``Background.depth`` (default 1000).  Ties: the later object in ``Scene.objects`` is in front.
* Radiance is linear (exposure units of ``clblur.responses``: the response maps it to a
  normalised value).  Keep it inside the response's unclipped range (below 1 for ``srgb``) to
  score blur models rather than the saturation policy.
* Sub-pixel sampling: ``spp x spp`` stratified points per pixel (box filter), the same for the
  sharp frame and every instant.  ``alpha`` is the fraction of them covered by an object at
  ``t = 0``; ``exposure_alpha`` the same averaged over the shutter (the truth of a blurred
  matte).
* Swept region: pixels that any object covers (any sub-pixel point) at any instant or at
  ``t = 0``; every pixel when the background moves (then every pixel changes).
* Hidden light (``Render.hidden``): the fraction of a pixel's exposure that comes from surface
  points the sharp frame does not show (background disoccluded by a moving object, the part of
  a far object behind a near one, anything outside the frame at ``t = 0``), looked up on the
  sub-pixel grid.  No method that sees only the sharp frame can know that light; it bounds
  what any single-frame vector blur can score there.
* Clean plate (``Render.plate``): the background layer alone at ``t = 0`` through the same
  response and rounding, as a multi-layer render delivers it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from clblur.pixels import imax, quantise
from clblur.responses import Response, per_channel

__all__ = ["Texture", "wave_texture", "flat_texture", "Disc", "Rect", "MaskShape", "star_mask",
           "SceneObject", "Background", "Scene", "Render", "render", "psnr",
           "frame_displacements", "example_scenes"]

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


@dataclass(eq=False)
class Render:
    """Everything ``render`` returns (see the module Conventions)."""

    image: np.ndarray          # the true exposure: response + quantisation of ``exposure``
    exposure: np.ndarray       # H x W x C float64, linear mean over the shutter
    sharp: np.ndarray          # the frame at t = 0, response + quantisation
    sharp_linear: np.ndarray   # H x W x C float64 linear radiance at t = 0
    flow: np.ndarray           # H x W x 2 float32, displacement over the exposure
    flow_first: np.ndarray     # H x W x 2 float32, P(0) - P(-1/2)
    flow_second: np.ndarray    # H x W x 2 float32, P(1/2) - P(0)
    depth: np.ndarray          # H x W float32, smaller = nearer
    alpha: np.ndarray          # H x W float32, object coverage at t = 0
    exposure_alpha: np.ndarray  # H x W float32, object coverage averaged over the shutter
    ids: np.ndarray            # H x W int32: 0 background, i + 1 for scene.objects[i]
    swept: np.ndarray          # H x W bool
    hidden: np.ndarray         # H x W float32, shutter fraction of light the sharp frame hides
    plate: np.ndarray          # the background alone at t = 0 (a clean plate), like ``sharp``
    response: list[Response] = field(default_factory=list)
    samples: int = 0


def _grid(height: int, width: int, spp: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel sample positions, H x W x spp^2 each (stratified, pixel centres at integers)."""
    off = (np.arange(spp) + 0.5) / spp - 0.5
    oy, ox = np.meshgrid(off, off, indexing="ij")
    y = np.arange(height, dtype=np.float64)[:, None, None] + oy.ravel()[None, None, :]
    x = np.arange(width, dtype=np.float64)[None, :, None] + ox.ravel()[None, None, :]
    return np.broadcast_to(x, (height, width, spp * spp)), \
        np.broadcast_to(y, (height, width, spp * spp))


def _window(obj: SceneObject, t: float, height: int, width: int) -> tuple[slice, slice] | None:
    """Rows/columns that can contain the object at time ``t`` (None when off screen)."""
    cx, cy = obj.position(t)
    r = obj.shape.extent + 1.0
    r0, r1 = max(int(math.floor(cy - r)), 0), min(int(math.ceil(cy + r)) + 1, height)
    c0, c1 = max(int(math.floor(cx - r)), 0), min(int(math.ceil(cx + r)) + 1, width)
    if r0 >= r1 or c0 >= c1:
        return None
    return slice(r0, r1), slice(c0, c1)


def _draw(scene: Scene, order: list[int], x: np.ndarray, y: np.ndarray, t: float,
          channels: int) -> tuple[np.ndarray, np.ndarray, list]:
    """Radiance (H x W x S x C) and the visible layer's ID (H x W x S int32, 0 background) at
    time ``t``: the background, then objects far to near, each painting over what is behind
    it.  Also the painted parts ``(index, window, mask, u, v)`` for the hidden-light bookkeeping."""
    bg = scene.background
    bvx, bvy = bg.velocity
    rad = bg.texture(x - bvx * t, y - bvy * t)
    if rad.shape[-1] != channels:
        raise ValueError(f"background texture gives {rad.shape[-1]} channels, expected "
                         f"{channels}")
    ids = np.zeros(x.shape, np.int32)
    parts = []
    for i in order:
        obj = scene.objects[i]
        win = _window(obj, t, scene.height, scene.width)
        if win is None:
            continue
        u, v = obj.to_local(x[win], y[win], t)
        m = obj.shape.inside(u, v)
        if not m.any():
            continue
        rad[win][m] = obj.texture(u[m], v[m])
        ids[win][m] = i + 1
        parts.append((i, win, m, u[m], v[m]))
    return rad, ids, parts


def _fine(ids: np.ndarray, spp: int) -> np.ndarray:
    """H x W x spp^2 sub-pixel IDs -> the (H spp) x (W spp) grid they sample."""
    h, w = ids.shape[:2]
    return ids.reshape(h, w, spp, spp).transpose(0, 2, 1, 3).reshape(h * spp, w * spp)


def _hidden_at_centre(ids0: np.ndarray, spp: int, layer: int, x0: np.ndarray,
                      y0: np.ndarray) -> np.ndarray:
    """True where a surface point of ``layer`` now at ``(x0, y0)`` at t = 0 is not what the
    sharp frame shows there (covered by another layer, or outside the frame)."""
    gx = np.floor((x0 + 0.5) * spp).astype(np.int64)
    gy = np.floor((y0 + 0.5) * spp).astype(np.int64)
    inside = (gx >= 0) & (gx < ids0.shape[1]) & (gy >= 0) & (gy < ids0.shape[0])
    hidden = np.ones(x0.shape, bool)
    hidden[inside] = ids0[gy[inside], gx[inside]] != layer
    return hidden


def render(scene: Scene, response="srgb", dtype=np.uint8, *, samples: int = 64,
           spp: int = 2, channels: int = 3) -> Render:
    """Render ``scene``: the true exposure at ``samples`` shutter instants and the passes at
    the shutter's centre.

    Parameters
    ----------
    scene : the layered scene.
    response : a response spec or ``Response`` (or one per channel), as ``clblur.blur`` takes.
    dtype : output dtype of ``image`` and ``sharp`` (uint8, uint16, float32, float64).
    samples : shutter instants ``K`` (midpoint rule); at least 2.
    spp : sub-pixel samples per axis (``spp^2`` per pixel, box filter).
    channels : colour channels the textures return.

    Returns
    -------
    Render
        See the module Conventions for every field's units and signs.
    """
    if samples < 2:
        raise ValueError(f"samples must be >= 2, got {samples}")
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    imax(dtype)  # rejects unsupported dtypes early
    h, w = scene.height, scene.width
    resp = per_channel(response, channels)
    # far to near; ties keep list order, so a later object paints over an earlier one
    order = sorted(range(len(scene.objects)), key=lambda i: -scene.objects[i].depth)
    x, y = _grid(h, w, spp)
    rad0, ids0, _ = _draw(scene, order, x, y, 0.0, channels)
    fine0 = _fine(ids0, spp)
    bvx, bvy = scene.background.velocity
    acc = np.zeros((h, w, channels))
    cov_acc = np.zeros((h, w))
    hid_acc = np.zeros((h, w))
    swept = np.zeros((h, w), bool)
    for k in range(samples):
        t = (k + 0.5) / samples - 0.5
        rad, ids, parts = _draw(scene, order, x, y, t, channels)
        acc += rad.mean(axis=2)
        covered = ids > 0
        cov_acc += covered.mean(axis=2)
        swept |= covered.any(axis=2)
        # light from surfaces the sharp frame does not show (disoccluded background, the
        # hidden part of a far object, anything outside the frame at t = 0)
        hidden = np.zeros(ids.shape, bool)
        bg = ids == 0
        hidden[bg] = _hidden_at_centre(fine0, spp, 0, x[bg] - bvx * t, y[bg] - bvy * t)
        for i, win, m, u, v in parts:
            seen = ids[win][m] == i + 1
            x0, y0 = scene.objects[i].to_screen(u[seen], v[seen], 0.0)
            sub = hidden[win]
            idx = tuple(a[seen] for a in np.nonzero(m))
            sub[idx] = _hidden_at_centre(fine0, spp, i + 1, x0, y0)
        hid_acc += hidden.mean(axis=2)
    exposure = acc / samples
    sharp_linear = rad0.mean(axis=2)
    swept |= (ids0 > 0).any(axis=2)
    if scene.background.moves():
        swept[:] = True

    # passes at the pixel centres (t = 0), not anti-aliased
    yc, xc = np.mgrid[0:h, 0:w].astype(np.float64)
    flow = np.empty((h, w, 2))
    flow[...] = (bvx, bvy)
    first = flow / 2
    second = flow / 2
    depth = np.full((h, w), scene.background.depth, np.float64)
    ids_c = np.zeros((h, w), np.int32)
    for i in order:
        obj = scene.objects[i]
        u, v = obj.to_local(xc, yc, 0.0)
        m = obj.shape.inside(u, v)
        if not m.any():
            continue
        p = {t: np.stack(obj.to_screen(u[m], v[m], t), axis=-1) for t in (-0.5, 0.0, 0.5)}
        flow[m] = p[0.5] - p[-0.5]
        first[m] = p[0.0] - p[-0.5]
        second[m] = p[0.5] - p[0.0]
        depth[m] = obj.depth
        ids_c[m] = i + 1

    def picture(lin: np.ndarray) -> np.ndarray:
        out = np.empty_like(lin)
        for c, r in enumerate(resp):
            out[..., c] = r.forward(lin[..., c])
        return quantise(out, dtype)

    plate = scene.background.texture(x, y).mean(axis=2)  # the background layer at t = 0
    return Render(image=picture(exposure), exposure=exposure, sharp=picture(sharp_linear),
                  plate=picture(plate),
                  sharp_linear=sharp_linear, flow=flow.astype(np.float32),
                  flow_first=first.astype(np.float32), flow_second=second.astype(np.float32),
                  depth=depth.astype(np.float32), alpha=(ids0 > 0).mean(axis=2).astype(np.float32),
                  exposure_alpha=(cov_acc / samples).astype(np.float32), ids=ids_c, swept=swept,
                  hidden=(hid_acc / samples).astype(np.float32),
                  response=resp, samples=samples)


def frame_displacements(scene: Scene, shutter: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame displacements a renderer would store at ``t = 0`` for a shutter fraction
    ``shutter`` (exposure / frame interval, 0 < shutter <= 1): ``(prev_to_current,
    current_to_next)``, each H x W x 2 float32 in clblur's axes (x right, y down, pixels per
    frame), of the material point at each pixel centre: ``P(0) - P(-1/s)`` and
    ``P(1/s) - P(0)``.  Feed them to ``clblur.vectors.to_blender`` / ``to_nuke`` to build a
    renderer's vector pass."""
    if not 0 < shutter <= 1:
        raise ValueError(f"shutter must be a fraction of the frame in (0, 1], got {shutter}")
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


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of ``a`` against ``b`` (same dtype), over ``mask`` (H x W) if given; the
    peak is the dtype's full scale (255 for uint8)."""
    peak = imax(np.asarray(b).dtype)
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    if mask is not None:
        d = d[np.asarray(mask, bool)]
        if d.size == 0:
            raise ValueError("empty mask: no pixel to score")
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else 10 * math.log10(peak * peak / mse)


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
