"""What the extended model leaves: a held-out test for structure no effect explains.

The vocabulary (``clblur.study.effects``) names the causes the study knows.  Real data can
hold others (an in-camera tone curve that changes from frame to frame, flare, a sensor's
soft knee), and a report that lists only the named effects would pass over them.  So after
the selection the extended model is tested against a flexible alternative that names no
cause: an offset of its own for every bin of code (per channel), and, as a second
alternative, for every bin of every pair or step (``group``); the code a value is binned by
is the model's estimate of its noise-free level (``_level``).  The offsets of one fold are
the mean residuals of that fold's own fit (weighted by the model's precision; its own rows
only), and they are scored on the other fold's blocks exactly as an effect is
(``Folds.block_score``: per-block held-out gain, the block-robust ``weighted_test``, the
least gain ``MIN_GAIN``).  Where neither alternative predicts the held-out blocks
significantly better, the model's mean is adequate to the precision of the data; where one
does, the report names the codes (and pairs) where the data depart from the model, and by
how much.

Conventions
-----------
Codes are the study's 8-bit codes.  Bins: ``CODE_BIN`` codes for the pooled alternative,
``GROUP_BIN`` per group; a bin with fewer than ``MIN_COUNT`` valid values in a fold keeps
offset 0 there.  The two alternatives share the study's false-positive rate
(Bonferroni: ``alpha / 2`` each).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from clblur.study.crossfit import block_terms
from clblur.study.model import observed_mean
from clblur.study.significance import weighted_test
from clblur.study.variants import predict

if TYPE_CHECKING:
    from clblur.study.crossfit import Folds
    from clblur.study.model import Group

__all__ = ["CODE_BIN", "GROUP_BIN", "MIN_COUNT", "leftover", "describe"]

CODE_BIN = 16.0
GROUP_BIN = 32.0
MIN_COUNT = 20


def _level(g: Group, p: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The prediction and variance of ``g``'s values under ``p``, and the code each value
    is binned by: the prediction moved towards the observation by the share of the
    variance that the source's noise carries, ``pred + share (y - pred)``.

    Why not the prediction alone: it is read from the source's noisy codes, and a source
    code the noise pushed up predicts too high where few pixels are brighter (regression to
    the mean), so binned by prediction the residuals of a true model run from positive at a
    pair's low codes to negative at its high codes.  On noisy null series (``a = 1e-3``)
    that read as structure left on 3 of 10 seeds.  The residual is uncorrelated with this
    estimate of the noise-free code (to first order, for Gaussian noise), so a true model
    leaves no offset by it, and a real departure, a function of the true code, still shows.
    """
    pred, var, share = predict(g, p, source_share=True)
    pred = observed_mean(g, pred, var)  # a kept value's mean (``model.observed_mean``)
    return pred, var, pred + share * np.where(g.valid, g.target - pred, 0.0)


