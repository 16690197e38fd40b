"""The device layer labels (``clblur/opencl/labels.py``) against ``clblur.layering``.

Every check is exact: the int32 labels equal ``clblur.layering.layer_labels``' (with the cap
``MAX_LAYERS`` and with a cap no scene reaches, so that every ordered surface shows), and the
device's components before the sliver merge equal ``layering._components`` of the host's
joins.  Scenes: the bench's, ``tests/layered_scenes.py``'s, slanted planes, sky, antialiased
(mixed-pixel) edges with slivers, more surfaces than the cap, a snake and a spiral, noise,
degenerate shapes, and invalid depth.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from clblur import layering
from clblur.layering import MAX_LAYERS

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

CAPS = (MAX_LAYERS, 2, 10 ** 6)


def check(depth: np.ndarray, caps=CAPS) -> None:
    """Labels equal to the host's for each cap, and the raw components equal too."""
    from clblur.opencl.labels import layer_labels, surface_components

    for cap in caps:
        want = layering.layer_labels(depth, cap)
        got = layer_labels(depth, cap)
        assert got.dtype == np.int32 and got.shape == depth.shape
        assert np.array_equal(got, want), f"labels differ at {int((got != want).sum())} px"
    w = layering._inverse_depth(depth)
    n, comp = layering._components(layering._continuous(w, 1), layering._continuous(w, 0))
    got_comp, got_n = surface_components(depth)
    assert got_n == n
    assert np.array_equal(got_comp, comp)


def bench_depth() -> np.ndarray:
    from bench_occlusion import speed_scene

    _, _, depth = speed_scene(pan=(16.0, 2.0))
    return depth


def slanted(h: int, w: int, a: float, bx: float, by: float) -> np.ndarray:
    """A plane: inverse depth affine in the image."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return 1.0 / (a + bx * xx + by * yy)


def antialiased(h: int, w: int, discs, background: np.ndarray, ss: int = 4) -> np.ndarray:
    """Discs (cx, cy, r, depth) over ``background`` rendered with ss x ss sub-pixels per
    pixel, each pixel the mean of its sub-pixels' depths: mixed pixels along every edge."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = np.broadcast_arrays(xx[:, :, None, None] + o[None, None, None, :],
                               yy[:, :, None, None] + o[None, None, :, None])
    z = np.broadcast_to(background[:, :, None, None], x.shape).copy()
    for cx, cy, r, d in discs:
        inside = (np.hypot(x - cx, y - cy) < r) & (d < z)
        z[inside] = d
    return z.mean(axis=(2, 3))


def test_bench_scene(opencl):
    depth = bench_depth()
    check(depth[153:558, 303:798])  # a view: rows not contiguous
    check(depth, caps=(MAX_LAYERS,))


def test_device_memory_path(opencl, monkeypatch, rng):
    """The path of a device with its own memory (a GPU), taken on any device: a view of rows
    sent in one rectangular copy, the uploads blocking."""
    from clblur.opencl import runtime
    from clblur.opencl.labels import _depth_buffer

    rt = runtime(None)
    monkeypatch.setattr(rt, "unified", False)
    depth = bench_depth()
    check(depth[153:558, 303:798], caps=(MAX_LAYERS,))
    check(rng.uniform(1.0, 3.0, (50, 70))[5:45:2, 3:60], caps=(MAX_LAYERS,))  # every 2nd row
    view = depth[10:50, 20:90].astype(np.float32)[:, 3:60]
    with rt.lock:
        buf = _depth_buffer(rt, view, rect=True)
        back = np.empty(view.shape, view.dtype)
        opencl.pyopencl_module().enqueue_copy(rt.queue, back, buf, is_blocking=True)
    assert np.array_equal(back, view)


def test_layered_scenes(opencl):
    from layered_scenes import scenes

    for scene in scenes().values():
        _, depth = scene.maps()
        check(depth)


def test_slanted_planes(opencl):
    h, w = 90, 120
    ground = slanted(h, w, 0.01, 0.0, 0.004)  # a ground plane, nearer downwards
    wall = slanted(h, w, 0.3, 0.002, -0.001)
    depth = ground.copy()
    depth[20:60, 30:80] = wall[20:60, 30:80]
    check(depth)
    check(slanted(h, w, 0.5, 0.01, 0.02))  # one plane: one surface


def test_sky(opencl, rng):
    h, w = 64, 80
    depth = slanted(h, w, 0.02, 0.0, 0.003)
    depth[:20] = np.inf
    depth[30:40, 10:30] = 5.0
    depth[5:10, 50:60] = 8.0  # an object in front of the sky
    depth[50, 70] = np.inf  # a single sky pixel inside the ground
    depth[rng.random((h, w)) < 0.02] = np.inf
    check(depth)
    check(np.full((6, 7), np.inf))


