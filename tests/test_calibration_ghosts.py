"""Moving objects in an exposure bracket: found without a response model, and left out of
the calibration's samples and scores (``clblur.calibration.ghosts``)."""

from __future__ import annotations

import numpy as np
import pytest
from bracket_scenes import exposure, scene  # tests/ is on the path (pytest rootdir)

from clblur.calibration import ExposureSeries, calibrate
from clblur.calibration.compare import selection_score
from clblur.calibration.evaluate import evaluate
from clblur.calibration.ghosts import moving_pixels

H, W = 240, 360
TIMES = [2.0**-i for i in range(5)]


def brackets():
    """The same gamma-2.2 bracket twice: a static scene, and one where three objects (a
    bright one, a dark one, a textured one) stand at different places in two frames."""
    radiance = scene(H, W, seed=11)
    rng = np.random.default_rng(2)
    static = [exposure(radiance, t, rng) for t in TIMES]
    moved = [im.copy() for im in static]
    objects = np.zeros((H, W), bool)
    where = {1: [(20, 30), (150, 200), (40, 250)], 3: [(120, 40), (30, 150), (160, 300)]}
    for frame, spots in where.items():
        light = [radiance[60:120, 60:100] * 6.0, radiance[60:120, 60:100] * 0.1,
                 radiance[::-1, ::-1][0:60, 0:40]]
        for (y, x), lit in zip(spots, light, strict=True):
            view = radiance.copy()
            view[y:y + 60, x:x + 40] = lit
            moved[frame][y:y + 60, x:x + 40] = exposure(view, TIMES[frame], rng)[y:y + 60,
                                                                                 x:x + 40]
            objects[y:y + 60, x:x + 40] = True
    return (ExposureSeries.create(static, TIMES), ExposureSeries.create(moved, TIMES),
            objects)


def test_the_objects_are_found_and_the_static_scene_is_not():
    static, moved, objects = brackets()
    assert not static.moving.any()
    found = moved.moving
    assert found[objects].mean() > 0.8  # of the objects' pixels (some match the scene)
    assert found[~objects].mean() < 0.03  # of the scene's (the 2-pixel rim is widened)
    # the order of the images does not matter, only their exposures
    np.testing.assert_array_equal(
        moving_pixels(moved.images[::-1], TIMES[::-1]), found)


def test_a_bracket_with_moving_objects_calibrates_as_the_static_one():
    static, moved, _ = brackets()
    models = ["polynomial", "gamma-offset"]
    clean = calibrate(static, models, refit=False, n_samples=300)
    spoiled = calibrate(moved, models, refit=False, n_samples=300)
    # fitted on the spoiled bracket, scored on the static one: as good as the clean fit
    for name in models:
        ours = selection_score(evaluate(static, spoiled.fits[name], refit=False))
        theirs = selection_score(clean.evaluations[name])
        assert ours < theirs + 0.15, (name, ours, theirs)
    assert "left out as not static" in moved.moving_note()


def test_an_object_in_one_frame_spoils_only_its_pixels_in_a_16_bit_series():
    radiance = scene(H, W, seed=4)
    rng = np.random.default_rng(0)
    images = [exposure(radiance, t, rng).astype(np.uint16) * 257 for t in TIMES]
    images[2][100:140, 200:260] = 65535 - images[2][100:140, 200:260]
    found = ExposureSeries.create(images, TIMES).moving
    assert found[100:140, 200:260].mean() > 0.9
    assert found.sum() < 1.5 * 44 * 64  # the object and its widened rim


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_a_static_series_leaves_nothing_out(dtype):
    radiance = scene(120, 160, seed=9)
    rng = np.random.default_rng(1)
    images = [exposure(radiance, t, rng) for t in TIMES]
    if dtype == np.float32:
        images = [im.astype(np.float32) / 255 for im in images]
    series = ExposureSeries.create(images, TIMES)
    assert not series.moving.any() and series.moving_note() is None
