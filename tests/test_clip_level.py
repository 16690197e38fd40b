"""Cameras that clip below full scale (``clblur.pixels.clip_level``): calibration and the
study take the clip point for clipping, not for light; a series that clips at full scale,
or a chart whose brightest patch is merely flat, is untouched."""

from __future__ import annotations

import numpy as np
import pytest
from bracket_scenes import exposure, scene

from clblur.calibration import calibrate
from clblur.calibration.series import ExposureSeries
from clblur.pixels import clip_level

TIMES = (8.0, 4.0, 2.0, 1.0, 0.5, 0.25)


def series_frames(clip: int | None, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    radiance = scene(120, 160, seed)
    frames = [exposure(radiance, t, rng) for t in TIMES]
    return frames if clip is None else [np.minimum(f, clip) for f in frames]


def test_a_clip_below_full_scale_is_found():
    frames = series_frames(230)
    assert clip_level(frames[0], frames[1]) == pytest.approx(230 / 255)
    plain = series_frames(None)
    assert clip_level(plain[0], plain[1]) == 1.0  # clips at 255
    wide = [(f.astype(np.uint16) * 64) for f in series_frames(None)]  # 14-bit data in 16 bits
    assert clip_level(wide[0], wide[1]) == pytest.approx(255 * 64 / 65535)
    assert clip_level(frames[0].astype(np.float32) / 255) == 1.0  # floats: not judged


def test_a_flat_brightest_patch_is_not_clipping():
    """A chart whose brightest patch sits, flat and noiseless, below full scale."""
    chart = np.repeat(np.repeat(np.array([[20, 60, 110], [150, 190, 240]], np.uint8), 40, 0),
                      40, 1)[..., None].repeat(3, 2)
    darker = (chart * 0.7).astype(np.uint8)
    assert clip_level(chart) == pytest.approx(240 / 255)  # alone it looks clipped
    assert clip_level(chart, darker) == 1.0  # one stop down it is one value, not a spread


def test_calibration_leaves_the_clip_point_out():
    clipped = ExposureSeries.create(series_frames(230), TIMES)
    assert clipped.white_level == pytest.approx(230 / 255)
    cal = calibrate(clipped, ["exp"], refit=False)
    valid_top = cal.evaluations["exp"]["valid"][1]
    assert valid_top < 230 / 255
    sampling = cal.fits["exp"].sampling
    for s in sampling.per_channel:
        assert s.highest[s.valid].max() < 230 / 255  # normalised: no sampled value clipped
    plain = ExposureSeries.create(series_frames(None), TIMES)
    assert plain.white_level == 1.0
    assert calibrate(plain, ["exp"], refit=False).evaluations["exp"]["valid"][1] == \
        pytest.approx(252.5 / 255)


def test_the_study_censors_the_clip_point():
    from clblur.study.series import clip_code, series_groups

    frames = series_frames(230)
    assert clip_code(frames, list(TIMES)) == 230
    for g in series_groups(frames, list(TIMES), max_pixels=4000):
        assert not (g.valid & (g.target >= 230)).any()


def test_a_subset_keeps_the_clip_level_of_its_series():
    """Leave-one-exposure-out refits see the camera's clip point even without the longest
    exposure that shows it."""
    frames = series_frames(230)
    dim = [frames[-1] // 4, frames[-1] // 8]  # two frames too dark to reach the clip point
    clipped = ExposureSeries.create(frames + dim, (*TIMES, 0.0625, 0.03125))
    darkest = clipped.subset([len(frames), len(frames) + 1])
    assert ExposureSeries.create(dim, (0.0625, 0.03125)).white_level == 1.0
    assert darkest.white_level == clipped.white_level == pytest.approx(230 / 255)
