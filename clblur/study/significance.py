"""Test statistics of per-block held-out improvements.

``t_test``: the one-sided t statistic of the mean improvement over blocks and its p-value
(Student's t with ``B - 1`` degrees of freedom); ``weighted_test``: the same with block
weights, robust to blocks of very different size.

Conventions
-----------
``d``: held-out improvement per block (nats; positive favours the extension).  Returns
``(statistic, p_value)``, the p-value one-sided.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

__all__ = ["t_test", "weighted_test"]


def t_test(d: np.ndarray) -> tuple[float, float]:
    """One-sided t statistic and p-value that the mean of ``d`` is > 0."""
    if d.size < 3:
        return 0.0, 1.0
    sd = float(d.std(ddof=1))
    if sd <= 1e-12 * max(1.0, float(np.abs(d).max())):
        return 0.0, 1.0
    t = float(d.mean()) / (sd / math.sqrt(d.size))
    return t, float(stats.t.sf(t, d.size - 1))


def weighted_test(d: np.ndarray, u: np.ndarray, a: np.ndarray) -> tuple[float, float]:
    """One-sided test that the summed held-out gain ``sum d`` is > 0, block-robust.

    ``T = sum d_b / sqrt(sum u_b^2)`` (a cluster-robust Wald statistic: pixels inside a block
    may be correlated, blocks are nearly independent); Student's t with Satterthwaite's
    degrees of freedom ``(sum a)^2 / sum a^2 - 1``, so a gain carried by a few blocks is
    judged with the few degrees of freedom those blocks give.  See ``Folds.block_score``.
    """
    if d.size < 2:
        return 0.0, 1.0
    v = float((u * u).sum())
    if v <= 1e-300 or float(a.sum()) <= 0:
        return 0.0, 1.0
    t = float(d.sum()) / math.sqrt(v)
    df = max(1.0, min(d.size - 1.0, float(a.sum()) ** 2 / float((a * a).sum()) - 1.0))
    return t, float(stats.t.sf(t, df))
