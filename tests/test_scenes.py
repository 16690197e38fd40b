"""The sub-frame ground-truth renderer (clblur.scenes) and the depth-layer score against it."""

from __future__ import annotations

import inspect
import math

import numpy as np
import pytest

import clblur
from clblur import scenes
from clblur.scenes import Background, Disc, Rect, Scene, SceneObject, flat_texture, wave_texture


def _bg(seed: int = 1, velocity=(0.0, 0.0)) -> Background:
    return Background(wave_texture(seed, (0.2, 0.15, 0.1), 0.6), velocity=velocity)


def test_static_scene_exposure_is_the_sharp_frame():
    sc = Scene(64, 48, _bg(), (SceneObject(Rect(20, 12), wave_texture(2, (0.5, 0.4, 0.3)),
                                           (30.0, 20.0), depth=1.0, angle=0.4),))
    r = scenes.render(sc, samples=64)
    np.testing.assert_allclose(r.exposure, r.sharp_linear, rtol=0, atol=1e-12)
    assert np.array_equal(r.image, r.sharp)
    assert not r.flow.any() and not r.hidden.any()
    bg = r.alpha == 0  # the clean plate is the sharp frame wherever no object is
    assert np.array_equal(r.plate[bg], r.sharp[bg]) and not np.array_equal(r.plate, r.sharp)
    # the swept region of a still object is the object itself
    assert np.array_equal(r.swept, r.alpha > 0)


def test_uniform_pan_equals_clblur_uniform_blur():
    """A full-frame texture moving uniformly: the truth is clblur's uniform blur (inside the
    frame, away from the edges where the truth sees content entering from outside)."""
    v = (13.0, -6.0)
    sc = Scene(96, 64, _bg(3, velocity=v))
    r = scenes.render(sc, "srgb", samples=64)
    assert r.swept.all()
    np.testing.assert_array_equal(r.flow[..., 0], v[0])
    got = clblur.blur(r.sharp, v, "srgb", backend="numpy")
    m = int(math.ceil(max(abs(v[0]), abs(v[1])) / 2)) + 2
    inner = (slice(m, -m), slice(m, -m))
    diff = np.abs(got[inner].astype(int) - r.image[inner])
    assert diff.max() <= 2
    assert scenes.psnr(got[inner], r.image[inner]) > 48
    # and the blur is really there: the sharp frame is far from the truth
    assert scenes.psnr(r.sharp[inner], r.image[inner]) < 40


def test_time_average_matches_analytic_coverage():
    """A flat disc crossing a black floor: on its centre row, the covered fraction of the
    shutter is the overlap of [x - r, x + r] with the centre's path, within 1 / K."""
    r_, v, cx, cy, k = 6.0, 30.0, 40.0, 20.0, 64
    sc = Scene(80, 40, Background(flat_texture((0.0, 0.0, 0.0))),
               (SceneObject(Disc(r_), flat_texture((0.5, 0.5, 0.5)), (cx, cy), (v, 0.0)),))
    r = scenes.render(sc, "linear", np.float64, samples=k, spp=1)
    x = np.arange(80, dtype=np.float64)
    lo = np.clip((x - r_ - cx) / v, -0.5, 0.5)
    hi = np.clip((x + r_ - cx) / v, -0.5, 0.5)
    expect = np.maximum(hi - lo, 0)
    np.testing.assert_allclose(r.exposure_alpha[int(cy)], expect, atol=1.0 / k + 1e-6)
    np.testing.assert_allclose(r.exposure[int(cy), :, 0], 0.5 * r.exposure_alpha[int(cy)],
                               atol=1e-6)


def test_depth_order_ids_alpha_and_ties():
    red, blue = flat_texture((0.6, 0.0, 0.0)), flat_texture((0.0, 0.0, 0.6))
    a = SceneObject(Disc(10), red, (30.0, 24.0), depth=2.0)
    b = SceneObject(Disc(10), blue, (38.0, 24.0), depth=1.0)
    r = scenes.render(Scene(64, 48, _bg(), (a, b)), "linear", np.float64)
    assert r.ids[24, 34] == 2 and r.depth[24, 34] == 1.0 and r.sharp[24, 34, 2] == 0.6
    near_red = SceneObject(Disc(10), red, (30.0, 24.0), depth=0.5)
    r2 = scenes.render(Scene(64, 48, _bg(), (near_red, b)), "linear", np.float64)
    assert r2.ids[24, 34] == 1 and r2.sharp[24, 34, 0] == 0.6
    tie = SceneObject(Disc(10), red, (30.0, 24.0), depth=1.0)
    r3 = scenes.render(Scene(64, 48, _bg(), (tie, b)), "linear", np.float64)
    assert r3.ids[24, 34] == 2  # equal depth: the later object is in front
    assert r.depth[0, 0] == 1000.0 and r.ids[0, 0] == 0
    lone = scenes.render(Scene(64, 48, _bg(), (a,)), "linear", np.float64, spp=4)
    assert abs(lone.alpha.sum() - math.pi * 100) < 0.02 * math.pi * 100


