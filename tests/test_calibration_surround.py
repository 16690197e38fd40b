"""Calibration's check for local tone mapping (``clblur.calibration.surround``): a bracket
whose codes depend on each region's brightness is reported, plain brackets (noisy, JPEG,
misregistered, or fitted with a wrong curve) are not."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from bracket_scenes import exposure, objects_scene
from scipy import ndimage

from clblur.calibration import ExposureSeries
from clblur.calibration.compare import calibrate
from clblur.calibration.report import write_report
from clblur.calibration.surround import SURROUND_SCALE, describe, surround_codes
from clblur.camera import local_tone


def bracket(seed: int, strength: float = 0.0, noise: float = 0.004, jpeg: int = 0,
            shift: float = 0.0, sharpen: float = 0.0, bits: int = 8,
            tone_sigma: float = 10.0, edge_aware: bool = False, texture: float = 0.0,
            h: int = 240, w: int = 320) -> ExposureSeries:
    """Five exposures one stop apart of ``objects_scene``, gamma-2.2 codes; ``strength``:
    local tone mapping (``camera.local_tone``, surround blurred by ``tone_sigma`` px;
    ``edge_aware``: its surround a bilateral filter of the log light instead, which stops at
    edges, as cameras' halo-free tone mapping does); ``texture``: the light times
    ``exp(texture n)``, ``n`` unit noise blurred by 1.5 px (a fine texture on every object);
    ``jpeg``: stored
    at that quality; ``shift``: each frame's light moved by up to that many pixels;
    ``sharpen``: an unsharp mask of that amount (sigma 1.5 px) on the codes, as a camera's
    JPEG engine sharpens; ``bits``: 16 for uint16 codes (noise ``noise / 2``)."""
    rng = np.random.default_rng(seed)
    radiance = objects_scene(h, w, seed)
    if texture:
        n = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 1.5)
        radiance = radiance * np.exp(texture * n / n.std())[..., None]
    times = 2.0 ** np.arange(5) / 8.0
    images = []
    for t in times:
        light = radiance * t
        if strength and edge_aware:
            level = np.log(np.maximum(light.mean(axis=2), 1e-6)).astype(np.float32)
            surround = cv2.bilateralFilter(level, -1, 0.7, tone_sigma)
            light = light * np.exp(strength * np.tanh(np.log(0.18) - surround))[..., None]
        elif strength:
            light = local_tone(light, strength, tone_sigma)
        if shift:
            dy, dx = rng.uniform(-shift, shift, 2)
            light = ndimage.shift(light, (dy, dx, 0), order=1, mode="nearest")
        if bits == 16:
            v = np.clip(light, 0, 1) ** (1 / 2.2) + rng.normal(0, noise / 2, light.shape)
            images.append(np.clip(np.rint(v * 65535), 0, 65535).astype(np.uint16))
            continue
        im = exposure(light, 1.0, rng, noise=noise)
        if sharpen:
            f = im.astype(np.float32)
            f += sharpen * (f - cv2.GaussianBlur(f, (0, 0), 1.5))
            im = np.clip(np.rint(f), 0, 255).astype(np.uint8)
        if jpeg:
            im = cv2.imdecode(cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, jpeg])[1],
                              cv2.IMREAD_UNCHANGED)
        images.append(im)
    return ExposureSeries.create(images, times)


@pytest.mark.parametrize("seed", [1, 2])
def test_local_tone_mapping_is_reported(seed, tmp_path):
    cal = calibrate(bracket(seed, strength=0.3), ["gamma-offset"])
    r = cal.surround
    assert r["dependent"], describe(r)
    assert r["statistic"] > 4 and r["offset_codes"] > 0.6
    # where: the largest offsets beyond the code's own are codes wide, in a named surround
    top = r["largest"][0]
    assert abs(top["offset_codes"]) > 1.5 and top["surround_codes"][1] > top["surround_codes"][0]
    text = describe(r)
    assert "DEPENDS" in text and "local tone mapping" in text
    report = write_report(tmp_path / "rep", cal.series, cal.fits, cal.evaluations, cal.best)
    assert "## Does the error depend on the surround?" in report.read_text()
    assert "Auto Lighting Optimizer" in report.read_text()


@pytest.mark.parametrize("case", [
    {"model": "gamma-offset"},
    {"model": "gamma-offset", "noise": 0.016},  # high ISO: few pixels are flat in codes
    {"model": "gamma-offset", "jpeg": 85},
    {"model": "gamma-offset", "shift": 0.5},  # a registration left half a pixel off
    {"model": "gamma-offset", "sharpen": 1.0},  # halos in codes, at the edges' scale
    {"model": "exp"},  # a curve that cannot fit: its error depends on the code, not the surround
])
@pytest.mark.parametrize("seed", [1, 2])
def test_a_bracket_without_local_tone_mapping_is_not_reported(case, seed):
    opts = {k: v for k, v in case.items() if k != "model"}
    cal = calibrate(bracket(seed, **opts), [case["model"]])
    r = cal.surround
    assert not r["dependent"], describe(r)
    assert r["tested"] and r["contrast_values"] > 20_000  # looked, noisy or not
    assert r["offset_codes"] < 0.25
    assert "DEPENDS" not in describe(r)


@pytest.mark.parametrize("strength", [0.0, 0.3])
def test_a_16_bit_bracket_is_judged_in_its_own_codes(strength):
    r = calibrate(bracket(1, strength=strength, bits=16), ["gamma-offset"]).surround
    assert r["min_offset_codes"] == pytest.approx(0.5 * 257)
    assert r["dependent"] == bool(strength), describe(r)
    if strength:  # the same lift as in 8 bits, in 16-bit codes
        assert r["offset_codes"] > 0.6 * 257 and r["largest"][0]["codes"][1] > 256


def test_a_scene_whose_codes_all_share_one_surround_is_not_tested():
    """A fine texture averages to one surround everywhere: no code is seen in two surrounds,
    so the check cannot tell and says so rather than "no dependence"."""
    rng = np.random.default_rng(0)
    light = cv2.GaussianBlur(np.exp(rng.normal(0, 1, (240, 320))), (0, 0), 3) / 3
    times = [0.25, 0.5, 1.0]
    images = [np.clip(np.rint(np.clip(light * t, 0, 1) ** (1 / 2.2) * 255
                              + rng.normal(0, 1, light.shape)), 0, 255).astype(np.uint8)
              for t in times]
    r = calibrate(ExposureSeries.create(images, times), ["gamma-offset"]).surround
    assert not r["tested"] and not r["dependent"] and r["values"] > 50_000
    assert describe(r, 1).startswith("Surround: not tested. Only 0 flat held-out values")


def test_a_significant_trace_below_the_least_offset_is_named_a_trace():
    r = {"tested": True, "dependent": False, "statistic": 3.3, "p_value": 6e-4, "alpha": 1e-3,
         "offset_codes": 0.06, "min_offset_codes": 0.5, "values": 18_000_000, "blocks": 144,
         "pairs": 27, "largest": []}
    assert describe(r).startswith("Surround: a trace only.")
    r.update(p_value=0.01, statistic=2.3)
    assert describe(r).startswith("Surround: no dependence.")


def test_surround_codes_reduced_for_a_wide_sigma_match_the_exact_gaussian():
    rng = np.random.default_rng(3)
    h, w = 1200, 1600  # sigma 62.5 px: blurred on a copy reduced 7 times
    small = rng.uniform(0, 255, (h // 40, w // 40, 3)).astype(np.float32)
    image = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)  # hard-edged blocks
    got = surround_codes(image)
    exact = cv2.GaussianBlur(image.mean(axis=2), (0, 0), SURROUND_SCALE * math.hypot(h, w),
                             borderType=cv2.BORDER_REFLECT)
    assert got.shape == (h, w)
    assert np.abs(got - exact).max() < 1.0  # codes of 255, against contrast of 255
