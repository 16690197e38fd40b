"""The virtual camera renders exactly the documented physics (clblur.camera docstring)."""

from __future__ import annotations

import numpy as np
import pytest

import clblur
from clblur.camera import Camera, accelerating_weights, random_scene, vignette
from clblur.pixels import quantise
from clblur.responses import Exp, Gamma, Linear


def test_static_capture_is_response_of_exposure_quantised(rng):
    scene = random_scene(rng, (24, 32), 3)
    cam = Camera(response=Exp(2.0))
    got = cam.capture(scene, 0.7)
    want = quantise(Exp(2.0).forward(scene * 0.7), np.uint8)
    np.testing.assert_array_equal(got, want)
    assert got.dtype == np.uint8 and got.shape == scene.shape


def test_one_response_per_channel_is_each_channel_through_its_own(rng):
    scene = random_scene(rng, (24, 32), 3)
    curves = (Exp(2.0), Gamma(2.2), Linear())
    got = Camera(response=curves).capture(scene, 0.7)
    for c, curve in enumerate(curves):
        np.testing.assert_array_equal(got[..., c], Camera(response=curve).capture(
            scene[..., c], 0.7))
    with pytest.raises(ValueError, match="3 responses for 1 channel"):
        Camera(response=curves).capture(scene[..., :1], 0.7)


def test_blurred_capture_is_the_papers_eq9_of_the_static_capture(rng):
    # exp camera, float output: averaging exposure then the response == clblur.blur with exp
    scene = random_scene(rng, (24, 32), 3, high=0.6)
    cam = Camera(response=Exp(3.0))
    static = cam.capture(scene, dtype=np.float64)
    blurred = cam.capture(scene, motion=(5.5, -2.0), dtype=np.float64)
    want = clblur.blur(static, (5.5, -2.0), Exp(3.0), backend="numpy")
    np.testing.assert_allclose(blurred, want, atol=1e-9)


def test_time_weights_and_anchor_reach_the_kernels(rng):
    scene = random_scene(rng, (16, 40), 1)
    cam = Camera(response=Linear())
    w = accelerating_weights(9, 3.0)
    got = cam.capture(scene, motion=(8.0, 0.0), weights=w, anchor="start", dtype=np.float64)
    want = clblur.blur(scene, (8.0, 0.0), "linear", weights=w, anchor="start",
                       backend="numpy")
    np.testing.assert_allclose(got, want, atol=1e-12)
    # a per-pixel flow field goes through the same kernels
    flow = np.zeros((16, 40, 2), np.float32)
    flow[..., 0] = 8.0
    field = cam.capture(scene, motion=flow, weights=w, anchor="start", dtype=np.float64)
    np.testing.assert_allclose(field, want, atol=1e-9)


def test_vignetting_is_cos4_fixed_to_the_sensor():
    flat = np.full((21, 31), 0.5)
    cam = Camera(response=Linear(), vignetting=0.6)
    got = cam.capture(flat, dtype=np.float64)
    v = vignette((21, 31), 0.6)
    np.testing.assert_allclose(got, 0.5 * v, atol=1e-12)
    assert v[10, 15] == pytest.approx(1.0)
    assert v[0, 0] == pytest.approx(1 / 1.6 ** 2)  # corner: r = R
    # a moving flat scene blurs to the same flat exposure: the falloff does not move
    np.testing.assert_allclose(cam.capture(flat, motion=(6.0, 0.0), dtype=np.float64),
                               0.5 * v, atol=1e-12)


def test_black_level_gain_and_channel_gains(rng):
    scene = random_scene(rng, (8, 8), 3, high=0.5)
    cam = Camera(response=Gamma(2.0), black_level=0.05, channel_gains=(1.2, 1.0, 0.8))
    got = cam.capture(scene, 1.0, gain=1.1, dtype=np.float64)
    y = scene * 1.1 * np.array([1.2, 1.0, 0.8])
    np.testing.assert_allclose(got, 0.05 + 0.95 * np.sqrt(y), atol=1e-12)
    np.testing.assert_allclose(cam.capture(np.zeros((4, 4, 3)), dtype=np.float64), 0.05)
    override = cam.capture(scene, channel_gains=(1.0, 1.0, 1.0), dtype=np.float64)
    np.testing.assert_allclose(override, 0.05 + 0.95 * np.sqrt(scene), atol=1e-12)
    # one black level per channel: each channel lifted by its own
    levels = np.array([0.02, 0.07, 0.045])
    per = Camera(response=Gamma(2.0), black_level=tuple(levels))
    np.testing.assert_allclose(per.capture(scene, dtype=np.float64),
                               levels + (1 - levels) * np.sqrt(scene), atol=1e-12)


