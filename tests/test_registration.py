"""Registration of hand-held exposure series (``clblur.registration``): known shifts are
recovered exactly, aligned series are left alone, and calibration and the study see the
images as if they had been shot on a tripod."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from bracket_scenes import exposure, scene  # tests/ is on the path (pytest rootdir)

from clblur.calibration.series import ExposureSeries, load_series
from clblur.registration import align_series, pair_shift

MARGIN = 12


def _handheld(seed: int, times=(8.0, 4.0, 2.0, 1.0, 0.5, 0.25, 0.125), h=180, w=240):
    """A bracket whose frames are windows of one scene at random whole-pixel offsets (up to
    ``MARGIN``): (frames, offsets, the frames cut to the common window)."""
    rng = np.random.default_rng(seed)
    radiance = scene(h + 2 * MARGIN, w + 2 * MARGIN, seed)
    offsets = rng.integers(-MARGIN, MARGIN + 1, (len(times), 2))
    frames, whole = [], []
    for t, (dy, dx) in zip(times, offsets, strict=True):
        # the shortest frame sits on a pedestal with noise, as Memorial's do
        full = exposure(radiance, t, rng, pedestal=0.05 if t == min(times) else 0.0)
        whole.append(full)
        frames.append(full[MARGIN + dy:MARGIN + dy + h, MARGIN + dx:MARGIN + dx + w])
    lo, hi = offsets.max(axis=0), offsets.min(axis=0)
    common = [f[MARGIN + lo[0]:MARGIN + hi[0] + h, MARGIN + lo[1]:MARGIN + hi[1] + w]
              for f in whole]
    return frames, offsets, common, list(times)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_known_shifts_are_recovered_exactly(seed):
    frames, offsets, common, times = _handheld(seed)
    reg = align_series(frames, times)
    ref = reg.reference
    # the scene point at (y, x) of the reference frame is at (y + o_ref - o_i) in frame i
    assert reg.shifts.tolist() == (offsets[ref] - offsets).tolist()
    assert not reg.unregistered
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(reg.crop(f, i), common[i])


def test_a_tripod_series_is_left_as_it_is():
    _, _, still, times = _handheld(3)  # the common crops: no motion between them
    reg = align_series(still, times)
    assert not reg.moved and reg.shifts.tolist() == [[0, 0]] * len(still)
    series = ExposureSeries.create(still, times).aligned()
    assert all(a is b for a, b in zip(series.images, still, strict=True))


def test_a_link_without_common_range_is_reported_not_guessed():
    rng = np.random.default_rng(0)
    lit = rng.integers(20, 230, (64, 64, 3)).astype(np.uint8)
    black = np.zeros_like(lit)
    assert pair_shift(lit, black) is None
    reg = align_series([lit, black], [2.0, 1.0])
    assert reg.unregistered == (1,) and not reg.moved


def _write_bracket(folder: Path, frames, times) -> Path:
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"f{i}.png"), f)
    (folder / "times.txt").write_text("".join(f"f{i}.png {t}\n" for i, t in enumerate(times)))
    return folder / "times.txt"


def test_calibrate_registers_a_handheld_bracket(tmp_path, capsys):
    from clblur.cli import main

    frames, offsets, common, times = _handheld(4)
    times_file = _write_bracket(tmp_path / "bracket", frames, times)
    series = load_series(tmp_path / "bracket", times_file)
    for im, c in zip(series.images, common, strict=True):  # as if shot on a tripod
        np.testing.assert_array_equal(im, c[..., ::-1])  # written as BGR, read as RGB
    raw = load_series(tmp_path / "bracket", times_file, align=False)
    assert raw.registration is None and raw.shape == frames[0].shape[:2]
    assert main(["calibrate", str(tmp_path / "bracket"), "--times", str(times_file),
                 "--model", "exp", "--samples", "200", "--no-refit", "--quiet",
                 "-o", str(tmp_path / "r.json"), "--report", str(tmp_path / "rep")]) == 0
    out = capsys.readouterr().out
    moved = [f"f{i}.png ({dy}, {dx})" for i, (dy, dx) in
             enumerate((offsets[series.registration.reference] - offsets).tolist())
             if dy or dx]
    assert out.startswith("registered: " + ", ".join(moved) + " px (rows, cols) against ")
    assert "Registered: f" in (tmp_path / "rep" / "report.md").read_text()


def test_the_study_registers_an_exposure_series(tmp_path):
    from clblur.calibration.series import folder_series
    from clblur.study.run import groups_from_manifest

    frames, offsets, common, times = _handheld(5, times=(4.0, 2.0, 1.0))
    times_file = _write_bracket(tmp_path / "bracket", frames, times)
    _write_bracket(tmp_path / "tripod", common, times)
    notes: dict = {}
    moved = groups_from_manifest(folder_series(tmp_path / "bracket", times_file), 3000,
                                 notes=notes)
    still = groups_from_manifest(folder_series(tmp_path / "tripod", tmp_path / "tripod"
                                               / "times.txt"), 3000)
    ref = times.index(2.0)
    assert notes["registration"]["shifts"] == {f"f{i}.png": s for i, s in
                                               enumerate((offsets[ref] - offsets).tolist())}
    for a, b in zip(moved, still, strict=True):  # the same pixels, so the same groups
        np.testing.assert_array_equal(a.target, b.target)
    json.dumps(notes)  # the report is JSON


def test_memorial_is_registered_as_shot_and_shifted_copies_are_recovered(shared_data):
    folder = shared_data / "memorial"
    if not folder.is_dir():
        pytest.skip("memorial stack not in the shared data")
    series = load_series(folder, folder / "shutter_times.txt", align=False)
    exposures = series.relative_exposures()
    reg = align_series(series.images, exposures)
    assert not reg.moved and not reg.unregistered  # Debevec's stack is registered
    rng = np.random.default_rng(5)
    m = 20
    offsets = rng.integers(-m, m + 1, (len(series.images), 2))
    cut = [im[m + dy:im.shape[0] - m + dy, m + dx:im.shape[1] - m + dx]
           for im, (dy, dx) in zip(series.images, offsets, strict=True)]
    reg = align_series(cut, exposures)
    assert reg.shifts.tolist() == (offsets[reg.reference] - offsets).tolist()


def test_the_study_crops_a_one_pixel_move_of_one_frame(tmp_path):
    # the misregistration effect is one shift shared by every step: a single frame moved by
    # a row shifts its two steps in opposite directions, which no shared shift fits, so the
    # registration takes it out, as it does a larger move
    from clblur.calibration.series import folder_series
    from clblur.study.run import groups_from_manifest

    _, _, common, times = _handheld(6, times=(4.0, 2.0, 1.0))
    moved = [common[0][1:], common[1][:-1], common[2][:-1]]  # the longest one row up
    times_file = _write_bracket(tmp_path / "bracket", moved, times)
    _write_bracket(tmp_path / "tripod", [c[1:-1] for c in common], times)  # the common rows
    notes: dict = {}
    groups = groups_from_manifest(folder_series(tmp_path / "bracket", times_file), 3000,
                                  notes=notes)
    still = groups_from_manifest(folder_series(tmp_path / "tripod", tmp_path / "tripod"
                                               / "times.txt"), 3000, align=False)
    reg = notes["registration"]
    assert reg["shifts"]["f0.png"] == [-1, 0]
    assert "cropped to" in reg["summary"]
    for a, b in zip(groups, still, strict=True):  # the pixels of the common window
        np.testing.assert_array_equal(a.target, b.target)


def _turned(seed: int, degrees, times=(4.0, 2.0, 1.0, 0.5, 0.25), h=240, w=320):
    """A bracket whose frames see one scene turned by ``degrees`` (x right, y down) about
    the frame's centre and moved by a few pixels, rendered from the continuous scene (no
    nearest-pixel staircase): (frames, the 2 x 3 map of each frame, scene (x, y, 1) to frame
    (x, y))."""
    rng = np.random.default_rng(seed)
    m = 40
    radiance = scene(h + 2 * m, w + 2 * m, seed)
    frames, maps = [], []
    for t, deg in zip(times, degrees, strict=True):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        rot = np.array([[c, -s], [s, c]])
        centre = np.array([(w - 1) / 2 + m, (h - 1) / 2 + m])
        move = rng.uniform(-3, 3, 2)
        # frame (x, y) shows the scene at rot^-1 (frame - centre + m - move) + centre
        to_frame = np.hstack([rot, (centre - m + move - rot @ centre)[:, None]])
        light = cv2.warpAffine(radiance, to_frame, (w, h), flags=cv2.INTER_CUBIC)
        frames.append(exposure(np.maximum(light, 0), t, rng))
        maps.append(to_frame)
    return frames, maps


@pytest.mark.parametrize("seed, degrees", [(0, (0.0, 0.4, -0.3, 0.6, -0.5)),
                                           (1, (1.5, -1.0, 0.2, 0.8, 0.0))])
def test_a_turned_bracket_is_registered_to_the_nearest_pixel(seed, degrees):
    frames, truth = _turned(seed, degrees)
    reg = align_series(frames, [4.0, 2.0, 1.0, 0.5, 0.25])
    assert reg.maps is not None and not reg.unregistered
    ref = reg.reference
    back = np.linalg.inv(np.vstack([truth[ref], [0, 0, 1]]))
    rows, cols = reg.window
    corners = np.array([[x, y, 1.0] for y in (rows.start, rows.stop - 1)
                        for x in (cols.start, cols.stop - 1)])
    for i, f in enumerate(frames):
        true_map = truth[i] @ back  # reference (x, y, 1) to frame i (x, y)
        assert abs(reg.turn_degrees(i) - (degrees[i] - degrees[ref])) < 0.05
        # every window pixel is read within half a pixel of where frame i shows its point,
        # so the nearest pixel is the true one up to that half pixel
        err = np.abs(corners @ reg.maps[i].T - corners @ true_map.T).max()
        assert err < 0.5, (i, err)
        # and the crop reads, for each window pixel, the frame's pixel nearest to its map
        cut = reg.crop(f, i)
        assert cut.shape[:2] == (rows.stop - rows.start, cols.stop - cols.start)
        ys, xs = np.mgrid[rows, cols]
        at = np.stack([xs, ys, np.ones_like(xs)], axis=-1).astype(np.float64) @ reg.maps[i].T
        near = np.floor(at + 0.5).astype(int)
        assert near.min() >= 0 and near[..., 0].max() < f.shape[1] \
            and near[..., 1].max() < f.shape[0]  # the window lies inside every frame
        same = (cut == f[near[..., 1], near[..., 0]]).all(axis=-1)
        assert same.mean() > 0.999  # exact halves may round either way in OpenCV


def test_a_turn_is_reported_and_a_small_one_is_not_applied():
    from clblur.registration import describe, summary

    frames, _ = _turned(2, (0.0, 0.6, 0.0, 0.0, 0.0))
    names = [f"f{i}.png" for i in range(5)]
    reg = align_series(frames, [4.0, 2.0, 1.0, 0.5, 0.25])
    report = describe(reg, names)
    assert abs(report["turns_deg"]["f1.png"] - 0.6) < 0.05
    assert "f1.png" in summary(reg, names) and "turned +0.6" in summary(reg, names)
    json.dumps(report)
    # a turn that moves the frame's corners by less than TURN_PX is taken as none: the
    # series is registered as whole-pixel moves, each frame a view
    frames, _ = _turned(2, (0.0, 0.05, 0.0, 0.0, 0.0))
    reg = align_series(frames, [4.0, 2.0, 1.0, 0.5, 0.25])
    assert reg.maps is None and "turns_deg" not in describe(reg, names)


def test_calibration_of_a_turned_bracket_matches_the_tripod(tmp_path):
    from clblur.calibration import calibrate

    degrees = (0.0, 0.8, -0.6, 0.7, -0.9)
    times = [4.0, 2.0, 1.0, 0.5, 0.25]
    turned, _ = _turned(3, degrees, times=times)
    tripod, _ = _turned(3, (0.0,) * 5, times=times)

    def k_and_error(frames, turns=True):
        series = ExposureSeries.create(frames, times)
        reg = align_series(frames, series.relative_exposures(), turns=turns)
        cut = ExposureSeries([reg.crop(f, i) for i, f in enumerate(frames)], series.exposures,
                             None, series.names, reg)
        cal = calibrate(cut, ["exp"], n_samples=400, refit=False)
        return (np.array([r.params()["k"] for r in cal.responses]),
                cal.evaluations["exp"]["rmse_darker"][1])

    k_tripod, e_tripod = k_and_error(tripod)
    k_shifted, e_shifted = k_and_error(turned, turns=False)
    k_turned, e_turned = k_and_error(turned)
    # taken as whole-pixel moves the corners mix scene points and the error grows; with the
    # turns the fit is the tripod's
    assert e_shifted > 1.5 * e_tripod  # 50.9 against 19.7 when written
    assert e_turned < 1.15 * e_tripod  # 21.3
    assert np.abs(k_turned / k_tripod - 1).max() < 0.03


def test_a_turn_too_dark_to_tell_is_reported_not_guessed():
    from clblur.registration import describe, summary

    times = (4.0, 2.0, 1.0, 0.5, 0.25)
    frames, _ = _turned(4, (0.0, 0.6, 0.0, -0.5, 0.8), times=times)
    # the shortest frame lit only in its middle ninth: enough for its shift, one block
    lit = np.zeros_like(frames[4])
    h, w = lit.shape[:2]
    middle = (slice(h // 3, 2 * h // 3), slice(w // 3, 2 * w // 3))
    lit[middle] = frames[4][middle]
    frames[4] = lit
    names = [f"f{i}.png" for i in range(5)]
    reg = align_series(frames, list(times))
    assert reg.untold == (4,) and not reg.unregistered
    assert abs(reg.turn_degrees(1) - 0.6) < 0.05  # the others are told
    # taken as the turn of its longer neighbour, which it is chained to
    assert reg.turn_degrees(4) == pytest.approx(reg.turn_degrees(3))
    assert describe(reg, names)["turn_untold"] == ["f4.png"]
    assert summary(reg, names).endswith("taken as none): f4.png")


def test_frames_that_did_not_turn_are_cut_not_read():
    # the reference and a frame linked to it by a whole-pixel shift alone are views of the
    # stored frames when another frame turned
    frames, _ = _turned(2, (0.0, 0.6, 0.0, 0.0, 0.0))
    reg = align_series(frames, [4.0, 2.0, 1.0, 0.5, 0.25])
    assert reg.maps is not None
    for i in (reg.reference, 3):
        assert np.shares_memory(reg.crop(frames[i], i), frames[i])
    assert not np.shares_memory(reg.crop(frames[1], 1), frames[1])
