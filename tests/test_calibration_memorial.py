"""The issue's target on the real Memorial stack (skips without ../shared/data)."""

from __future__ import annotations

import pytest

from clblur.calibration import evaluate, fit, load_series
from clblur.calibration.sampling import sample_series


@pytest.fixture(scope="module")
def memorial(shared_data):
    folder = shared_data / "memorial"
    if not folder.is_dir():
        pytest.skip("memorial stack not in the shared data")
    series = load_series(folder, folder / "shutter_times.txt")
    return series, sample_series(series, 600)


def test_memorial_best_model_meets_the_target(memorial):
    series, sampling = memorial
    best = fit(series, "nonparametric", sampling=sampling)
    # leave-one-exposure-out on a fixed subset of the held-out pixels (speed)
    e = evaluate(series, best, gaps=(1, 4), max_pixels=40000)
    # the target, predicting each exposure from the longer one (see the study doc)
    assert e["rmse_darker"][1] <= 4.5
    assert e["rmse_darker"][4] <= 4.0
    assert e["rmse"][1] <= 4.5  # both directions pooled, 1 stop
    assert e["n_values"][4] > 1000


def test_memorial_paper_curve_is_far_worse(memorial):
    series, sampling = memorial
    paper = fit(series, "exp", sampling=sampling)
    offset = fit(series, "exp-offset", sampling=sampling)
    free = fit(series, "nonparametric", sampling=sampling)
    scores = {m.model: evaluate(series, m, gaps=(1, 4), refit=False, max_pixels=40000)
              for m in (paper, offset, free)}
    for gap in (1, 4):
        assert scores["exp"]["rmse_darker"][gap] > 2 * scores["exp-offset"]["rmse_darker"][gap]
        assert scores["exp-offset"]["rmse_darker"][gap] > scores["nonparametric"][
            "rmse_darker"][gap]
    assert paper.aic > offset.aic > free.aic
    # the black level Eq. 3 lacks: 13 .. 25 DN on this stack
    assert all(0.04 < p["black_level"] < 0.12 for p in offset.params["per_channel"])
