"""Small layered scenes with an exact sub-frame exposure, for the layered-exposure tests and
``bench/bench_occlusion.py``.

A scene is a textured static background (depth ``BACKGROUND_DEPTH``) and textured discs, each
with a centre at the anchor time, a radius, a displacement over the whole shutter and a depth.
``render(t)`` draws the scene at shutter time ``t`` in [0, 1] with exact occlusion (the nearest
disc covering each sub-pixel wins) and ``SS`` x ``SS`` sub-pixels per pixel, averaged in linear
light; ``truth`` averages ``K`` such renders at the mid-points of ``K`` equal shutter slices,
the exposure a camera records.  Textures move with their disc.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BACKGROUND_DEPTH = 100.0
SS = 4


@dataclass(frozen=True)
class Disc:
    centre: tuple[float, float]  # (x, y) at the anchor time
    radius: float
    motion: tuple[float, float]  # (dx, dy) over the whole shutter
    depth: float
    seed: int


def texture(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """Smooth linear-light RGB texture in [0.04, 0.9] (a few random sinusoids)."""
    rng = np.random.default_rng(seed)
    out = np.empty((*x.shape, 3))
    for c in range(3):
        acc = np.full(x.shape, rng.uniform(0.25, 0.6))
        for _ in range(3):
            fx, fy = rng.normal(scale=0.25, size=2)
            acc += rng.uniform(0.05, 0.12) * np.sin(fx * x + fy * y + rng.uniform(0, 6.3))
        out[..., c] = acc
    return np.clip(out, 0.04, 0.9)


@dataclass(frozen=True)
class Scene:
    shape: tuple[int, int]
    discs: tuple[Disc, ...]
    anchor: float = 0.5
    background_seed: int = 7

    def _sub(self):
        h, w = self.shape
        o = (np.arange(SS) + 0.5) / SS - 0.5
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        return (xx[:, :, None, None] + o[None, None, None, :],
                yy[:, :, None, None] + o[None, None, :, None])

    def render(self, t: float) -> np.ndarray:
        """Linear RGB at shutter time ``t`` (H x W x 3 float64), exact occlusion."""
        x, y = self._sub()
        x, y = np.broadcast_arrays(x, y)
        colour = texture(x, y, self.background_seed)
        depth = np.full(x.shape, BACKGROUND_DEPTH)
        for d in self.discs:
            cx = d.centre[0] + d.motion[0] * (t - self.anchor)
            cy = d.centre[1] + d.motion[1] * (t - self.anchor)
            inside = (np.hypot(x - cx, y - cy) < d.radius) & (d.depth < depth)
            tex = texture(x - cx, y - cy, d.seed)
            colour = np.where(inside[..., None], tex, colour)
            depth = np.where(inside, d.depth, depth)
        return colour.mean(axis=(2, 3))

    def background(self) -> np.ndarray:
        """The clean plate: linear RGB of the background alone (H x W x 3)."""
        return Scene(self.shape, (), self.anchor, self.background_seed).render(self.anchor)

    def truth(self, k: int = 64) -> np.ndarray:
        return np.mean([self.render((i + 0.5) / k) for i in range(k)], axis=0)

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(flow H x W x 2 float32, depth H x W) at the anchor time, from each pixel centre."""
        h, w = self.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        flow = np.zeros((h, w, 2), np.float32)
        depth = np.full((h, w), BACKGROUND_DEPTH)
        for d in self.discs:
            inside = (np.hypot(xx - d.centre[0], yy - d.centre[1]) < d.radius) & (d.depth < depth)
            flow[inside] = d.motion
            depth[inside] = d.depth
        return flow, depth

    def swept(self) -> np.ndarray:
        """Pixels any disc covers at some time of the shutter (the scored region)."""
        h, w = self.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        out = np.zeros((h, w), bool)
        for d in self.discs:
            for t in np.linspace(0, 1, 65):
                cx = d.centre[0] + d.motion[0] * (t - self.anchor)
                cy = d.centre[1] + d.motion[1] * (t - self.anchor)
                out |= np.hypot(xx - cx, yy - cy) < d.radius + 1
        return out


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB, peak 1) of two encoded images over ``mask``."""
    mse = float(np.mean((a[mask] - b[mask]) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-20))


def scenes() -> dict[str, Scene]:
    """The scenes of the tests and the bench."""
    return {
        "disc": Scene((64, 96), (Disc((40.0, 32.0), 12.0, (20.0, 0.0), 10.0, 1),)),
        "disc-diagonal": Scene((64, 96), (Disc((48.0, 30.0), 10.0, (16.0, -12.0), 10.0, 2),)),
        # the two discs touch at the anchor time and cross during the shutter
        "crossing-faster-behind": Scene((72, 112), (
            Disc((46.0, 36.0), 12.0, (8.0, 2.0), 5.0, 3),     # near, slow
            Disc((66.0, 34.0), 9.0, (-28.0, 0.0), 20.0, 4),   # far, fast
        )),
        "crossing-faster-in-front": Scene((72, 112), (
            Disc((46.0, 36.0), 12.0, (8.0, 2.0), 20.0, 5),
            Disc((66.0, 34.0), 9.0, (-28.0, 0.0), 5.0, 6),
        )),
        "static": Scene((48, 64), (Disc((30.0, 24.0), 10.0, (0.0, 0.0), 10.0, 8),)),
        # two discs in opposite corners: layered apart, each on its own crop
        "two-far-apart": Scene((160, 288), (
            Disc((34.0, 30.0), 14.0, (16.0, 0.0), 10.0, 9),
            Disc((250.0, 128.0), 12.0, (-10.0, 8.0), 20.0, 10),
        )),
    }
