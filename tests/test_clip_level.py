"""Cameras that clip below full scale (``clblur.pixels.clip_level``): calibration and the
study take the clip point for clipping, not for light; a series that clips at full scale,
or a chart whose brightest patch is merely flat, is untouched."""

from __future__ import annotations

import numpy as np
import pytest
from bracket_scenes import exposure, scene

from clblur.calibration import calibrate
from clblur.calibration.fitting import transfer
from clblur.calibration.sampling import sample_series
from clblur.calibration.series import ExposureSeries
from clblur.pixels import clip_level

TIMES = (8.0, 4.0, 2.0, 1.0, 0.5, 0.25)


def series_frames(clip: int | None, seed: int = 0, noise: float = 0.004,
                  exact_clip: bool = False) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    radiance = scene(120, 160, seed)
    frames = [exposure(radiance, t, rng, noise=noise, exact_clip=exact_clip) for t in TIMES]
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
    # the report's clipped column counts the pixels at the clip point (it read 0.0 %)
    from clblur.calibration.report import series_table

    longest = series_table(clipped).splitlines()[-1]
    share = float(longest.split("|")[4].strip().removesuffix(" %"))
    assert share == pytest.approx(100 * np.mean(series_frames(230)[0] >= 230), abs=0.05)
    assert share > 1.0
    cal = calibrate(clipped, ["exp"], refit=False)
    valid_top = cal.evaluations["exp"]["valid"][1]
    assert valid_top < 230 / 255
    sampling = cal.fits["exp"].sampling
    for s in sampling.per_channel:
        assert s.highest[s.valid].max() < 230 / 255  # normalised: no sampled value clipped
    plain = ExposureSeries.create(series_frames(None, exact_clip=True), TIMES)
    assert plain.white_level == 1.0
    assert calibrate(plain, ["exp"], refit=False).evaluations["exp"]["valid"][1] == \
        pytest.approx(252.5 / 255)


def test_the_spline_leaves_the_clip_point_out():
    # its random single pixels had only 0 and full scale left out: a camera clipping at 230
    # had its pile of 230s fitted as light (a video-range bracket: held-out 23.4 DN against
    # 2.1 for gamma-offset; now 2.2)
    clipped = ExposureSeries.create(series_frames(230), TIMES)
    plain = ExposureSeries.create(series_frames(None), TIMES)
    cal = calibrate(clipped, ["spline", "gamma-offset"], refit=False)
    for s in cal.fits["spline"].sampling.pixels:
        assert s.values[s.valid].max() == pytest.approx(230 / 255)  # the sampling keeps all ...
    curve = cal.fits["spline"].responses[0]
    truth = calibrate(plain, ["spline"], refit=False).fits["spline"].responses[0]
    v = np.linspace(0.1, 0.85, 50)  # ... the fit does not: it is the unclipped series' curve
    for ratio in (0.5, 2.0):
        got, want = (transfer(c, v, ratio) for c in (curve, truth))
        keep = want < 0.85
        assert np.abs(got[keep] - want[keep]).max() * 255 < 1.5
    rmse = {m: cal.evaluations[m]["rmse_darker"][1] for m in ("spline", "gamma-offset")}
    assert rmse["spline"] < 1.5 * rmse["gamma-offset"], rmse


def test_the_spline_counts_the_pile_as_censored():
    """Targets on a pile below full scale are clipped, as targets at full scale are: the
    spline's pools just below the pile keep their trimmed mean, not their darker targets
    only.  Left out, they put the curve 0.7 - 1.1 codes off the truth near the pile with 3
    codes of noise; counted as censored, 0.06 - 0.29 (validation.md, "A pile below full
    scale, censored in the spline's pools too")."""
    from clblur.calibration.cross_exposure import pooled_pairs

    frames = series_frames(230, noise=0.012)
    clipped = ExposureSeries.create(frames, TIMES)
    top = clipped.white_level - 0.5 / 255
    pixels = [p.with_range(2.5 / 255, top) for p in sample_series(clipped, 1000).pixels]
    tau = clipped.relative_exposures()
    for clip_high, censored in ((None, False), (top, True)):
        errors, counts = [], []
        for p in pixels:
            src, mean, ratio, count = pooled_pairs(p.values, p.valid, tau, 4.5, 255,
                                                   clip_high=clip_high)
            truth = src * ratio ** (1 / 2.2)  # the camera is a gamma-2.2 curve
            # pools whose targets lie within 15 codes (5 noise sigmas) below the pile
            close = (truth > 215 / 255) & (truth < 228 / 255)
            errors.append(mean[close] - truth[close])
            counts.append(count[close])
        bias = float(np.average(np.concatenate(errors), weights=np.concatenate(counts)) * 255)
        if censored:
            assert abs(bias) < 0.5, bias
        else:  # the pile's targets left out: the pools keep their darker targets only
            assert bias < -1.0, bias
    cal = calibrate(clipped, ["spline"], refit=False)
    near = np.linspace(170, 228, 59) / 255  # the top 60 codes below the pile
    for c, curve in enumerate(cal.fits["spline"].responses):
        # one stop down from them, and one stop up to them
        for v, ratio in ((near, 0.5), (near / 2 ** (1 / 2.2), 2.0)):
            err = np.abs(transfer(curve, v, ratio) - v * ratio ** (1 / 2.2)).max() * 255
            assert err < 0.6, (c, ratio, err)