def test_noise_variance_is_a_y_plus_b_and_clipped_pixels_are_unnoised():
    a, b = 2e-3, 1e-5
    cam = Camera(response=Linear(), noise_a=a, noise_b=b, full_well=True)
    rng = np.random.default_rng(7)
    for y in (0.05, 0.4):
        got = cam.capture(np.full((300, 300), y), rng=rng, dtype=np.float64)
        assert got.mean() == pytest.approx(y, rel=0.01)
        # the sample variance of 90000 values is within ~1.5 % of the truth (5 sigma)
        assert got.var() == pytest.approx(a * y + b, rel=0.05)
    clipped = cam.capture(np.full((10, 10), 1.5), rng=rng, dtype=np.float64)
    np.testing.assert_array_equal(clipped, 1.0)


def test_seeded_captures_are_deterministic():
    scene = random_scene(np.random.default_rng(3), (20, 20), 3)
    cam = Camera(noise_a=1e-3, noise_b=1e-6)
    one = cam.capture(scene, motion=(3.0, 1.0), rng=np.random.default_rng(11))
    two = cam.capture(scene, motion=(3.0, 1.0), rng=np.random.default_rng(11))
    np.testing.assert_array_equal(one, two)
    scene2 = random_scene(np.random.default_rng(3), (20, 20), 3)
    np.testing.assert_array_equal(scene, scene2)


def test_accelerating_weights_follow_one_over_speed():
    w = accelerating_weights(11, 4.0)
    assert w.sum() == pytest.approx(1.0)
    assert w[0] / w[-1] == pytest.approx(4.0)
    assert np.all(np.diff(w) < 0)
    assert np.all(np.diff(accelerating_weights(11, 0.5)) > 0)


def test_bad_input_is_named():
    cam = Camera(noise_a=1e-3)
    with pytest.raises(ValueError, match="rng"):
        cam.capture(np.ones((4, 4)))
    with pytest.raises(ValueError, match="radiance"):
        Camera().capture(-np.ones((4, 4)))
    with pytest.raises(TypeError, match="radiance"):
        Camera().capture([[1.0]])
    with pytest.raises(ValueError, match="channel gains"):
        Camera().capture(np.ones((4, 4, 3)), channel_gains=(1.0, 1.0))
    with pytest.raises(ValueError, match="black_level"):
        Camera(black_level=1.5)
    with pytest.raises(ValueError, match="black_level"):
        Camera(black_level=(0.1, -0.1, 0.0))
    with pytest.raises(ValueError, match="black levels for 3 channel"):
        Camera(black_level=(0.1, 0.1)).capture(np.ones((4, 4, 3)))
    with pytest.raises(ValueError, match="speed ratio"):
        accelerating_weights(5, -1.0)


def test_opencl_backend_renders_the_same_blur(opencl, rng):
    scene = random_scene(rng, (24, 32), 3)
    cam = Camera()
    ref = cam.capture(scene, motion=(7.0, 2.0), dtype=np.float64)
    got = cam.capture(scene, motion=(7.0, 2.0), dtype=np.float64, backend="opencl")
    np.testing.assert_allclose(got, ref, atol=1e-5)


def test_storage_truncation_offset_and_shift(rng):
    scene = random_scene(rng, (12, 16), 3, high=0.6)
    v = Exp(3.0).forward(scene)
    np.testing.assert_array_equal(Camera(storage="floor").capture(scene),
                                  np.floor(v * 255).astype(np.uint8))
    np.testing.assert_array_equal(Camera(code_offset=0.4).capture(scene),
                                  np.rint(v * 255 + 0.4).astype(np.uint8))
    # a whole-pixel shift moves the image: out(p) = in(p - s), edges clamped
    lin = Camera(response=Linear())
    got = lin.capture(scene, dtype=np.float64, shift=(1.0, 0.0))
    np.testing.assert_allclose(got[:, 1:], scene[:, :-1], atol=1e-12)
    half = lin.capture(scene, dtype=np.float64, shift=(0.0, 0.5))
    np.testing.assert_allclose(half[1:], 0.5 * (scene[1:] + scene[:-1]), atol=1e-12)
    with pytest.raises(ValueError, match="storage"):
        Camera(storage="ceil")
