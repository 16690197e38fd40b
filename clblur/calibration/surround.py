"""Does the held-out error depend on the surround?  Calibration's check for local tone mapping.

A response curve maps a pixel's light to its code whatever lies around it.  A camera that
renders each region by its own brightness does not: Canon's Auto Lighting Optimizer, Nikon's
Active D-Lighting, Sony's DRO and every phone's HDR rendering lift shadows in dark regions
and hold highlights down in bright ones, so one light gets two codes in two surrounds, and
across a bracket the lift changes as a region brightens.  The curve ``calibrate`` fits to
such a bracket is an average over surrounds, and blurring through it puts light where the
camera did not.  No curve per channel can hold the difference, so the check asks the data
directly: at one code, does the held-out prediction error depend on how bright the pixel's
surround is?

Test
----
* Values: the held-out pixels of ``clblur.calibration.evaluate`` (never sampled, static,
  the source valid and the target seldom clipped, both images intact; at most
  ``MAX_PIXELS`` of them), *flat* in both images: the 3 x 3 means of the codes span at most
  ``FLAT_TOLERANCE`` of full scale over the pixel's 3 x 3 neighbourhood (an edge's
  misregistration, sharpening halo or demosaicing depends on its neighbourhood too, at a
  few pixels' scale, and is not what is asked; the means, so that a high-ISO bracket's
  noise does not leave no flat pixel).  Pairs: every pair of the evaluated gaps, the target
  the darker image (the source's noise compressed, as in ``compare.selection_score``).
  Residual: the prediction through the chosen model fitted on all images, minus the
  target, in code values.  No curve can take up a dependence on the surround, so leaving
  the target out would change only what the base absorbs.
* The code a value is placed by is the mean of its source pixel's 8 neighbours, not its
  own: binned by its own noisy code, a value pushed up by noise is predicted too high
  where brighter pixels are rare (regression to the mean), and how rare they are differs
  between dark and bright surrounds, which read as a dependence on the surround on
  plain noisy brackets (t up to 2.7 before this choice, on the nulls of the tests).
* Base: per pair and channel, a piecewise-linear function of that code with knots
  ``KNOT_STEP`` codes apart (what another curve, or the pair's exposure ratio, could
  absorb).  Alternative: the base plus an offset per ``CODE_BIN`` codes and
  ``SURROUND_BIN`` codes of the target's surround (``surround_codes``); a cell with fewer
  than ``MIN_COUNT`` values keeps 0.
* Cross-fitted on a checkerboard of ``GRID`` x ``GRID`` blocks: both are fitted on one
  colour's blocks and scored on the other's.  Gain of a value: its squared error under the
  base minus under the alternative; per block, summed.  Under no dependence the held-out
  gain is at most 0 (the finer offsets only fit noise), so ``t = sum d_b / sqrt(sum d_b^2)``
  over the blocks (pixels in a block may be correlated, blocks nearly independent), one-
  sided, Student's t with ``B - 1`` degrees of freedom.
* Reported when ``p < alpha`` *and* the gain per value, as a root mean square offset, is at
  least ``MIN_OFFSET`` codes of 255 (scaled to the series' depth), half a code, the most the
  rounding to codes moves a value itself: a trace of a tenth of a code (a wrong curve's
  error changes faster than the base's knots follow) can be significant on millions of
  pixels and is harmless to a blur.  A significant trace below it is named as one.
* Only codes that the series shows in two or more surrounds can tell; fewer than
  ``MIN_CONTRAST`` such values and the verdict is "not tested", not "no dependence".
* Limit: an edge-aware tone mapping (its surround stops at edges, as cameras' halo-free
  ones do) lifts a flat region by a function of that region's own level, which a curve
  holds; what no curve holds lies at edges and in textures, which the flat test leaves out.
  Such a bracket shows as a trace (``docs/studies/validation.md``, "Calibration's check for
  local tone mapping").  Textures are left out on purpose: there a camera's noise
  reduction, stronger in the darker frame, flattens the texture, which lifts a pixel darker
  than its surround and lowers a brighter one, the same signature as a local lift.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from clblur.calibration.evaluate import FLAT_TOLERANCE, local_range
from clblur.calibration.fitting import ResponseFit, transfer

if TYPE_CHECKING:
    from clblur.calibration.evaluate import HeldOut
    from clblur.calibration.series import ExposureSeries

__all__ = ["ALPHA", "CODE_BIN", "GRID", "KNOT_STEP", "MAX_PIXELS", "MIN_CONTRAST", "MIN_COUNT",
           "MIN_OFFSET",
           "SURROUND_BIN", "SURROUND_SCALE", "describe", "surround_codes",
           "surround_dependence"]

# the width (Gaussian sigma) of a pixel's surround, as a share of the image diagonal: wide
# enough to hold a region's brightness rather than an edge's (13 px on a 240 x 360 image,
# 146 px on a 10 MP one), as local tone mapping adapts to a region
SURROUND_SCALE = 1.0 / 32.0
CODE_BIN = 16.0  # codes of 256: the bins of the alternative
KNOT_STEP = 8.0  # codes of 256 between the base's knots (finer: it is the code's own share)
SURROUND_BIN = 64.0  # codes of 256 of the surround (the study's bins)
GRID = 12
MIN_COUNT = 20
MIN_OFFSET = 0.5  # codes of 255
MAX_PIXELS = 2_000_000
# values whose code the series shows in two or more surrounds (cells of ``MIN_COUNT`` in
# both folds) that a test needs; fewer: "not tested"
MIN_CONTRAST = 2000
ALPHA = 1e-3


def surround_codes(image: np.ndarray) -> np.ndarray:
    """The brightness of every pixel's surround: the mean code over the channels of
    ``image`` (H x W x C), Gaussian-weighted with sigma ``SURROUND_SCALE`` times the image
    diagonal (edges mirrored).  H x W float64, in the image's codes.

    A sigma over 32 px is blurred on a copy reduced by ``sigma // 8`` (area averages) and
    brought back bilinearly: a 10 MP image's 146 px Gaussian costs 0.56 s instead of 12.5 s,
    within 0.1 code of the exact one (``docs/studies/validation.md``, "The study's surround,
    now shared").
    """
    import cv2

    h, w = image.shape[:2]
    mean = image.reshape(h, w, -1).mean(axis=2, dtype=np.float64).astype(np.float32)
    sigma = SURROUND_SCALE * math.hypot(h, w)
    factor = int(sigma // 8) if sigma > 32 else 1
    if factor > 1:
        small = cv2.resize(mean, (max(1, round(w / factor)), max(1, round(h / factor))),
                           interpolation=cv2.INTER_AREA)
        small = cv2.GaussianBlur(small, (0, 0), sigma / factor,
                                 borderType=cv2.BORDER_REFLECT)
        out = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    else:
        out = cv2.GaussianBlur(mean, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return out.astype(np.float64)


def _local(image: np.ndarray, coords: np.ndarray, tolerance: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """At ``coords``, per channel: the mean code of each pixel's 8 neighbours (an estimate
    of its noise-free code that does not hold its own noise), and whether it is flat: its
    3 x 3 neighbourhood spans at most ``tolerance`` codes in the image's 3 x 3 means (so
    that the noise of a high-ISO bracket does not leave no flat pixel, and an edge of that
    contrast still counts as one)."""
    import cv2

    img = image.astype(np.float32)
    c = img.shape[2]
    box = cv2.boxFilter(img, -1, (3, 3), normalize=False,
                        borderType=cv2.BORDER_REFLECT).reshape(img.shape)
    neighbours = (box - img).reshape(-1, c)[coords] / 8.0
    return neighbours, local_range(box / 9.0, coords) <= tolerance


def _knots(source: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Each value's knot interval ``k`` and its place ``u`` in [0, 1) between knots ``k``
    and ``k + 1`` (``KNOT_STEP`` codes of 256 apart)."""
    x = source / (step * KNOT_STEP)
    k = np.clip(np.floor(x).astype(np.int64), 0, int(256 // KNOT_STEP) - 1)
    return k, np.clip(x - k, 0.0, 1.0)


def _base(k: np.ndarray, u: np.ndarray, e: np.ndarray, nk: int) -> np.ndarray:
    """Least-squares offsets at the ``nk + 1`` knots of a piecewise-linear function of the
    code (a unit pseudo-value at 0 on each knot keeps an empty one at 0): what any smooth
    change of the curve over the pair could absorb, a slope inside a bin included."""
    n = nk + 1
    a = np.zeros((n, n))
    diag = (np.bincount(k, (1 - u) ** 2, minlength=n) + np.bincount(k + 1, u * u, minlength=n))
    off = np.bincount(k, (1 - u) * u, minlength=n)[:nk]
    a[np.arange(n), np.arange(n)] = diag + 1.0
    a[np.arange(nk), np.arange(1, n)] = off
    a[np.arange(1, n), np.arange(nk)] = off
    rhs = np.bincount(k, (1 - u) * e, minlength=n) + np.bincount(k + 1, u * e, minlength=n)
    return np.linalg.solve(a, rhs)


def _at(knots: np.ndarray, k: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The piecewise-linear function with values ``knots`` at interval ``k``, place ``u``."""
    return knots[k] * (1 - u) + knots[k + 1] * u


def _offsets(key: np.ndarray, r: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``r`` per cell (0 where fewer than ``MIN_COUNT`` values), and the counts."""
    cnt = np.bincount(key, minlength=size).astype(np.float64)
    total = np.bincount(key, r, minlength=size)
    return np.where(cnt >= MIN_COUNT, total / np.maximum(cnt, 1.0), 0.0), cnt


def surround_dependence(series: ExposureSeries, fit_result: ResponseFit, held: HeldOut,
                        pairs: list[tuple[int, int]], *, alpha: float = ALPHA,
                        min_offset: float = MIN_OFFSET) -> dict:
    """Test whether the held-out error of ``fit_result`` depends on the surround (module doc).

    Args:
        series: the exposure series.
        fit_result: the chosen model's fit on all images.
        held: the held-out values (``evaluate.held_out``).
        pairs: (source, target) image indices, the target the darker image.
        alpha: the false-positive rate; ``min_offset``: the least root mean square offset,
            codes of 255, that counts.

    Returns:
        A dict: ``tested`` (bool: at least ``MIN_CONTRAST`` values have a code the series
        shows in two or more surrounds, ``contrast_values``), ``dependent`` (bool: tested,
        significant and at least ``min_offset``), ``statistic``,
        ``p_value``, ``offset_codes`` (the held-out gain as a root mean square offset, code
        values of the series), ``min_offset_codes``, ``values``, ``blocks``, ``pairs``, and
        ``largest`` (up to five cells: source, target, channel, codes, surround codes, the
        offset beyond the code's own, values), codes in the series' code values.
    """
    full = series.full_scale
    h, w = series.shape
    step = (full + 1.0) / 256.0  # one code of 256 in the series' codes
    nk, nb, ns = int(256 // KNOT_STEP), int(256 // CODE_BIN), int(256 // SURROUND_BIN)
    # at most MAX_PIXELS of the held-out pixels (a fixed random subset): enough for the
    # test, and a 24 MP bracket's local means stay a few hundred MB
    sel = np.arange(held.size)
    if held.size > MAX_PIXELS:
        sel = np.sort(np.random.default_rng(0).choice(held.size, MAX_PIXELS, replace=False))
    coords = held.coords[sel]
    rows, cols = np.divmod(coords, w)
    block = (rows * GRID // h) * GRID + cols * GRID // w
    fold = ((rows * GRID // h) + (cols * GRID // w)) % 2
    gain = np.zeros(GRID * GRID)
    count = np.zeros(GRID * GRID)
    cells: list[dict] = []
    contrast = 0
    surrounds: dict[int, np.ndarray] = {}
    local: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    tau = series.relative_exposures()
    for k in {k for pair in pairs for k in pair}:
        local[k] = _local(series.images[k], coords, FLAT_TOLERANCE * full)
    for i, j in pairs:
        if j not in surrounds:
            surrounds[j] = surround_codes(series.images[j]).reshape(-1)[coords]
        ratio = float(tau[j] / tau[i])
        sbin_all = np.clip((surrounds[j] / step // SURROUND_BIN).astype(np.int64), 0, ns - 1)
        for c in range(series.channels):
            m = held.scored(i, j, c)[sel] & local[i][1][:, c] & local[j][1][:, c]
            if not m.any():
                continue
            source = held.codes[i][sel[m], c].astype(np.float64)
            target = held.codes[j][sel[m], c].astype(np.float64)
            e = transfer(fit_result.responses[c], source / full, ratio) * full - target
            kb, u = _knots(local[i][0][m, c], step)
            ka = (kb * int(KNOT_STEP) // int(CODE_BIN)) * ns + sbin_all[m]
            f, b = fold[m], block[m]
            on = [f == 0, f == 1]
            knots = [_base(kb[o], u[o], e[o], nk) for o in on]
            resid = [e[o] - _at(knots[k], kb[o], u[o]) for k, o in enumerate(on)]
            alt = [_offsets(ka[o], resid[k], nb * ns) for k, o in enumerate(on)]
            for k, o in enumerate(on):  # score fold k with the other fold's fit
                rb = e[o] - _at(knots[1 - k], kb[o], u[o])
                d = rb**2 - (rb - alt[1 - k][0][ka[o]]) ** 2
                gain += np.bincount(b[o], d, minlength=gain.size)
                count += np.bincount(b[o], minlength=count.size)
            # the pooled offsets beyond the code's own (each fold's on its own base), for
            # the report
            cnt_a = alt[0][1] + alt[1][1]
            # what the test can see: codes met in two or more surrounds, in both folds
            seen = [(a[1] >= MIN_COUNT).reshape(nb, ns) for a in alt]
            both = (seen[0].sum(axis=1) >= 2) & (seen[1].sum(axis=1) >= 2)
            contrast += int(cnt_a.reshape(nb, ns)[seen[0] & seen[1] & both[:, None]].sum())
            beyond = (alt[0][0] * alt[0][1] + alt[1][0] * alt[1][1]) / np.maximum(cnt_a, 1.0)
            for cell in np.flatnonzero(cnt_a >= 2 * MIN_COUNT):
                cells.append({"source": series.names[i], "target": series.names[j],
                              "channel": c, "cell": int(cell), "beyond": float(beyond[cell]),
                              "values": int(cnt_a[cell])})
    used = count > 0
    d, n = gain[used], count[used]
    values = int(n.sum())
    t, p = 0.0, 1.0
    if d.size >= 3 and float((d * d).sum()) > 0:
        t = float(d.sum() / math.sqrt(float((d * d).sum())))
        p = float(stats.t.sf(t, d.size - 1))
    per_value = float(d.sum() / values) if values else 0.0
    offset = math.sqrt(max(per_value, 0.0))
    least = min_offset * full / 255.0
    cells.sort(key=lambda x: -abs(x["beyond"]) * math.sqrt(x["values"]))
    largest = []
    for x in cells[:5]:
        code, s = divmod(x["cell"], ns)
        largest.append({"source": x["source"], "target": x["target"], "channel": x["channel"],
                        "codes": [code * CODE_BIN * step, (code + 1) * CODE_BIN * step],
                        "surround_codes": [s * SURROUND_BIN * step,
                                           min((s + 1) * SURROUND_BIN * step, full + 1.0)],
                        "offset_codes": x["beyond"], "values": x["values"]})
    tested = contrast >= MIN_CONTRAST
    return {"tested": tested, "dependent": bool(tested and p < alpha and offset >= least),
            "statistic": t, "p_value": p, "alpha": alpha, "offset_codes": offset,
            "min_offset_codes": least, "values": values, "contrast_values": contrast,
            "blocks": int(d.size), "pairs": len(pairs), "largest": largest}


def describe(result: dict, channels: int = 3) -> str:
    """One paragraph for the report and the command line (``result``:
    ``surround_dependence``'s)."""
    head = (f"held-out error by the surround's brightness (flat pixels, darker targets, "
            f"{result['pairs']} pair(s), {result['values']} values, {result['blocks']} "
            f"blocks): t = {result['statistic']:.2f}, p = {result['p_value']:.2g}, "
            f"offsets {result['offset_codes']:.2f} codes root mean square beyond the code's "
            f"own (counts from {result['min_offset_codes']:.3g})")
    if not result.get("tested", True):
        return (f"Surround: not tested. Only {result.get('contrast_values', 0)} flat held-out "
                f"values (of {result['values']}) have a code that the series shows in two or "
                f"more surrounds, {MIN_CONTRAST} needed: too few to tell whether the camera's "
                "rendering depends on the neighbourhood (local tone mapping).")
    if not result["dependent"]:
        if result["p_value"] < result["alpha"]:  # many values see a trace no blur would
            return ("Surround: a trace only. The " + head + ": significant on this many "
                    "values, but below the least offset that counts: no local tone mapping "
                    "worth the name on flat pixels (an edge-aware one, which follows each "
                    "region's own level, can show there as no more than such a trace).")
        return ("Surround: no dependence. The " + head + ". The error at a code does not "
                "depend on the surround: no sign of local tone mapping.")
    spots = []
    for x in result["largest"][:3]:
        where = f"codes {x['codes'][0]:.0f}-{x['codes'][1]:.0f}"
        if channels > 1:
            where += f" of channel {x['channel']}"
        lo, hi = x["surround_codes"]
        spots.append(f"{where} in surrounds of {lo:.0f}-{hi:.0f}, {x['target']} from "
                     f"{x['source']}: {x['offset_codes']:+.2f} codes ({x['values']} values)")
    return ("Surround: the error DEPENDS on it. The " + head + "; most at " + "; ".join(spots)
            + " (prediction minus the image). One light gets different codes in dark and "
            "bright regions: the camera's processing adapts to the neighbourhood (local tone "
            "mapping: Canon's Auto Lighting Optimizer, Nikon's Active D-Lighting, Sony's DRO, "
            "a phone's HDR rendering), or charge blooms next to clipped highlights. No curve "
            "holds that; this one is an average over the surrounds. Shoot the bracket with "
            "that processing off, or from raw.")