def test_clipped_pixels_that_read_below_the_pile_are_clipping():
    """Noise added after the clip (this generator's, a film scanner's) spreads a clipped
    pixel below full scale: the series clips where its surely clipped pixels start to read,
    for calibration and the study alike; exact clipping, far outliers, padding and a JPEG's
    codec spread leave the level alone."""
    from clblur.pixels import pile_floor, series_clip_level
    from clblur.study.series import clip_code, series_groups

    exact = series_frames(None, exact_clip=True)
    noisy = series_frames(None)  # read noise of 1 code, after the clip
    wide = series_frames(None, noise=0.012)  # 3 codes
    assert pile_floor(exact, TIMES) == 1.0
    floor = pile_floor(noisy, TIMES)
    assert 250 / 255 <= floor <= 253 / 255  # 2 - 5 noise sigmas below the pile
    assert pile_floor(wide, TIMES) <= floor - 4 / 255
    assert ExposureSeries.create(noisy, TIMES).white_level == floor
    assert ExposureSeries.create(exact, TIMES).white_level == 1.0
    assert clip_code(noisy, list(TIMES)) == round(255 * floor)
    for g in series_groups(noisy, list(TIMES), max_pixels=4000):  # the study censors there
        assert not (g.valid & (g.target >= round(255 * floor))).any()
    assert clip_code(noisy, list(TIMES), block=8) == 255  # a JPEG's spread: near_clip's
    assert series_clip_level(noisy, TIMES, lossless=False) == 1.0
    # a few surely clipped pixels far below the pile (a misregistered edge, a moving object)
    # are not a spread
    odd = [f.copy() for f in exact]
    sure = np.flatnonzero((exact[1][..., 0] == 255).ravel())[::40]
    odd[0].reshape(-1, 3)[sure, 0] = 180
    assert pile_floor(odd, TIMES) == 1.0
    # a border padded with pure blue is no clipped light
    assert pile_floor(_padded(exact), TIMES) == 1.0
    # nothing clips: a dim bracket, and one whose brightest codes are a handful (where the
    # most common value near the top is 0 and every pixel would have passed for clipped)
    rng = np.random.default_rng(5)
    dim = [exposure(np.minimum(scene(120, 160, 0), 0.1), t, rng) for t in TIMES]
    assert max(int(f.max()) for f in dim) < 250 and pile_floor(dim, TIMES) == 1.0
    tiny = [(rng.integers(0, 5, (60, 80, 3)) * k).astype(np.uint8) for k in (1, 2)]
    assert pile_floor(tiny, (1.0, 2.0)) == 1.0


def test_a_pile_below_full_scale_spread_both_ways_is_found():
    """A white balance applied after the clip puts red's pile at 217 and blue's at 235, and
    noise added after it spreads each pile both ways, so a channel's top code is the upper
    tail of its spread, not its pile: found from the longest image's most common value near
    the top.  Unfound, calibration took the spread for light (on a bracket like this one,
    84 codes off in red: validation.md, "Clipped pixels that read below the pile")."""
    from clblur.pixels import pile_floor

    gains = (217 / 255, 1.0, 235 / 255)
    rng = np.random.default_rng(0)
    radiance = scene(120, 160, 0)
    noisy = [exposure(radiance, t, rng, noise=0.005, gains=gains) for t in TIMES]
    exact = [exposure(radiance, t, rng, noise=0.005, gains=gains, exact_clip=True)
             for t in TIMES]
    assert ExposureSeries.create(exact, TIMES).white_level == pytest.approx(217 / 255)
    floor = pile_floor(noisy, TIMES)
    assert 211 / 255 <= floor <= 215 / 255  # 2 - 5 noise sigmas below red's pile
    series = ExposureSeries.create(noisy, TIMES)
    assert series.white_level == floor
    cal = calibrate(series, ["gamma-offset"], refit=False)
    v = np.linspace(40, 200, 81) / 255
    for c, (curve, g) in enumerate(zip(cal.fits["gamma-offset"].responses, gains,
                                       strict=True)):
        want = v * 2 ** (-1 / 2.2)  # one stop down, any gain after the curve
        assert np.abs(transfer(curve, v, 0.5) - want).max() * 255 < 0.5, (c, g)


