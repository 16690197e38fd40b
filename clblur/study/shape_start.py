"""Starting points for the free-shape ``response_shape`` fit, from the data themselves.

The study's likelihood in the shape parameters (``gamma``, ``rho`` and the ``ExpShape`` warp)
has flat valleys and local minima: started at the paper's Eq. 3 an optimiser often stays near
it, although the camera's curve is S-shaped (a JPEG tone curve) or a display gamma.  Pixels
whose source histogram sits on a single code (every exposure-series step, the still parts of
pairs and stacks) are exactly the data of ``clblur calibrate``'s cross-exposure objective, so
the same fit (``clblur.calibration.cross_exposure.fit_cross_exposure``) gives a curve in a
second; projected onto the study's ``ExpShape`` family it is a start near the right basin.
The start changes where the search begins, never what is tested: the fitted model is still
the nested ``ExpShape`` with its likelihood maximised on one fold and scored on the other.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from clblur.calibration.cross_exposure import fit_cross_exposure
from clblur.responses import ExpShape, MonotoneSpline, default_knots, warp_basis
from clblur.study.effects import PARAMS, black_levels
from clblur.study.model import WARP_KEYS, Group

__all__ = ["shape_starts"]

_MIN_POOLS = 24  # distinct (source code, ratio) pools below which no curve is fitted
_SHAPE = ("gamma", "rho", *WARP_KEYS)


def shape_starts(groups: list[Group], start: dict[str, float]) -> list[dict[str, float]]:
    """``start`` with its shape parameters replaced by the projected cross-exposure curve.

    Parameters
    ----------
    groups : list of Group
        The groups being fitted (one fold).
    start : dict
        The current parameters; its black levels and ``gain`` are used, the rest is kept.

    Returns
    -------
    list of dict
        Two starts (the projection begun from Eq. 3 and from a display gamma), or none when
        fewer than ``_MIN_POOLS`` single-code pools with a ratio other than 1 exist.
    """
    curve = _cross_exposure_curve(groups, float(start.get("gain", 0.0)))
    if curve is None:
        return []
    u, x_knots, lo, hi = curve
    # the curve pools every channel's codes: their mean black level normalises it
    levels = black_levels(start, groups[0].channels)
    black = sum(levels) / len(levels)
    v = np.linspace(max(lo, black + 0.02), min(hi, 0.97), 48)
    if v[0] >= v[-1]:
        return []
    target = np.log(np.maximum(np.interp(v, u, x_knots), 1e-12))
    w = np.clip((v - black) / (1.0 - black), 1e-6, 1 - 1e-6)
    basis = warp_basis(w, len(WARP_KEYS))
    lower = [PARAMS[n][1] for n in _SHAPE] + [-np.inf]
    upper = [PARAMS[n][2] for n in _SHAPE] + [np.inf]

    def resid(q):  # log inverse of ExpShape; q[-1] a free exposure offset (the unit cancels)
        return ExpShape.log_shape_inverse(w, q[0], q[1]) + q[2:-1] @ basis + q[-1] - target

    out = []
    for g0, r0 in ((1.0, 1.0), (2.2, 0.05)):
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            sol = least_squares(resid, [g0, r0, *([0.0] * len(WARP_KEYS)), 0.0],
                                bounds=(lower, upper))
        out.append({**start, **dict(zip(_SHAPE, (float(t) for t in sol.x[:-1]), strict=True))})
    return out


def _cross_exposure_curve(groups: list[Group], gain: float):
    """Knots and knot exposures of the spline fitted to the single-code pixels (cached on
    the first group per gain), with the 1st..99th percentile of the source values."""
    cache = groups[0].__dict__.setdefault("_shape_curve", {})
    key = round(gain, 4)
    if key in cache:
        return cache[key]
    src, tgt, ratio = [], [], []
    for g in groups:
        h = g.hist.get((0, 0))
        if h is None:
            continue
        r_all = np.broadcast_to(np.asarray(g.ratio, np.float64), g.rows.shape)
        for c in range(g.channels):
            m = h[c].tocsr()
            ok = (np.diff(m.indptr) == 1) & g.valid[:, c]
            code = m.indices[m.indptr[:-1][ok]]
            t = g.target[ok, c]
            keep = (code > 2) & (code < 253) & (t > 2) & (t < 253)
            src.append(code[keep].astype(np.float64))
            tgt.append(t[keep])
            ratio.append(r_all[ok][keep] * np.exp(gain))
    result = None
    if src:
        src, tgt, ratio = (np.concatenate(a) for a in (src, tgt, ratio))
        moving = np.abs(np.log(np.maximum(ratio, 1e-300))) > 1e-3  # ratio 1 shows no shape
        src, tgt, ratio = src[moving], tgt[moving], ratio[moving]
        key_r = np.unique(ratio, return_inverse=True)[1]
        uniq, inv, count = np.unique(src + 256.0 * key_r, return_inverse=True,
                                     return_counts=True)
        if uniq.size >= _MIN_POOLS:
            mean = np.bincount(inv, weights=tgt) / count / 255.0
            pool_ratio = np.bincount(inv, weights=ratio) / count
            u = default_knots(16)
            theta = fit_cross_exposure(u, (uniq % 256.0) / 255.0, mean, pool_ratio,
                                       np.sqrt(count) * 255.0, 0.3)
            lo, hi = np.percentile(src, [1, 99]) / 255.0
            result = (u, MonotoneSpline.knot_exposures(theta), float(lo), float(hi))
    cache[key] = result
    return result
