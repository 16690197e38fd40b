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