def test_the_spline_reads_a_spread_pile_as_clipped():
    """With the noise after the clip, values of 252 - 254 that are clipped light entered the
    spline as sources: 10 - 65 codes off at its top (validation.md, "Clipped pixels that
    read below the pile")."""
    cal = calibrate(ExposureSeries.create(series_frames(None, noise=0.012), TIMES), ["spline"],
                    refit=False)
    near = np.linspace(170, 248, 79) / 255
    for c, curve in enumerate(cal.fits["spline"].responses):
        for v, ratio in ((near, 0.5), (near / 2 ** (1 / 2.2), 2.0)):
            err = np.abs(transfer(curve, v, ratio) - v * ratio ** (1 / 2.2)).max() * 255
            assert err < 1.0, (c, ratio, err)


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


# where each frame of a registered bracket was padded: (frame, edge, width), as Memorial's
# frames are padded along different edges by different widths
PADS = ((1, "top", 6), (3, "left", 5), (4, "bottom", 7), (5, "right", 8))


def _band(shape, edge: str, width: int) -> np.ndarray:
    band = np.zeros(shape[:2], bool)
    band[{"top": np.s_[:width], "bottom": np.s_[-width:], "left": np.s_[:, :width],
          "right": np.s_[:, -width:]}[edge]] = True
    return band


def _padded(frames: list[np.ndarray]) -> list[np.ndarray]:
    """The frames with their ``PADS`` painted pure blue, as Memorial's are."""
    out = [f.copy() for f in frames]
    for i, edge, width in PADS:
        out[i][_band(out[i].shape, edge, width)] = (0, 0, 255)
    return out


def test_a_padded_border_is_found_and_a_scene_run_is_not():
    from clblur.pixels import series_padding

    frames = series_frames(None)
    pads = series_padding(_padded(frames), TIMES)
    truth = [np.zeros(f.shape[:2], bool) for f in frames]
    for i, edge, width in PADS:
        truth[i] = _band(frames[i].shape, edge, width)
    for p, t in zip(pads, truth, strict=True):
        np.testing.assert_array_equal(p, t)
    # a run of one colour along an edge that obeys the exposures is scene, not padding
    flat = [f.copy() for f in frames]
    for f, t in zip(flat, TIMES, strict=True):
        f[:, :20] = min(255, round(40 * t))  # a flat strip, brighter with exposure
    assert not any(p.any() for p in series_padding(flat, TIMES))


def test_the_study_leaves_padding_out_and_bounds_the_black_level_allowing_for_noise():
    from clblur.study.series import series_groups

    frames = series_frames(None)
    notes: dict = {}
    padded = _padded(frames)
    groups = series_groups(padded, list(TIMES), max_pixels=4000, notes=notes)
    assert sorted(notes["padding"]) == [i for i, _, _ in PADS]
    bands = {i: _band(frames[i].shape, e, wd) for i, e, wd in PADS}
    for g in groups:  # no pixel padded in the step's source or target is sampled
        k, j = (int(v) for v in g.name.removeprefix("step").split("-"))  # longest first
        for i in (k, j):
            if i in bands:
                assert not bands[i][g.rows, g.cols].any()
    # a frame on a pedestal of 12 codes whose single pixels scatter down to 0 and which is
    # shaded by +-2 codes over the frame: not its darkest pixel nor its darkest patch (both
    # below the level), here the frame's mean code (the darkest patch plus its noise is more)
    rng = np.random.default_rng(3)
    shade = np.linspace(-2.0, 2.0, 80)[None, :, None]
    dark = np.clip(np.rint(12 + shade + 3 * rng.standard_normal((64, 80, 3))), 0,
                   255).astype(np.uint8)
    dark[10, 10] = 0
    brighter = np.clip(dark.astype(int) * 2, 0, 255).astype(np.uint8)
    from clblur.study.variants import darkest_codes

    g = series_groups([brighter, dark], [2.0, 1.0], max_pixels=1000)[0]
    np.testing.assert_allclose(darkest_codes(g), dark.reshape(-1, 3).mean(axis=0))
    assert np.all(np.abs(darkest_codes(g) - 12) < 0.2)
    # blacks crushed to code 0 over a patch (a JPEG engine's): the level is 0 there
    crushed = dark.copy()
    crushed[20:40, 20:40] = 0
    g = series_groups([brighter, crushed], [2.0, 1.0], max_pixels=1000)[0]
    np.testing.assert_array_equal(darkest_codes(g), 0.0)