def test_antialiased_edges_and_slivers(opencl, rng):
    h, w = 96, 128
    background = slanted(h, w, 0.02, 0.0001, 0.0002)
    discs = [(40.0, 40.0, 18.0, 10.0), (70.0, 50.0, 15.0, 5.0), (100.0, 30.0, 9.0, 20.0),
             (100.0, 75.0, 12.5, 10.0), (20.0, 80.0, 6.0, 2.0)]
    check(antialiased(h, w, discs, background))
    for _ in range(3):
        discs = [(rng.uniform(0, w), rng.uniform(0, h), rng.uniform(2, 25),
                  rng.choice([2.0, 4.0, 10.0, 20.0])) for _ in range(8)]
        check(antialiased(h, w, discs, background))


def test_sliver_between_equal_depths(opencl, monkeypatch):
    """A sliver between two surfaces at one depth: their means are too close for the device's
    sums, so the component image is downloaded (the reference's means) and the exact tie is
    broken as the reference breaks it."""
    from clblur.opencl import labels

    depth = np.full((40, 50), 50.0)
    depth[5:30, 5:20] = 10.0
    depth[8:36, 21:45] = 10.0
    depth[:, 20] = 20.0  # one column between them: a sliver
    calls = []
    original = labels._download_comp
    monkeypatch.setattr(labels, "_download_comp",
                        lambda *a: calls.append(1) or original(*a))
    check(depth)
    assert calls, "the exact means were not taken"
    # an exact tie (w = 1/4 sums exactly): a row sliver under block A touches block C at its
    # end; A is reached through a down pair, C through a right pair, and the reference's loop
    # order (right pairs, then down) makes A the target
    depth = np.full((30, 40), 40.0)
    depth[2:12, 2:20] = 4.0  # A
    depth[12, 2:20] = 8.0  # the sliver
    depth[12:20, 20:30] = 4.0  # C (diagonal to A: not joined)
    calls.clear()
    check(depth)
    assert calls


