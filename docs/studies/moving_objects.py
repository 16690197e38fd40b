"""Moving objects in an exposure bracket: what they do to a calibration, with and without
``clblur.calibration.ghosts`` leaving them out.

    python docs/studies/rendered_brackets.py /tmp/brackets
    python docs/studies/moving_objects.py /tmp/brackets

Into each rendered camera's bracket (the truth is known: ``rendered_brackets.py``) ``n``
blocks of 120 x 120 pixels of the scene are moved to another place in two of the five frames,
as a walker or a car would stand somewhere else in each exposure.  Each family is fitted on
the spoiled bracket and scored on the clean one (held-out RMSE of the darker target, mean of
the 1- and 4-stop gaps, ``selection_score``), so the score says how far the objects moved the
curve.  ``without mask`` is the same calibration with ``moving_pixels`` replaced by an empty
mask (the code before 2026-11-28).  Prints a markdown table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import clblur.calibration.series as series_module
from clblur.calibration import ExposureSeries, calibrate, load_series
from clblur.calibration.compare import selection_score
from clblur.calibration.evaluate import evaluate

MODELS = ["exp", "gamma-offset", "polynomial", "spline"]
BLOCK = 120


def spoil(series: ExposureSeries, blocks: int, seed: int = 1) -> ExposureSeries:
    """``series`` with ``blocks`` scene blocks moved to other places in two frames each."""
    images = [im.copy() for im in series.images]
    rng = np.random.default_rng(seed)
    h, w = series.shape
    for _ in range(blocks):
        y0, x0, y1, x1 = (int(rng.integers(0, n - BLOCK)) for n in (h, w, h, w))
        for i in rng.choice(len(images), 2, replace=False):
            images[i][y1:y1 + BLOCK, x1:x1 + BLOCK] = series.images[i][y0:y0 + BLOCK,
                                                                       x0:x0 + BLOCK]
    return ExposureSeries.create(images, series.exposures, series.f_numbers, series.names)


def scores(clean: ExposureSeries, spoiled: ExposureSeries) -> tuple[dict, str]:
    """Each family fitted on ``spoiled``, scored on ``clean``; and the family chosen."""
    result = calibrate(spoiled, MODELS, refit=False, max_pixels=100000)
    return ({m: selection_score(evaluate(clean, result.fits[m], gaps=[1, 4], refit=False,
                                         max_pixels=100000)) for m in MODELS}, result.best)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("brackets", type=Path, help="folder of rendered_brackets.py")
    parser.add_argument("--cameras", nargs="+", default=["cam_a", "cam_c"])
    parser.add_argument("--blocks", type=int, default=6)
    args = parser.parse_args()
    print("| camera | model | clean bracket | objects, left out | objects, kept |")
    print("|---|---|---|---|---|")
    for cam in args.cameras:
        clean = load_series(args.brackets / f"{cam}.json")
        spoiled = spoil(clean, args.blocks)
        base, best_clean = scores(clean, clean)
        masked, best_masked = scores(clean, spoiled)
        share = 100 * spoiled.moving.mean()
        real = series_module.ExposureSeries.moving
        series_module.ExposureSeries.moving = property(
            lambda s: np.zeros(s.shape, bool))  # the code before the mask
        try:
            kept, best_kept = scores(clean, spoil(clean, args.blocks))
        finally:
            series_module.ExposureSeries.moving = real
        for m in MODELS:
            print(f"| {cam} | {m} | {base[m]:.2f} | {masked[m]:.2f} | {kept[m]:.2f} |")
        print(f"| {cam} | chosen | {best_clean} | {best_masked} ({share:.1f} % left out) | "
              f"{best_kept} |")


if __name__ == "__main__":
    main()