def test_rotation_vectors_are_exposure_chords():
    """A rectangle spinning in place by w over the exposure: every covered pixel moves along a
    chord perpendicular to its radius, of length 2 r sin(w / 2); halves add up."""
    w = 0.5
    sc = Scene(64, 64, _bg(), (SceneObject(Rect(40, 20), wave_texture(5, (0.4, 0.4, 0.4)),
                                           (32.0, 32.0), spin=w),))
    r = scenes.render(sc, samples=64)
    yy, xx = np.nonzero(r.ids == 1)
    rad = np.stack([xx - 32.0, yy - 32.0], axis=-1)
    f = r.flow[yy, xx].astype(np.float64)
    np.testing.assert_allclose(np.hypot(*f.T), 2 * np.hypot(*rad.T) * math.sin(w / 2),
                               atol=1e-4)
    np.testing.assert_allclose((f * rad).sum(axis=1), 0, atol=1e-3)
    # positive spin turns +x towards +y (clockwise on screen): right of centre moves down
    assert r.flow[32, 50, 1] > 0
    np.testing.assert_allclose(r.flow_first + r.flow_second, r.flow, atol=1e-4)


def test_hidden_light_is_confined_to_the_swept_region():
    sc = scenes.example_scenes(120, 80)["disc"]
    r = scenes.render(sc, samples=64)
    assert not r.hidden[~r.swept].any()
    # 12 px right of the disc's centre (radius 18, 36 px over the shutter): background for
    # t < -1/6, and the disc hides that background at t = 0 -> a third of the light is hidden
    assert r.hidden[40, 72] == pytest.approx(1 / 3, abs=0.05)
    assert r.hidden[40, 60] == 0  # always on the disc, whose texture the frame shows
    assert 0 < r.swept.mean() < 0.5


def test_psnr_mask_and_errors():
    a = np.zeros((4, 4, 3), np.uint8)
    b = a.copy()
    b[0, 0] = 10
    m = np.zeros((4, 4), bool)
    m[0, 0] = True
    assert scenes.psnr(a, b, m) == pytest.approx(10 * math.log10(255 ** 2 / 100))
    assert scenes.psnr(a, b, ~m) == float("inf")
    with pytest.raises(ValueError):
        scenes.psnr(a, b, np.zeros((4, 4), bool))
    with pytest.raises(ValueError):
        scenes.render(Scene(8, 8, _bg()), samples=1)


needs_depth = pytest.mark.skipif("depth" not in inspect.signature(clblur.blur).parameters,
                                 reason="clblur.blur does not take depth= yet (occlusion branch)")


@needs_depth
def test_depth_layers_score_on_a_crossing_with_the_fast_object_behind():
    """Two discs cross during the shutter, the fast one behind: the depth-ordered blur must
    beat the gather clearly over the swept region and where the sharp frame shows the light;
    with no occlusion (a pan) it must not lose more than 0.1 dB to the gather
    (docs/studies/occlusion.md, scaled-down scenes)."""
    sc = scenes.example_scenes(120, 80)
    r = scenes.render(sc["crossing_fast_behind"], "srgb", samples=64)
    gather = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy")
    depth = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth=r.depth)
    visible = r.swept & (r.hidden < 0.01)
    g, d = scenes.psnr(gather, r.image, r.swept), scenes.psnr(depth, r.image, r.swept)
    assert d > g + 3.0, (d, g)
    assert scenes.psnr(depth, r.image, visible) > scenes.psnr(gather, r.image, visible) + 3.0
    pan = scenes.render(sc["pan"], "srgb", samples=64)
    g = scenes.psnr(clblur.blur(pan.sharp, pan.flow, "srgb", backend="numpy"), pan.image)
    d = scenes.psnr(clblur.blur(pan.sharp, pan.flow, "srgb", backend="numpy", depth=pan.depth),
                    pan.image)
    assert d >= g - 0.1, (d, g)


def _rank(depth: np.ndarray) -> np.ndarray:
    """Depth -> integer layer IDs (0 = nearest), one per distinct depth."""
    return np.unique(depth, return_inverse=True)[1].reshape(depth.shape).astype(np.int32)


@needs_depth
def test_layer_ids_put_the_fast_object_behind_where_speed_cannot():
    """With the fast disc behind, ordering by speed paints it in front; the true order (the
    renderer's depth as layer IDs) must score clearly better over the swept region."""
    r = scenes.render(scenes.example_scenes(120, 80)["crossing_fast_behind"], "srgb", samples=64)
    by_speed = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth="speed")
    by_ids = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth=_rank(r.depth))
    s, i = scenes.psnr(by_speed, r.image, r.swept), scenes.psnr(by_ids, r.image, r.swept)
    assert i > s + 5.0, (i, s)


@needs_depth
@pytest.mark.parametrize("name", ["crossing_fast_front", "crossing_fast_behind"])
def test_float_depth_orders_near_objects_in_front_of_a_far_background(name):
    """A renderer's Z pass: objects at depth 1 and 2 over a background at 1000 (a layering by
    gaps in the global depth range merged the two discs).  The float depth must order them as
    their ranks do, also where the far disc shows as a sliver between the near one and the
    background (fast behind)."""
    r = scenes.render(scenes.example_scenes(120, 80)[name], "srgb", samples=64)
    by_depth = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth=r.depth)
    by_ids = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth=_rank(r.depth))
    assert scenes.psnr(by_depth, r.image, r.swept) > scenes.psnr(by_ids, r.image, r.swept) - 0.5
