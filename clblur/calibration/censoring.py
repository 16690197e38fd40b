"""Which held-out values to score where the target sometimes clips: chosen by the source.

Where the darker (or brighter) image of a pair sometimes clips, keeping only the targets that
did not selects on their noise: their mean sits above (below) what the true curve predicts,
and a fitted curve that bends to that selection outscores the true curve
(``docs/studies/validation.md``, "Held-out values chosen by the source, not by the target's
own noise").  The held-out evaluation (``clblur.calibration.evaluate``) chooses its scored
values here.  The spline's fit and its cross-validation, which pool pixels by source value,
use the clipped targets instead: each pool trimmed symmetrically
(``clblur.calibration.cross_exposure.pooled_pairs``; validation.md, "Clipped targets
counted in the spline's pools").
"""

from __future__ import annotations

import numpy as np

__all__ = ["CENSORED", "uncensored"]

# The share of clipped targets a scored source value may have: dropping that few of the
# targets there moves the mean of the rest by under 0.03 of their noise (a normal's tail).
CENSORED = 0.01


def uncensored(source: np.ndarray, target: np.ndarray, low: float, high: float,
               censored: float = CENSORED) -> np.ndarray:
    """Which values to score: where the target is seldom clipped, judged by the source alone.

    The share of targets at or below ``low`` is fitted as a non-increasing function of the
    source value, the share at or above ``high`` as a non-decreasing one (isotonic
    regression over the distinct source values, weighted by their counts, so a few outliers
    are pooled with their neighbours rather than cutting the range); a source value is kept
    where both shares are at most ``censored``.  Every target at a kept source value is
    scored but the clipped ones themselves (at most ``censored`` of them), so what decides
    is the source, never the target's own noise.

    Args:
        source: the source image's values, one per pixel-channel: its integer codes, or
            any values that order as they do.
        target: the target image's values at the same pixel-channels.
        low, high: the valid range; a target outside it is clipped.
        censored: the largest share of clipped targets a kept source value may have.

    Returns:
        A boolean mask over ``source``: the values to score.
    """
    from scipy.optimize import isotonic_regression

    if source.size == 0:
        return np.zeros(0, dtype=bool)
    if np.issubdtype(source.dtype, np.integer):  # codes: counted, not sorted (10 MP a pair)
        which = source.astype(np.intp)
        count = np.bincount(which)
    else:
        which, count = np.unique(source, return_inverse=True, return_counts=True)[1:]
    seen = count > 0
    below = np.bincount(which, target <= low, count.size)[seen] / count[seen]
    above = np.bincount(which, target >= high, count.size)[seen] / count[seen]
    dark = isotonic_regression(below, weights=count[seen], increasing=False).x
    bright = isotonic_regression(above, weights=count[seen], increasing=True).x
    keep = np.zeros(count.size, dtype=bool)
    keep[seen] = (dark <= censored) & (bright <= censored)
    return keep[which] & (target > low) & (target < high)