def test_slivers_between_equal_depths_random(opencl, rng):
    """Slivers between two blocks at one depth (many sizes and depths): the device's and the
    reference's sums of equal values round differently, so without the tolerance of
    ``labels._merge_slivers`` the tie would be decided differently in some of these."""
    for _ in range(60):
        z = rng.choice([3.0, 7.0, 0.3, 1.1, 9.7, 13.0])
        h = int(rng.integers(20, 60))
        w1, w2 = (int(v) for v in rng.integers(3, 30, 2))
        depth = np.full((h, w1 + w2 + 1), 5 * z)
        depth[:, :w1] = z
        depth[:, w1 + 1:] = z
        depth[:, w1] = 2 * z  # the sliver
        depth[:rng.integers(1, h // 2), :] = 5 * z
        depth[rng.integers(h // 2, h):, w1 + 1:] = 5 * z
        check(depth, caps=(MAX_LAYERS, 10 ** 6))


def test_jumps_at_the_threshold(opencl, rng):
    """Neighbours whose inverse-depth jump lies within a few ulps of DEPTH_TAU * min(w) on
    either side: any other arithmetic (float32, a fused multiply-add, another tau) moves some
    of them across."""
    h, w = 48, 60
    depth = np.empty((h, w))
    for r in range(h):
        z0 = rng.uniform(1.0, 50.0)
        w0 = 1.0 / z0
        ideal = 1.0 / (w0 + layering.DEPTH_TAU * w0)
        z1 = ideal
        for _ in range(int(rng.integers(-4, 5))):
            z1 = np.nextafter(z1, np.inf if rng.random() < 0.5 else 0.0)
        block = np.arange(w) // 6 % 2 == 0
        depth[r] = np.where(block, z0, z1)
    joins = layering._continuous(layering._inverse_depth(depth), 1)
    assert joins.any() and not joins.all()  # both sides of the threshold occur
    check(depth)
    check(np.ascontiguousarray(depth.T))


def test_exact_means_path(opencl, monkeypatch, rng):
    """The reference's means taken for every sliver (no tolerance): the same labels."""
    from clblur.opencl import labels

    monkeypatch.setattr(labels, "_U", 1.0)
    h, w = 96, 128
    discs = [(rng.uniform(0, w), rng.uniform(0, h), rng.uniform(2, 25),
              rng.choice([2.0, 4.0, 10.0, 20.0])) for _ in range(8)]
    check(antialiased(h, w, discs, slanted(h, w, 0.02, 0.0001, 0.0002)))


def test_more_surfaces_than_the_cap(opencl):
    h, w = 80, 160
    depth = np.full((h, w), 200.0)
    for i in range(12):
        depth[10 + (i % 3) * 22: 28 + (i % 3) * 22, 5 + i * 12: 14 + i * 12] = 3.0 * 1.4 ** i
    check(depth)


def serpentine(h: int, w: int, width: int = 2, gap: int = 1) -> np.ndarray:
    """A snake of ``width`` px walking the rows (gap px apart) from left to right and back."""
    mask = np.zeros((h, w), bool)
    row, right = 0, True
    while row + width <= h:
        mask[row:row + width, :] = True
        nxt = row + width + gap
        if nxt + width <= h:  # the turn
            col = slice(w - width, w) if right else slice(0, width)
            mask[row + width:nxt, col] = True
        row, right = nxt, not right
    return mask


def spiral(n: int, width: int = 2, gap: int = 1) -> np.ndarray:
    """A square spiral: a stroke ``width`` px wide walked right, down, left, up, ... inwards,
    its arms ``gap`` px apart (legs n, n, n, then two each step shorter)."""
    mask = np.zeros((n, n), bool)
    step = width + gap
    r = c = 0
    legs = [n - width] * 3
    length = n - width - step
    while length > 0:
        legs += [length, length]
        length -= step
    for i, leg in enumerate(legs):
        dr, dc = ((0, 1), (1, 0), (0, -1), (-1, 0))[i % 4]
        for _ in range(leg + 1):
            mask[r:r + width, c:c + width] = True
            r, c = r + dr, c + dc
        r, c = r - dr, c - dc
    return mask


@pytest.mark.parametrize("shape", [(64, 200), (203, 61)])
def test_snake(opencl, shape):
    h, w = shape
    depth = np.where(serpentine(h, w), 5.0, 50.0)
    check(depth)
    check(np.where(serpentine(h, w, width=3, gap=2), 5.0, 50.0))
    # the snake as the far surface
    check(np.where(serpentine(h, w, width=2, gap=2), 50.0, 5.0))


def test_spiral(opencl):
    for n, width, gap in ((97, 2, 1), (120, 3, 2), (64, 2, 3)):
        depth = np.where(spiral(n, width, gap), 4.0, 40.0)
        check(depth)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # the host's median
def test_noise(opencl, rng):
    check(rng.uniform(1.0, 100.0, (64, 80)))  # nearly every pixel its own surface
    check(rng.choice([1.0, 2.0], (70, 90)))  # percolating clusters
    check(rng.choice([1.0, 1.5, 2.0, np.inf], (50, 60)))
    # smooth surfaces with noise below and above the threshold
    base = slanted(80, 100, 0.05, 0.0003, 0.0004)
    check(base * (1 + rng.normal(0, 0.01, base.shape)))
    check(base * (1 + rng.normal(0, 0.04, base.shape)))


def test_float32(opencl, rng):
    depth = bench_depth()[153:558, 303:798].astype(np.float32)
    check(depth)
    check(rng.uniform(1.0, 10.0, (30, 40)).astype(np.float32))


@pytest.mark.parametrize("shape", [(1, 37), (41, 1), (1, 1), (2, 2), (1, 5), (5, 1), (4, 4)])
def test_degenerate_shapes(opencl, rng, shape):
    for _ in range(4):
        depth = rng.choice([1.0, 2.0, 3.0, np.inf], shape)
        check(depth)
    check(np.full(shape, 7.0))


def test_large_tiles_and_seams(opencl, rng):
    """Surfaces crossing many union-find tiles and seams, sizes not multiples of a tile."""
    h, w = 131, 257
    depth = slanted(h, w, 0.02, 0.0, 0.0002)
    yy, xx = np.mgrid[0:h, 0:w]
    depth[(xx + yy) % 37 < 3] = 4.0  # diagonal stripes
    depth[(xx - 2 * yy) % 53 < 2] = 9.0
    check(depth)


def test_non_depth_orders_use_the_host(opencl, rng):
    from clblur.opencl.labels import layer_labels

    ids = rng.integers(0, 6, (20, 30))
    assert np.array_equal(layer_labels(ids), layering.layer_labels(ids))
    speed = -rng.uniform(0, 10, (20, 30))
    assert np.array_equal(layer_labels(speed, rule="speed"),
                          layering.layer_labels(speed, rule="speed"))
    row = rng.choice([1.0, 5.0], 40)
    assert np.array_equal(layer_labels(row), layering.layer_labels(row))


@pytest.mark.parametrize("bad", [np.nan, 0.0, -1.0, -np.inf])
def test_invalid_depth(opencl, bad):
    from clblur.opencl.labels import layer_labels

    depth = np.full((12, 14), 3.0)
    depth[4, 5] = bad
    depth[0, 0] = bad
    with pytest.raises(ValueError) as host:
        layering.layer_labels(depth)
    with pytest.raises(ValueError) as dev:
        layer_labels(depth)
    assert str(dev.value) == str(host.value)
