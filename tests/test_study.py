"""The study finds effects hidden by the virtual camera, and nothing in null data."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

import clblur
from clblur.camera import Camera, random_scene
from clblur.io import write_image
from clblur.manifest import write_manifest
from clblur.study import EFFECT_NAMES, pair_group, study, study_groups
from clblur.study.model import forward, inverse_table, null_params, predict
from clblur.study.synthetic import RANGES, null_stack, scenario

REPORT_KEYS = {"kind", "baseline", "findings", "extended", "gain"}
FINDING_KEYS = {"effect", "significant", "statistic", "p_value", "estimate", "explanation"}
# the extended model must cut the held-out RMSE at least this much (noise: the held-out NLL)
MARGIN = 0.5


def test_model_at_null_is_the_papers_blur(rng):
    # the code-histogram model at null parameters equals the reference kernels (Eq. 9, exp)
    scene = random_scene(rng, (30, 40), 3, high=0.5)
    static = Camera().capture(scene)
    assert static.max() < 255
    g = pair_group(static, static, (6.5, 2.0))
    pred, var = predict(g, null_params())
    ref = clblur.blur(static.astype(np.float64) / 255.0, (6.5, 2.0), "exp", backend="numpy")
    np.testing.assert_allclose(pred, 255.0 * ref[g.rows, g.cols], atol=1e-6)
    assert np.all(var >= 1.0 / 12.0)


def test_response_family_contains_exp_and_power_law():
    v = np.arange(255) / 255.0
    np.testing.assert_allclose(inverse_table(null_params())[:255], -np.log1p(-v), atol=1e-12)
    p = {**null_params(), "gamma": 2.2, "rho": 1e-3}
    np.testing.assert_allclose(inverse_table(p)[:255], v ** 2.2, atol=2e-3)
    x = np.linspace(0.01, 3, 50)
    back, _ = forward(np.power(-np.log1p(-0.5 * (1 - np.exp(-x))) / 0.5, 1.7), 1.7, 0.5)
    np.testing.assert_allclose(back, 1 - np.exp(-x), atol=1e-12)


@pytest.mark.parametrize("effect", EFFECT_NAMES)
def test_hidden_effect_is_ranked_first_and_significant(effect):
    rng = np.random.default_rng(1000 + EFFECT_NAMES.index(effect))
    sc = scenario({effect: None}, rng)
    r = study_groups(sc.kind, sc.groups).report
    top = r["findings"][0]
    assert top["effect"] == effect, (sc.truth, r["findings"][:2])
    assert top["significant"] and top["p_value"] < 0.05 / len(EFFECT_NAMES)
    if effect == "noise":
        assert r["extended"]["heldout_nll"] < MARGIN * r["baseline"]["heldout_nll"]
    else:
        assert r["extended"]["heldout_rmse"] < MARGIN * r["baseline"]["heldout_rmse"]
        assert r["gain"] > 0
    _check_estimate(effect, top["estimate"], sc.truth[effect])


def _check_estimate(effect: str, est: dict, truth: float) -> None:
    """Fitted magnitudes in the units of ``synthetic.RANGES``, where the family is exact."""
    if effect == "black_level":
        assert est["black_level_codes"] == pytest.approx(255 * truth, abs=1.0)
    elif effect == "response_shape":
        assert est["gamma"] == pytest.approx(truth, abs=0.1)
    elif effect == "vignetting":
        assert est["c"] == pytest.approx(truth, abs=0.05)
    elif effect == "exposure_gain":
        assert abs(np.log(est["gain"])) == pytest.approx(truth, abs=0.01)
    elif effect == "channel_gain":
        assert abs(np.log(est["gains"][0])) == pytest.approx(truth, abs=0.01)
    elif effect == "saturation":  # one factor for all clipped pixels: a lower bound
        assert 1.0 < est["factor"] <= truth * 1.05


def test_null_data_give_no_finding_on_95_percent_of_seeds():
    seeds = range(20)
    false = []
    for s in seeds:
        sc = scenario({}, np.random.default_rng(5000 + s), shape=(24, 40))
        r = study_groups(sc.kind, sc.groups).report
        if any(f["significant"] for f in r["findings"]):
            false.append(s)
    assert len(false) <= 1, f"false findings on seeds {false}"


@pytest.mark.parametrize("pair", [("response_shape", "noise"),
                                  ("saturation", "channel_gain")])
def test_pairs_of_effects_are_both_found(pair):
    rng = np.random.default_rng(20 + len(pair[0]))
    sc = scenario({e: None for e in pair}, rng)
    r = study_groups(sc.kind, sc.groups).report
    assert set(pair) <= set(r["extended"]["effects"]), (sc.truth, r["extended"]["effects"])
    assert r["findings"][0]["effect"] in pair


def test_frame_stack_null_and_response():
    null = study_groups("frame-stack", null_stack(np.random.default_rng(3)).groups).report
    assert not any(f["significant"] for f in null["findings"])
    sc = null_stack(np.random.default_rng(4), gamma=2.2)
    r = study_groups("frame-stack", sc.groups).report
    assert r["findings"][0]["effect"] == "response_shape"
    assert r["findings"][0]["estimate"]["gamma"] == pytest.approx(2.2, abs=0.2)


def test_report_keys_and_untestable_effects_are_listed():
    sc = scenario({}, np.random.default_rng(9), shape=(32, 48))
    r = study_groups(sc.kind, sc.groups).report
    assert set(r) == REPORT_KEYS
    assert {"model", "heldout_rmse"} <= set(r["baseline"])
    assert {"model", "effects", "heldout_rmse"} <= set(r["extended"])
    assert sorted(f["effect"] for f in r["findings"]) == sorted(EFFECT_NAMES)
    assert all(set(f) == FINDING_KEYS for f in r["findings"])
    sat = next(f for f in r["findings"] if f["effect"] == "saturation")
    assert sat["statistic"] is None and "not testable" in sat["explanation"]
    json.dumps(r)  # plain JSON


def _manifest(tmp_path, rng):
    scene = random_scene(rng, (40, 56), 3, high=0.35)
    cam = Camera()
    write_image(tmp_path / "s.png", cam.capture(scene))
    write_image(tmp_path / "b.png", cam.capture(scene, motion=(8.0, 1.0), gain=1.2))
    write_manifest(tmp_path / "m.json", {"kind": "blur-pair", "pairs": [
        {"static": "s.png", "blurred": "b.png", "motion": [8.0, 1.0]}]})
    return tmp_path / "m.json"


def test_cli_writes_report_markdown_and_figures(tmp_path, rng):
    from clblur.cli import study as cli

    m = _manifest(tmp_path, rng)
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    args = parser.parse_args(["study", str(m), "--report", str(tmp_path / "r.json"),
                              "--figures", str(tmp_path / "fig"), "--quiet"])
    assert args.func(args) == 0
    r = json.loads((tmp_path / "r.json").read_text())
    assert r["kind"] == "blur-pair" and r["findings"][0]["effect"] == "exposure_gain"
    assert "exposure_gain" in (tmp_path / "r.md").read_text()
    assert {"residuals_0.png", "profile_0.png", "response.png"} <= {
        p.name for p in (tmp_path / "fig").iterdir()}


def test_bad_input_is_named(tmp_path, rng):
    m = _manifest(tmp_path, rng)
    with pytest.raises(ValueError, match="input"):
        study(m, report=tmp_path / "s.png")
    with pytest.raises(ValueError, match="folder does not exist"):
        study(m, report=tmp_path / "missing" / "r.json")
    with pytest.raises(ValueError, match="max_pixels"):
        study(m, max_pixels=10)
    with pytest.raises(ValueError, match="8-bit"):
        pair_group(np.zeros((8, 8), np.uint16), np.zeros((8, 8), np.uint16), (1.0, 0.0))
    with pytest.raises(ValueError, match="shape"):
        pair_group(np.zeros((8, 8), np.uint8), np.zeros((8, 9), np.uint8), (1.0, 0.0))
    with pytest.raises(ValueError, match="unknown effect"):
        scenario({"lens_flare": 1.0}, rng)
    with pytest.raises(ValueError, match="nothing to study"):
        study_groups("blur-pair", [])
    assert set(RANGES) == set(EFFECT_NAMES)


def test_levin_pair_runs_on_measured_data(shared_data):
    from clblur.io import read_image, read_psf

    base = shared_data / "levin2009"
    g = pair_group(read_image(base / "gt" / "im1.png"), read_image(base / "im1_kernel1_img.png"),
                   read_psf(base / "gt" / "kernel1.png"), max_pixels=4000)
    r = study_groups("blur-pair", [g]).report
    assert np.isfinite(r["baseline"]["heldout_rmse"])
    assert r["extended"]["heldout_rmse"] <= r["baseline"]["heldout_rmse"] + 1e-9


def test_shared_data_manifests(shared_data, tmp_path):
    from clblur.manifest import load_manifest
    from clblur.study import shared

    assert len(load_manifest(shared.memorial(tmp_path, shared_data)).images) == 16
    assert len(load_manifest(shared.levin(tmp_path, shared_data)).pairs) == 32
    code_mean, gamma = shared.gopro(tmp_path, shared_data)
    stacks = load_manifest(code_mean).stacks
    assert len(stacks) == 4 and all(len(s.frames) == shared.GOPRO_STACK for s in stacks)
    # the code-mean long exposure is the rounded mean of its frames' codes
    from clblur.io import read_image

    frames = np.stack([read_image(f) for f in stacks[0].frames]).astype(np.float64)
    np.testing.assert_array_equal(read_image(stacks[0].long), np.rint(frames.mean(axis=0)))
    assert load_manifest(gamma).kind == "frame-stack"
