"""Can occlusion be had without layers?  A layer-free per-sample search, scored like the bench.

Issue 11's 2x cost target is out of reach of the layered exposure on PoCL (``occlusion.md``,
Cost): the layers' preparation alone costs several gathers.  Real-time vector blur (McGuire
et al. 2012, Guertin et al. 2014) builds no layers; a fixed-count reconstruction filter after
them scored 25.6 - 29.3 dB here.  This script measures a stronger layer-free design, one that
keeps exact occlusion per shutter sample and needs only per-pixel and per-tile passes (what a
single fused kernel could do):

- candidates: at each sample ``t`` a pixel ``p`` may show light from ``q = p - u t`` for its
  own vector ``u = v(p)`` and for the distinct fastest and slowest vectors of the 8 x 8 tiles
  within the reach (the tile-max / neighbour-max idea);
- a corner ``n`` of ``q``'s bilinear footprint counts only if its own vector lands it on
  ``p``: ``|(v(n) - u) t| <= 0.75`` px, with its bilinear weight as coverage;
- candidates composite front to back by depth; what no candidate covers is light hidden at
  the frame time, taken from a fill along the motion (the two nearest deeper pixels on the
  line through ``p`` along ``v(p)``, interpolated by distance) that moves with their vector;
- variant ``+ split``: pixels on a depth edge join the nearer surface with a coverage fitted
  to their light, as ``clblur.layer_planes.split_coverage`` does for the layers.

Scored as ``bench/bench_occlusion.py`` scores (``tests/layered_scenes.py``, sRGB-encoded,
swept region, the truth's K here 64), against the gather and the depth layers of
``clblur.blur`` (numpy reference).  Run: ``python docs/studies/occlusion_candidates.py``
(about 15 s).  Measured 2026-11-29: ``occlusion.md``, Cost.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import clblur
from clblur.responses import response
from clblur.sampling import bilinear_corners

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from layered_scenes import psnr, scenes  # noqa: E402

TILE = 8
LANDS_PX = 0.75  # a corner whose own vector puts it within this of p at time t lands there
EPS = 1e-3  # depths closer than this are one surface


def _corners(img: np.ndarray, x: np.ndarray, y: np.ndarray):
    """(corner values, bilinear weight) for the four corners of positions x, y."""
    h, w = img.shape[:2]
    y0, y1, x0, x1, fx, fy = bilinear_corners(x, y, h, w)
    yield from ((y0, x0, (1 - fx) * (1 - fy)), (y0, x1, fx * (1 - fy)),
                (y1, x0, (1 - fx) * fy), (y1, x1, fx * fy))


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return sum(img[yi, xi] * wt[..., None] for yi, xi, wt in _corners(img, x, y))


def hidden_fill(lin: np.ndarray, v: np.ndarray, depth: np.ndarray):
    """What lies behind each pixel: the nearest deeper pixel on each side along ``v(p)``,
    interpolated by distance (the pixel itself where nothing deeper is within reach), and
    the vector it moves with."""
    h, w = depth.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    speed = np.hypot(v[..., 0], v[..., 1])
    unit = v / np.maximum(speed, 1e-9)[..., None]
    found, colour, vector, dist = [], [], [], []
    for sign in (1, -1):
        hit_any = np.zeros((h, w), bool)
        col, vec, dst = lin.copy(), v.copy(), np.full((h, w), np.inf)
        for s in range(1, int(np.ceil(speed.max())) + 3):
            x, y = xx + sign * s * unit[..., 0], yy + sign * s * unit[..., 1]
            xi, yi = np.rint(x).astype(int), np.rint(y).astype(int)
            inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            xi, yi = np.clip(xi, 0, w - 1), np.clip(yi, 0, h - 1)
            hit = ~hit_any & inside & (depth[yi, xi] > depth + EPS) & (speed > 0)
            col[hit], vec[hit], dst[hit] = lin[yi, xi][hit], v[yi, xi][hit], s
            hit_any |= hit
        for store, item in zip((found, colour, vector, dist), (hit_any, col, vec, dst),
                               strict=True):
            store.append(item)
    both = found[0] & found[1]
    near = np.where(both, dist[1] / np.where(both, dist[0] + dist[1], 1.0), found[0] * 1.0)
    out = colour[0] * near[..., None] + colour[1] * (1 - near[..., None])
    out = np.where((found[0] | found[1])[..., None], out, lin)
    first = found[0] & (~found[1] | (dist[0] <= dist[1]))
    vec = np.where(first[..., None], vector[0], np.where(found[1][..., None], vector[1], v))
    return out, vec


def split_edges(lin: np.ndarray, v: np.ndarray, depth: np.ndarray):
    """Pixels on a depth edge join the nearest surface of their 3 x 3 neighbourhood, with a
    coverage fitted to their light between that surface's nearest unmixed light (within
    2 px) and what lies behind (``split_coverage``'s colour line).  Returns the
    premultiplied light, coverage, vectors and depths of the front surface at each pixel."""
    from clblur.layer_planes import split_coverage

    h, w = depth.shape
    pad = [(2, 2), (2, 2)]
    dp, vp, lp = (np.pad(a, pad + [(0, 0)] * (a.ndim - 2), mode="edge") for a in (depth, v, lin))
    near, far, v_near = np.full((h, w), np.inf), np.full((h, w), -np.inf), v.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            sl = (slice(2 + dy, 2 + dy + h), slice(2 + dx, 2 + dx + w))
            dn, vn = dp[sl], vp[sl]
            v_near[dn < near] = vn[dn < near]
            near, far = np.minimum(near, dn), np.maximum(far, dn)
    edge = far > near + EPS
    ep = np.pad(edge, pad, mode="edge")
    pure, best = np.full(lin.shape, np.nan), np.full((h, w), np.inf)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            sl = (slice(2 + dy, 2 + dy + h), slice(2 + dx, 2 + dx + w))
            ok = (np.abs(dp[sl] - near) <= EPS) & ~ep[sl] & (dx * dx + dy * dy < best)
            pure[ok], best[ok] = lp[sl][ok], dx * dx + dy * dy
    depth2, v2 = np.where(edge, near, depth), np.where(edge[..., None], v_near, v)
    behind, _ = hidden_fill(lin, v2, depth2)
    alpha = np.where(edge, split_coverage(lin, pure, behind), 1.0)
    front = np.where(edge[..., None], lin - (1 - alpha)[..., None] * behind, lin)
    return front, alpha, v2, depth2


def tile_vectors(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the distinct fastest and slowest vectors of the tiles within the reach
    (H x W x K x 2) and which of the K are candidates (H x W x K)."""
    h, w = v.shape[:2]
    th, tw = -(-h // TILE), -(-w // TILE)
    speed = np.hypot(v[..., 0], v[..., 1])
    ends = np.zeros((th, tw, 2, 2))
    for i in range(th):
        for j in range(tw):
            blk = (slice(i * TILE, (i + 1) * TILE), slice(j * TILE, (j + 1) * TILE))
            s, vv = speed[blk].ravel(), v[blk].reshape(-1, 2)
            ends[i, j] = vv[np.argmax(s)], vv[np.argmin(s)]
    r = int(np.ceil(speed.max() / TILE)) + 1
    sets = [[np.unique(np.round(ends[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1]
                                .reshape(-1, 2), 3), axis=0) for j in range(tw)]
            for i in range(th)]
    k = max(len(u) for row in sets for u in row)
    cand, ok = np.zeros((h, w, k, 2)), np.zeros((h, w, k), bool)
    for i in range(th):
        for j in range(tw):
            blk = (slice(i * TILE, (i + 1) * TILE), slice(j * TILE, (j + 1) * TILE))
            u = sets[i][j]
            cand[blk][:, :, :len(u)], ok[blk][:, :, :len(u)] = u, True
    ok &= ~np.all(np.abs(cand - v[:, :, None, :]) < 1e-3, axis=-1)  # the own vector
    return cand, ok


def search_blur(lin: np.ndarray, v: np.ndarray, depth: np.ndarray, anchor: float,
                split: bool) -> np.ndarray:
    """Linear H x W x 3 exposure by the per-sample candidate search (module docstring)."""
    h, w = depth.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    if split:
        front, alpha, v, depth = split_edges(lin, v, depth)
    else:
        front, alpha = lin, np.ones((h, w))
    behind, v_behind = hidden_fill(lin, v, depth)
    cand, ok = tile_vectors(v)
    n = int(np.ceil(np.hypot(v[..., 0], v[..., 1]).max())) + 1
    acc = np.zeros_like(lin)
    for t in np.linspace(0.0, 1.0, n) - anchor:
        light, cover, near = [], [], []
        for c in range(cand.shape[2] + 1):
            u = v if c == cand.shape[2] else cand[:, :, c]
            usable = np.ones((h, w), bool) if c == cand.shape[2] else ok[:, :, c]
            x, y = xx - u[..., 0] * t, yy - u[..., 1] * t
            usable &= (x > -0.5) & (x < w - 0.5) & (y > -0.5) & (y < h - 0.5)
            col, a, dsum, wsum = np.zeros_like(lin), np.zeros((h, w)), np.zeros((h, w)), 0.0
            for yi, xi, wt in _corners(lin, x, y):
                lands = np.hypot(*np.moveaxis((v[yi, xi] - u) * t, -1, 0)) <= LANDS_PX
                wt = wt * lands * usable
                col += front[yi, xi] * wt[..., None]
                a, dsum, wsum = a + wt * alpha[yi, xi], dsum + wt * depth[yi, xi], wsum + wt
            light.append(col)
            cover.append(a)
            near.append(np.where(wsum > 0, dsum / np.maximum(wsum, 1e-12), np.inf))
        light, cover = np.stack(light), np.stack(cover)
        out, left = np.zeros_like(lin), np.ones((h, w))
        for idx in np.argsort(np.stack(near), axis=0):  # front to back
            a = np.take_along_axis(cover, idx[None], 0)[0]
            col = np.take_along_axis(light, idx[None, ..., None], 0)[0]
            take = np.minimum(a, left)
            out += col * (take / np.maximum(a, 1e-12))[..., None]
            left -= take
        x, y = xx - v_behind[..., 0] * t, yy - v_behind[..., 1] * t
        acc += out + _bilinear(behind, x, y) * left[..., None]
    return acc / n


def main() -> None:
    srgb = response("srgb")
    print("PSNR (dB) over the swept region; in / out: the pixels inside / outside the moving "
          "objects at the frame time\n")
    print("| scene | gather | depth layers | search | search + split | depth layers in / out "
          "| search in / out | search + split in / out |")
    print("|---|---|---|---|---|---|---|---|")
    for name in ("disc", "disc-diagonal", "crossing-faster-behind", "crossing-faster-in-front"):
        sc = scenes()[name]
        lin, truth = sc.render(sc.anchor), srgb.forward(sc.truth(64))
        frame, (flow, depth), swept = srgb.forward(lin), sc.maps(), sc.swept()
        inside = swept & (depth < depth.max())
        got = {"gather": clblur.blur(frame, flow, "srgb", backend="numpy"),
               "layers": clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth)}
        for split in (False, True):
            got[split] = srgb.forward(search_blur(lin, flow.astype(float), depth, sc.anchor,
                                                  split))
        whole = [f"{psnr(got[k], truth, swept):.2f}" for k in ("gather", "layers", False, True)]
        parts = [f"{psnr(got[k], truth, inside):.2f} / {psnr(got[k], truth, swept & ~inside):.2f}"
                 for k in ("layers", False, True)]
        print(f"| {name} | " + " | ".join(whole + parts) + " |", flush=True)


if __name__ == "__main__":
    main()
