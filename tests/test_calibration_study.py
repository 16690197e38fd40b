"""The study and ``clblur calibrate`` fit the same response model (``clblur.responses``) and
must agree on the curve's shape on the same exposure series."""

from __future__ import annotations

import numpy as np
import pytest

from clblur.calibration import calibrate, fit, load_series
from clblur.calibration.fitting import transfer
from clblur.responses import ExpShape
from clblur.study import study_groups
from clblur.study.model import shape
from clblur.study.series import series_groups

# Largest disagreement, in code values, between the study's and the calibration's prediction
# of a value one stop darker and brighter (sources 40..200 DN where both are well constrained
# by the data).  The two fit different families of the same model (a smooth warp of Eq. 3 vs a
# free 64-knot spline) on different pixels, so a few DN apart is agreement.
AGREE_DN = 4.0


def s_curve(x):
    """S-shaped camera curve with a 10 DN black level (like a consumer JPEG's tone curve)."""
    b = 10 / 255
    return b + (1 - b) / (1.0 + (0.1 / np.maximum(x, 1e-12)) ** 0.9)


def make_series(rng, n=6, size=(48, 64)):
    radiance = 2.0 ** rng.uniform(-6, 4, size=(size[0] // 4, size[1] // 4))
    radiance = np.kron(radiance, np.ones((4, 4)))
    times = 2.0 ** -np.arange(n)
    imgs = []
    for t in times:
        v = s_curve(radiance * t)[..., None] * np.ones(3)
        imgs.append(np.clip(np.rint(v * 255 + rng.normal(0, 0.7, v.shape)), 0, 255)
                    .astype(np.uint8))
    return imgs, times


def study_curve(sel) -> ExpShape:
    p = sel.params
    return ExpShape(p["black"], *[shape(p).params()[k] for k in ("gamma", "rho")],
                    warp=tuple(shape(p).warp))


def disagreement_dn(a, b) -> float:
    v = np.linspace(40, 200, 81) / 255
    return max(float(np.max(np.abs(transfer(a, v, r) - transfer(b, v, r)))) * 255
               for r in (0.5, 2.0))


def test_study_and_calibrate_agree_on_an_s_curve():
    rng = np.random.default_rng(5)
    imgs, times = make_series(rng)
    from clblur.calibration import ExposureSeries

    series = ExposureSeries.create(imgs, times)
    cal = fit(series, "spline", n_samples=200)
    sel = study_groups("exposure-series", series_groups(imgs, list(times))).selection
    assert "response_shape" in sel.effects
    assert disagreement_dn(study_curve(sel), cal.responses[1]) < AGREE_DN


def test_agree_on_canon400d_road(shared_data):
    folder = shared_data / "canon400d_road"
    if not folder.is_dir():
        pytest.skip("canon400d_road not in the shared data")
    import cv2

    series = load_series(folder)
    small = [cv2.resize(im, (486, 324), interpolation=cv2.INTER_AREA) for im in series.images]
    from clblur.calibration import ExposureSeries

    series = ExposureSeries.create(small, series.exposures, series.f_numbers)
    cal = calibrate(series, ["spline"], refit=False, max_pixels=20000)
    sel = study_groups("exposure-series", series_groups(
        small, list(series.exposures), list(series.f_numbers))).selection
    assert "response_shape" in sel.effects
    assert disagreement_dn(study_curve(sel), cal.fits["spline"].responses[1]) < AGREE_DN