def _keys(level: np.ndarray, rows_group: np.ndarray | None, width: float,
          channels: int) -> np.ndarray:
    """Bin id of every (row, channel) value: channel and the bin of its code ``level``
    (``_level``), and the row's group where ``rows_group`` is given."""
    nbins = int(np.ceil(256.0 / width))
    b = np.clip((level // width).astype(np.int64), 0, nbins - 1)
    key = b + nbins * np.arange(channels)[None, :]
    if rows_group is not None:
        key = key + (nbins * channels) * rows_group[:, None]
    return key


def _offsets(folds: Folds, own: list[list[tuple]], f: int, block_group: np.ndarray | None,
             width: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Fold ``f``'s mean residual per bin under its own fit (precision-weighted; ``own``:
    ``_level`` of each fold's groups under that fold's fit), and the count of valid values
    behind each; bins with fewer than ``MIN_COUNT`` get 0."""
    num = np.zeros(size)
    den = np.zeros(size)
    cnt = np.zeros(size)
    for g, (pred, var, level) in zip(folds.part[f], own[f], strict=True):
        rg = None if block_group is None else block_group[g.block]
        key = _keys(level, rg, width, g.channels)[g.valid]
        w = 1.0 / var[g.valid]
        num += np.bincount(key, w * (g.target - pred)[g.valid], minlength=size)
        den += np.bincount(key, w, minlength=size)
        cnt += np.bincount(key, minlength=size)
    out = np.where(cnt >= MIN_COUNT, num / np.maximum(den, 1e-300), 0.0)
    return out, cnt


def _alternative(folds: Folds, own: list[list[tuple]], held: list[list[tuple]],
                 used: np.ndarray, block_group: np.ndarray | None, width: float,
                 ngroups: int) -> dict:
    """One alternative's offsets and held-out test (``own``/``held``: ``_level`` of each
    fold's groups under its own fit and under the other fold's)."""
    channels = folds.part[0][0].channels
    nbins = int(np.ceil(256.0 / width))
    size = nbins * channels * (ngroups if block_group is not None else 1)
    fitted = [_offsets(folds, own, f, block_group, width, size) for f in (0, 1)]
    terms = np.zeros((3, folds.nblocks))
    for f in (0, 1):
        offsets = fitted[1 - f][0]  # learnt on the other fold's own rows
        for g, (pb, var, level) in zip(folds.part[f], held[f], strict=True):
            rg = None if block_group is None else block_group[g.block]
            pe = pb + offsets[_keys(level, rg, width, channels)]
            terms += block_terms(g, pb, pe, var, folds.nblocks)
    d, u, a = terms
    reach = used & (a > 1e-12)
    t, p = weighted_test(d[reach], u[reach], a[reach])
    count = fitted[0][1] + fitted[1][1]
    mean = np.where(count > 0, (fitted[0][0] * fitted[0][1] + fitted[1][0] * fitted[1][1])
                    / np.maximum(count, 1), 0.0)
    return {"d": float(d[reach].sum()), "statistic": t, "p_value": p, "offsets": mean,
            "counts": count, "width": width, "nbins": nbins, "channels": channels}


def leftover(folds: Folds, params: list[dict], used: np.ndarray, groups: list[Group],
             alpha: float, min_gain: float) -> dict:
    """Test the model ``params`` (per fold) against per-bin offsets (module doc).

    Args:
        folds: the selection's ``crossfit.Folds``.
        params: the extended model's fit on each fold.
        used: the blocks that hold held-out values.
        groups: the study's groups (their ``block`` ids name each pair or step).
        alpha: the study's false-positive rate; ``min_gain``: the least held-out gain, nats
            per value, that counts (``select.MIN_GAIN``).

    Returns:
        A dict: ``structure`` (bool: either alternative significant and worth its gain),
        ``channels``, and per alternative (``by_code``, ``by_group``) its ``statistic``,
        ``p_value``, ``gain`` (held-out nats per value), ``significant`` and the
        ``largest`` departures (up to five bins: channel, codes, group name, mean offset in
        codes, values); ``by_code`` also its whole profile: ``offsets`` and ``counts``
        (channels x bins, both folds pooled) and ``bin_codes``, the bin's width.
    """
    nvalid = max(sum(folds.nvalid), 1)
    block_group = np.zeros(folds.nblocks, np.int64)
    for gi, g in enumerate(groups):
        block_group[g.block] = gi
    names = [g.name for g in groups]
    # each fold's values under its own fit (the offsets) and the other's (the test), once
    own = [[_level(g, params[f]) for g in folds.part[f]] for f in (0, 1)]
    held = [[_level(g, params[1 - f]) for g in folds.part[f]] for f in (0, 1)]
    out: dict = {}
    for label, bg, width in (("by_code", None, CODE_BIN), ("by_group", block_group, GROUP_BIN)):
        r = _alternative(folds, own, held, used, bg, width, len(groups))
        gain = r["d"] / nvalid
        significant = bool(r["p_value"] < alpha / 2 and gain >= min_gain)
        out[label] = {"statistic": r["statistic"], "p_value": r["p_value"], "gain": gain,
                      "significant": significant, "largest": _largest(r, names)}
        if bg is None:  # the whole profile, per channel (``report.figures``' leftover.png)
            shape = (r["channels"], r["nbins"])
            out[label]["offsets"] = r["offsets"].reshape(shape).tolist()
            out[label]["counts"] = r["counts"].reshape(shape).astype(int).tolist()
            out[label]["bin_codes"] = r["width"]
    out["structure"] = out["by_code"]["significant"] or out["by_group"]["significant"]
    out["channels"] = folds.part[0][0].channels
    return out


def _largest(r: dict, names: list[str], n: int = 5) -> list[dict]:
    """The bins with the largest evidence of an offset (``|offset| sqrt(count)``)."""
    off, cnt = r["offsets"], r["counts"]
    nb, ch = r["nbins"], r["channels"]
    order = np.argsort(-np.abs(off) * np.sqrt(cnt))
    out = []
    for k in order[:n]:
        if cnt[k] == 0 or off[k] == 0.0:
            break
        b, c, gi = int(k % nb), int((k // nb) % ch), int(k // (nb * ch))
        item = {"channel": c, "codes": [b * r["width"], min((b + 1) * r["width"], 256.0)],
                "offset_codes": float(off[k]), "values": int(cnt[k])}
        if len(off) > nb * ch:
            item["group"] = names[gi]
        out.append(item)
    return out


def describe(result: dict) -> str:
    """One paragraph for the report (``result``: ``leftover``'s, or its JSON form)."""
    parts = []
    for label, what in (("by_code", "an offset per bin of code"),
                        ("by_group", "an offset per bin of code in each pair or step")):
        r = result[label]
        parts.append(f"{what}: held-out gain {r['gain']:.3g} nats per value, "
                     f"t = {r['statistic']:.2f}, p = {r['p_value']:.2g}")
    if not result["structure"]:
        return ("What the model leaves: no structure. Tested against " + "; ".join(parts)
                + ". Neither predicts the held-out blocks both significantly better and by "
                "the least gain that counts, so the extended model's mean is adequate to "
                "the precision of these data.")
    # the alternative that gains the more, of those that count, says where
    label = max((k for k in ("by_code", "by_group") if result[k]["significant"]),
                key=lambda k: result[k]["gain"])
    spots = []
    for item in result[label]["largest"][:3]:
        where = f"codes {item['codes'][0]:.0f}-{item['codes'][1]:.0f}"
        if result["channels"] > 1:
            where += f" of channel {item['channel']}"
        if "group" in item:
            where += f" in {item['group']}"
        spots.append(f"{where}: {item['offset_codes']:+.2f} codes ({item['values']} values)")
    causes = ("a cause outside the vocabulary (a tone curve that changes between frames, "
              "flare, a soft knee, processing that depends on the image) or a named effect "
              "of the wrong form")
    if label == "by_group":
        causes += (", or, where a few pairs or steps carry it, something of their own (a "
                   "pair's kernel or alignment, a frame's exposure or processing)")
    return ("What the model leaves: structure that no effect of the vocabulary explains. "
            "Tested against " + "; ".join(parts) + ". The data depart from the extended "
            "model most at " + "; ".join(spots) + " (observed minus the model, by the "
            "model's estimate of the noise-free code). At work there: " + causes + ".")
