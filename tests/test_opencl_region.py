"""The device region mask (``clblur/opencl/region.py``) against
``clblur.layered_exposure.region_mask``.

Expected: the same mask, except at pixels where the reference's inverse departure lies within
``spread / 32`` of ``spread`` (the reference reads the vectors with ``cv2.remap``, which rounds
positions to 1/32 px, the device bilinearly in float; ``clblur/opencl/region.py``
Conventions).  Each mismatch is therefore checked to be in a flagged tile (the tiles match
exactly), away from every motion edge (``near`` matches exactly), on a pixel whose vectors
vary, and with the reference's departure that close to ``spread``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from layered_scenes import scenes

from clblur.halo import reach
from clblur.layer_planes import distance_to
from clblur.layered_exposure import (
    SPREAD_PX,
    TILE,
    _inverse_departure,
    boundary_mask,
    region_mask,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_occlusion import speed_scene  # noqa: E402

ANCHORS = (0.0, 0.5, 1.0)


def margin(spread: float) -> float:
    """How far from ``spread`` a mismatching pixel's departure may lie: positions rounded to
    1/32 px (at most 1/64 per axis) on vectors whose neighbours differ by at most ``spread``
    move a bilinear read by at most ``spread / 32``, times ``|t| <= 1``; plus float32
    rounding."""
    return spread / 32 + 1e-4


def edges(v: np.ndarray, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """(edge, varies) of the whole image, as the reference forms them on its crop."""
    from scipy.ndimage import maximum_filter, minimum_filter

    edge = np.zeros(v.shape[:2], bool)
    varies = np.zeros(v.shape[:2], bool)
    for c in range(2):
        comp = v[..., c]
        s = (maximum_filter(comp, size=3, mode="nearest")
             - minimum_filter(comp, size=3, mode="nearest"))
        edge |= s > np.float32(spread)
        varies |= s > 0
    return edge, varies


def check(v: np.ndarray, anchor: float, tile: int = TILE, spread: float = SPREAD_PX) -> int:
    """Compare the device's mask with the reference's; every mismatch must be explained (the
    module docstring).  The device's mask must not depend on its pixels per work-item (the
    GPU's 1, the CPU's ``CPU_RUN``, and one that divides neither the width nor the tile).
    Returns the number of mismatches."""
    from clblur.opencl.region import CPU_RUN
    from clblur.opencl.region import region_mask as device_mask

    v = np.ascontiguousarray(v, np.float32)
    want = region_mask(v, anchor, tile, spread)
    got = device_mask(v, anchor, tile, spread)
    assert got.shape == want.shape and got.dtype == bool
    for run in (1, 5, CPU_RUN):
        assert np.array_equal(device_mask(v, anchor, tile, spread, run=run), got)
    bad = np.nonzero(got != want)
    if not bad[0].size:
        return 0
    r = reach(v, anchor)
    assert boundary_mask(v, anchor, tile, spread)[bad].all(), "a mismatch outside the tiles"
    edge, varies = edges(v, spread)
    assert varies[bad].all(), "a mismatch where the vectors do not vary"
    near = distance_to(edge, bad) <= r + 2.0 if edge.any() else np.zeros(bad[0].size, bool)
    assert not near.any(), "a mismatch near a motion edge"
    departure = _inverse_departure(v, anchor, bad).astype(np.float64)
    # the host's departure decides the host's bit: it must lie on the host's side of spread
    assert np.array_equal(departure > np.float32(spread), want[bad])
    off = np.abs(departure - spread)
    assert off.max() <= margin(spread), (
        f"{bad[0].size} mismatches, departure up to {off.max():.4f} px from spread")
    return bad[0].size


def turning(h: int, w: int, omega: float, centre=None, move=(0.0, 0.0),
            scale: float = 0.0) -> np.ndarray:
    """A field turning by ``omega`` (rad over the shutter) about ``centre``, stretching by
    ``scale`` and translating by ``move``."""
    cy, cx = centre if centre is not None else ((h - 1) / 2, (w - 1) / 2)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    dx, dy = xx - cx, yy - cy
    c, s = math.cos(omega), math.sin(omega)
    vx = (c - 1) * dx - s * dy + scale * dx + move[0]
    vy = s * dx + (c - 1) * dy + scale * dy + move[1]
    return np.stack([vx, vy], axis=2).astype(np.float32)


@pytest.mark.parametrize("pan", [(16.0, 2.0), (0.0, 0.0)])
@pytest.mark.parametrize("anchor", ANCHORS)
def test_bench_scene(opencl, pan, anchor):
    _, flow, _ = speed_scene(pan=pan)
    check(flow, anchor)


@pytest.mark.parametrize("name", sorted(scenes()))
@pytest.mark.parametrize("anchor", ANCHORS)
def test_layered_scenes(opencl, name, anchor):
    flow, _ = scenes()[name].maps()
    check(flow, anchor)


@pytest.mark.parametrize("anchor", ANCHORS)
def test_zero_and_uniform(opencl, anchor):
    from clblur.opencl.region import region_mask as device_mask

    for v in (np.zeros((70, 90, 2), np.float32), np.full((70, 90, 2), (13.5, -4.25), np.float32)):
        assert not device_mask(v, anchor).any()
        assert check(v, anchor) == 0


@pytest.mark.parametrize("anchor", ANCHORS)
def test_turning(opencl, anchor):
    """A turning and stretching body (no motion edges: its departure decides), with a disc
    moving across it (motion edges: ``near``)."""
    mismatches = pixels = 0
    for omega, scale, move in ((0.1, 0.0, (1.0, 0.0)), (-0.2, 0.03, (2.0, -1.0)),
                               (0.03, -0.1, (0.0, 0.0))):
        v = turning(150, 230, omega, move=move, scale=scale)
        mismatches += check(v, anchor)
        yy, xx = np.mgrid[0:150, 0:230]
        v[np.hypot(xx - 60, yy - 50) < 25] = (-18.0, 4.0)
        mismatches += check(v, anchor)
        mask = region_mask(v, anchor)
        assert mask.any() and not mask.all()  # the cases are not trivial
        pixels += 2 * mask.size
    assert mismatches < 0.002 * pixels  # a thin band where the departure crosses spread


@pytest.mark.parametrize("anchor", ANCHORS)
def test_one_component_varies(opencl, anchor):
    """A body stretching along y only (x constant) and its transpose: ``varies`` and the
    departure must look at each component."""
    yy = np.arange(150, dtype=np.float32)[:, None] - np.float32(74.5)
    v = np.zeros((150, 120, 2), np.float32)
    v[..., 0] = 3.0
    v[..., 1] = np.float32(0.2) * yy
    for field in (v, v.transpose(1, 0, 2)[..., ::-1]):
        check(field, anchor)
        if anchor != 0.5:  # at 0.5 the departure stays below spread
            assert region_mask(field, anchor).any()


def test_random_fields(opencl, rng):
    """Smooth random fields with noise and steps: departures near spread everywhere."""
    import cv2

    for k in range(4):
        h, w = int(rng.integers(40, 160)), int(rng.integers(40, 160))
        coarse = rng.normal(scale=8.0, size=(h // 16 + 2, w // 16 + 2, 2)).astype(np.float32)
        v = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        v += rng.normal(scale=0.1 * k, size=v.shape).astype(np.float32)
        if k % 2:
            v[h // 3:, : w // 2] += np.float32(5.0)
        for anchor in (0.0, float(rng.random()), 1.0):
            check(v, anchor)


def test_parameters(opencl):
    """Other tile sizes and spreads."""
    flow, _ = scenes()["crossing-faster-behind"].maps()
    rot = turning(90, 120, 0.3)
    for tile, spread in ((8, 0.5), (5, 2.0), (1, 1.0), (32, 0.25)):
        check(flow, 0.5, tile, spread)
        check(rot, 0.3, tile, spread)


def test_spread_is_strict(opencl):
    """A step of exactly ``spread`` flags nothing; one a float32 ulp larger does."""
    from clblur.opencl.region import region_mask as device_mask

    v = np.zeros((48, 64, 2), np.float32)
    v[:, 32:, 0] = np.float32(SPREAD_PX)
    assert not device_mask(v, 0.5).any() and not region_mask(v, 0.5).any()
    v[:, 32:, 0] = np.nextafter(np.float32(SPREAD_PX), np.float32(2))
    assert device_mask(v, 0.5).any()
    assert check(v, 0.5) == 0
    # in a tile flagged by a larger step 12 px away (beyond R + 2), a step of exactly
    # spread is no motion edge: the pixels around it stay out
    v[:, 32:, 0] = np.float32(SPREAD_PX)
    v[:, 44:, 0] = np.float32(2.5)
    want = region_mask(v, 0.5)
    assert boundary_mask(v, 0.5)[:, 28:36].all() and not want[:, 28:36].any()
    assert check(v, 0.5) == 0


def test_near_bound(opencl):
    """Reaches whose ``R + 2`` falls just short of and just past ``sqrt(k)`` for an integer
    ``k`` that is a squared distance from a corner of an edge rectangle: the two give other
    masks, and the device's matches the reference's in each."""
    from clblur.opencl.region import near_limit

    for k in (13, 25, 50, 101):
        guess = np.float32((math.sqrt(k) - 2.0) / (1 + 1e-6))
        candidates = [guess]
        for _ in range(8):
            candidates = [np.nextafter(candidates[0], np.float32(0)), *candidates,
                          np.nextafter(candidates[-1], np.float32(99))]
        masks = []
        for past in (False, True):
            fits = [c for c in candidates
                    if (reach(np.array([[[c, 0]]], np.float32), 1.0) + 2.0 >= math.sqrt(k))
                    == past]
            longest = max(fits) if not past else min(fits)
            v = np.zeros((60, 80, 2), np.float32)
            v[20:40, 40:, 0] = longest
            assert near_limit(reach(v, 1.0)) == (k if past else k - 1)
            assert check(v, 1.0) == 0
            masks.append(region_mask(v, 1.0))
        assert (masks[0] != masks[1]).any()


def test_tiny_and_narrow(opencl):
    v = np.zeros((5, 7, 2), np.float32)
    v[2:, 3:] = (4.0, -2.0)
    for anchor in ANCHORS:
        assert check(v, anchor) == 0
    narrow = turning(50, 9, 0.3, move=(3.0, 1.0))
    narrow[20:30, 4:] = (-6.0, 0.0)
    for anchor in ANCHORS:
        check(narrow, anchor)
        check(narrow[:, :1], anchor)
        check(narrow[:1], anchor)


def test_empty_and_bad_shapes(opencl):
    from clblur.opencl.region import region_mask as device_mask

    assert device_mask(np.zeros((0, 4, 2), np.float32), 0.5).shape == (0, 4)
    with pytest.raises(ValueError):
        device_mask(np.zeros((4, 4), np.float32), 0.5)
    with pytest.raises(ValueError):
        device_mask(np.zeros((4, 4, 2), np.float32), 0.5, tile=0)
    with pytest.raises(ValueError):
        device_mask(np.zeros((4, 4, 2), np.float32), 0.5, run=0)


def test_region_and_reach_gives_the_hosts_reach(opencl):
    """The reach found on the way is clblur.halo.reach bit for bit (prepare takes it)."""
    from clblur.opencl.region import region_and_reach
    from clblur.opencl.region import region_mask as device_mask

    rng = np.random.default_rng(7)
    for shape, anchor in (((37, 53), 0.5), ((64, 130), 0.0), ((9, 5), 1.0)):
        v = (rng.standard_normal(shape + (2,)) * 9).astype(np.float32)
        mask, r = region_and_reach(v, anchor)
        assert r == reach(v, anchor)
        np.testing.assert_array_equal(mask, device_mask(v, anchor))
