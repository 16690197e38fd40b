"""The sub-frame ground-truth renderer and the score against it.

``render`` evaluates a ``Scene`` at ``samples`` instants of the shutter with exact occlusion,
averages the radiance in the linear domain, then applies the response and quantises; it also
returns the compositor's passes (``Render``).  ``psnr`` scores an image against it.

Conventions
-----------
The package's (``clblur.scenes``), which states the time, motion-vector, depth, coverage,
swept-region and hidden-light conventions in full.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from clblur.errors import InputError
from clblur.pixels import imax, quantise
from clblur.responses import Response, per_channel
from clblur.scenes.description import Scene, SceneObject

__all__ = ["Render", "object_layers", "render", "psnr"]


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
        raise InputError(f"background texture gives {rad.shape[-1]} channels, expected "
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
        raise InputError(f"samples must be >= 2, got {samples}")
    if spp < 1:
        raise InputError(f"spp must be >= 1, got {spp}")
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



def object_layers(scene: Scene, response="srgb", dtype=np.uint8, *, spp: int = 2,
                  channels: int = 3, overscan: int = 0) -> list[tuple[np.ndarray, np.ndarray,
                                                                           np.ndarray, np.ndarray]]:
    """The scene as a multi-layer render at t = 0: every object alone, then the background.

    Front to back, one ``(image, flow, first, second)`` per layer, ``overscan`` pixels beyond
    the frame on every side: ``image`` is H x W x (C + 1) in ``dtype``, colour through the
    response then coverage (straight alpha for integer dtypes, premultiplied for float: the
    convention of ``clblur.blur_layers``), the object's coverage anti-aliased as ``render``'s
    sharp frame; ``flow``, ``first`` and ``second`` are its vectors at the centres of the
    pixels it covers at all (its rigid motion there; zero elsewhere), as ``render`` defines
    them.  The background layer is opaque.
    """
    h, w, m = scene.height + 2 * overscan, scene.width + 2 * overscan, overscan
    resp = per_channel(response, channels)
    x, y = _grid(h, w, spp)
    x, y = x - m, y - m  # scene coordinates
    yc, xc = (a.astype(np.float64) - m for a in np.mgrid[0:h, 0:w])
    bvx, bvy = scene.background.velocity

    def encode(premultiplied: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        straight = dtype is not None and np.dtype(dtype).kind == "u"
        colour = premultiplied / np.where(alpha > 0, alpha, 1.0)[..., None] if straight \
            else premultiplied
        out = np.empty(colour.shape[:2] + (channels + 1,))
        for c, r in enumerate(resp):
            out[..., c] = r.forward(colour[..., c])
        out[..., channels] = alpha
        if straight:
            out[alpha == 0] = 0.0
        return quantise(out, dtype)

    layers = []
    for i in sorted(range(len(scene.objects)), key=lambda i: scene.objects[i].depth):
        obj = scene.objects[i]
        u, v = obj.to_local(x, y, 0.0)
        inside = obj.shape.inside(u, v)
        light = np.zeros(x.shape + (channels,))
        light[inside] = obj.texture(u[inside], v[inside])
        alpha = inside.mean(axis=2)
        vec = np.zeros((3, h, w, 2))
        # the body's motion at every pixel it covers at all (a rigid motion is defined at the
        # centre of a rim pixel too, whether or not the shape contains that point)
        u, v = obj.to_local(xc, yc, 0.0)
        at = alpha > 0
        u, v = u[at], v[at]
        if at.any():
            p = {t: np.stack(obj.to_screen(u, v, t), axis=-1) for t in (-0.5, 0.0, 0.5)}
            vec[0][at], vec[1][at], vec[2][at] = p[0.5] - p[-0.5], p[0.0] - p[-0.5], \
                p[0.5] - p[0.0]
        layers.append((encode(light.mean(axis=2), alpha), *vec.astype(np.float32)))
    plate = scene.background.texture(x, y).mean(axis=2)
    full = np.empty((h, w, 2), np.float32)
    full[...] = (bvx, bvy)
    layers.append((encode(plate, np.ones((h, w))), full, full / 2, full / 2))
    return layers


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of ``a`` against ``b`` (same dtype), over ``mask`` (H x W) if given; the
    peak is the dtype's full scale (255 for uint8)."""
    peak = imax(np.asarray(b).dtype)
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    if mask is not None:
        d = d[np.asarray(mask, bool)]
        if d.size == 0:
            raise InputError("empty mask: no pixel to score")
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else 10 * math.log10(peak * peak / mse)
