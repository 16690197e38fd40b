"""What the extended model leaves: a held-out test for structure no effect explains.

The vocabulary (``clblur.study.effects``) names the causes the study knows.  Real data can
hold others (an in-camera tone curve that changes from frame to frame, flare, a sensor's
soft knee, local tone mapping), and a report that lists only the named effects would pass
over them.  So after the selection the extended model is tested against flexible
alternatives that name no cause: an offset of its own for every bin of code (per channel);
for every bin of every pair or step (``group``); and for every bin of code and of the
brightness of the pixel's surround (``Group.surround``).  The code a value is binned by is
the model's estimate of its noise-free level (``_level``).  The offsets of one fold are the
mean residuals of that fold's own fit (weighted by the model's precision; its own rows
only), and they are scored on the other fold's blocks exactly as an effect is
(``Folds.block_score``: per-block held-out gain, the block-robust ``weighted_test``, the
least gain ``MIN_GAIN``).  Where no alternative predicts the held-out blocks significantly
better, the model's mean is adequate to the precision of the data; where one does, the
report names the codes (and pairs, or surrounds) where the data depart from the model, and
by how much.

Why the surround: every effect of the vocabulary, and the response itself, maps a pixel's
light to its code whatever lies around it.  A camera that adapts its rendering to the
neighbourhood (local tone mapping: shadows in dark regions lifted, highlights in bright
ones held down, as Canon's Auto Lighting Optimizer, Nikon's Active D-Lighting, Sony's DRO
and every phone's HDR rendering do) gives one light two codes in two surrounds, and across
exposures the lift changes as a region's brightness does.  A pure power of the local
brightness (``x -> x g(L)`` with ``log g`` linear in ``log L``) changes every exposure
ratio by one factor and is the exposure and the response's exponent again; anything else
leaves, at one code, a residual that depends on the surround.  That alternative is tested
against the one by code (its offsets as the base), so a departure that depends on the code
alone is not read as the surround's.

Conventions
-----------
Codes are the study's 8-bit codes.  Bins: ``CODE_BIN`` codes for the pooled alternative,
``GROUP_BIN`` per group, ``CODE_BIN`` by ``SURROUND_BIN`` codes of the surround (the mean
code over the channels, Gaussian-weighted over ``SURROUND_SCALE`` of the image diagonal:
``clblur.calibration.surround``, which calibration's own check shares); a bin with fewer
than ``MIN_COUNT`` valid values in a fold keeps offset 0 there.
The alternatives share the study's false-positive rate (Bonferroni: ``alpha / 3`` each,
``alpha / 2`` where the groups know no surrounds).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from clblur.study.crossfit import block_terms
from clblur.study.model import observed_mean
from clblur.study.significance import weighted_test
from clblur.study.variants import predict

if TYPE_CHECKING:
    from clblur.study.crossfit import Folds
    from clblur.study.model import Group

__all__ = ["CODE_BIN", "GROUP_BIN", "MIN_COUNT", "SURROUND_BIN", "leftover", "describe"]

CODE_BIN = 16.0
GROUP_BIN = 32.0
SURROUND_BIN = 64.0
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


@dataclass(frozen=True)
class _Bins:
    """How one alternative bins the values: by channel and ``width`` codes of the binned
    level (``_level``), and by the row's pair or step (``by_group``) or by its surround's
    brightness in ``SURROUND_BIN`` codes (``by_surround``, ``Group.surround``; a group
    without one has every row in the first bin)."""

    width: float
    channels: int
    ngroups: int = 1  # > 1: by pair or step
    nsurround: int = 1  # > 1: by surround

    @property
    def nbins(self) -> int:
        return int(np.ceil(256.0 / self.width))

    @property
    def size(self) -> int:
        return self.nbins * self.channels * self.nsurround * self.ngroups

    def keys(self, g: Group, level: np.ndarray, block_group: np.ndarray) -> np.ndarray:
        """Bin id of every (row, channel) value of ``g``."""
        nb, nc = self.nbins, self.channels
        b = np.clip((level // self.width).astype(np.int64), 0, nb - 1)
        key = b + nb * np.arange(nc)[None, :]
        if self.nsurround > 1 and g.surround is not None:
            s = np.clip((g.surround // SURROUND_BIN).astype(np.int64), 0, self.nsurround - 1)
            key = key + (nb * nc) * s[:, None]
        if self.ngroups > 1:
            key = key + (nb * nc * self.nsurround) * block_group[g.block][:, None]
        return key

    def where(self, k: int) -> tuple[int, int, int, int]:
        """Bin id ``k`` as (code bin, channel, surround bin, group)."""
        nb, nc, ns = self.nbins, self.channels, self.nsurround
        return k % nb, (k // nb) % nc, (k // (nb * nc)) % ns, k // (nb * nc * ns)


def _offsets(folds: Folds, own: list[list[tuple]], f: int, bins: _Bins,
             block_group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fold ``f``'s mean residual per bin under its own fit (precision-weighted; ``own``:
    ``_level`` of each fold's groups under that fold's fit), and the count of valid values
    behind each; bins with fewer than ``MIN_COUNT`` get 0."""
    num = np.zeros(bins.size)
    den = np.zeros(bins.size)
    cnt = np.zeros(bins.size)
    for g, (pred, var, level) in zip(folds.part[f], own[f], strict=True):
        key = bins.keys(g, level, block_group)[g.valid]
        w = 1.0 / var[g.valid]
        num += np.bincount(key, w * (g.target - pred)[g.valid], minlength=bins.size)
        den += np.bincount(key, w, minlength=bins.size)
        cnt += np.bincount(key, minlength=bins.size)
    out = np.where(cnt >= MIN_COUNT, num / np.maximum(den, 1e-300), 0.0)
    return out, cnt


def _alternative(folds: Folds, own: list[list[tuple]], held: list[list[tuple]],
                 used: np.ndarray, bins: _Bins, block_group: np.ndarray,
                 base: tuple[_Bins, list] | None = None) -> dict:
    """One alternative's offsets and held-out test (``own``/``held``: ``_level`` of each
    fold's groups under its own fit and under the other fold's).  ``base``: another
    alternative's bins and per-fold offsets, tested against instead of the model alone
    (the alternative by surround against the one by code: a departure that depends on the
    code alone is not the surround's)."""
    fitted = [_offsets(folds, own, f, bins, block_group) for f in (0, 1)]
    terms = np.zeros((3, folds.nblocks))
    for f in (0, 1):
        offsets = fitted[1 - f][0]  # learnt on the other fold's own rows
        for g, (pb, var, level) in zip(folds.part[f], held[f], strict=True):
            pe = pb + offsets[bins.keys(g, level, block_group)]
            if base is not None:
                pb = pb + base[1][1 - f][0][base[0].keys(g, level, block_group)]
            terms += block_terms(g, pb, pe, var, folds.nblocks)
    d, u, a = terms
    reach = used & (a > 1e-12)
    t, p = weighted_test(d[reach], u[reach], a[reach])
    count = fitted[0][1] + fitted[1][1]
    mean = np.where(count > 0, (fitted[0][0] * fitted[0][1] + fitted[1][0] * fitted[1][1])
                    / np.maximum(count, 1), 0.0)
    return {"d": float(d[reach].sum()), "statistic": t, "p_value": p, "offsets": mean,
            "counts": count, "fitted": fitted}


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
        A dict: ``structure`` (bool: an alternative significant and worth its gain),
        ``channels``, and per alternative (``by_code``, ``by_group``, and ``by_surround``
        where the groups know their pixels' surrounds) its ``statistic``, ``p_value``,
        ``gain`` (held-out nats per value; ``by_surround``'s beyond ``by_code``'s),
        ``significant`` and the ``largest`` departures (up to five bins: channel, codes,
        group name or surround codes, mean offset in codes, values; ``by_surround``'s
        offset beyond the code's own); ``by_code`` also its whole profile: ``offsets`` and
        ``counts`` (channels x bins, both folds pooled) and ``bin_codes``, the bin's width.
    """
    nvalid = max(sum(folds.nvalid), 1)
    block_group = np.zeros(folds.nblocks, np.int64)
    for gi, g in enumerate(groups):
        block_group[g.block] = gi
    names = [g.name for g in groups]
    channels = folds.part[0][0].channels
    # each fold's values under its own fit (the offsets) and the other's (the test), once
    own = [[_level(g, params[f]) for g in folds.part[f]] for f in (0, 1)]
    held = [[_level(g, params[1 - f]) for g in folds.part[f]] for f in (0, 1)]
    by_code = _Bins(CODE_BIN, channels)
    alternatives = {"by_code": by_code, "by_group": _Bins(GROUP_BIN, channels, len(groups))}
    if any(g.surround is not None for part in folds.part for g in part):
        alternatives["by_surround"] = _Bins(CODE_BIN, channels,
                                            nsurround=int(np.ceil(256.0 / SURROUND_BIN)))
    out: dict = {}
    code_fit = None
    for label, bins in alternatives.items():
        base = None if label != "by_surround" else (by_code, code_fit)
        r = _alternative(folds, own, held, used, bins, block_group, base)
        if label == "by_code":
            code_fit = r["fitted"]
            code_offsets = r["offsets"]
        gain = r["d"] / nvalid
        # the alternatives share the study's false-positive rate (Bonferroni)
        significant = bool(r["p_value"] < alpha / len(alternatives) and gain >= min_gain)
        beyond = None if base is None else code_offsets
        out[label] = {"statistic": r["statistic"], "p_value": r["p_value"], "gain": gain,
                      "significant": significant,
                      "largest": _largest(r, bins, names, beyond)}
        if label == "by_code":  # the whole profile, per channel (``report``'s leftover.png)
            shape = (channels, bins.nbins)
            out[label]["offsets"] = r["offsets"].reshape(shape).tolist()
            out[label]["counts"] = r["counts"].reshape(shape).astype(int).tolist()
            out[label]["bin_codes"] = bins.width
    out["structure"] = any(out[k]["significant"] for k in alternatives)
    out["channels"] = channels
    return out


def _largest(r: dict, bins: _Bins, names: list[str], beyond: np.ndarray | None,
             n: int = 5) -> list[dict]:
    """The bins with the largest evidence of an offset (``|offset| sqrt(count)``);
    ``beyond``: the offsets per code bin and channel (``by_code``'s) that a bin's own is
    reported beyond."""
    off, cnt = r["offsets"], r["counts"]
    if beyond is not None:
        plane = bins.nbins * bins.channels
        off = np.where(off != 0.0, off - beyond[np.arange(off.size) % plane], 0.0)
    order = np.argsort(-np.abs(off) * np.sqrt(cnt))
    out = []
    for k in order[:n]:
        if cnt[k] == 0 or off[k] == 0.0:
            break
        b, c, s, gi = bins.where(int(k))
        item = {"channel": c, "codes": [b * bins.width, min((b + 1) * bins.width, 256.0)],
                "offset_codes": float(off[k]), "values": int(cnt[k])}
        if bins.ngroups > 1:
            item["group"] = names[gi]
        if bins.nsurround > 1:
            item["surround_codes"] = [s * SURROUND_BIN, min((s + 1) * SURROUND_BIN, 256.0)]
        out.append(item)
    return out


_WHAT = {"by_code": "an offset per bin of code",
         "by_group": "an offset per bin of code in each pair or step",
         "by_surround": "an offset per bin of code and of the surround's brightness, "
                        "against the offset per bin of code"}


def _spot(item: dict, channels: int) -> str:
    where = f"codes {item['codes'][0]:.0f}-{item['codes'][1]:.0f}"
    if channels > 1:
        where += f" of channel {item['channel']}"
    if "group" in item:
        where += f" in {item['group']}"
    if "surround_codes" in item:
        lo, hi = item["surround_codes"]
        where += f" in surrounds of codes {lo:.0f}-{hi:.0f}"
    return f"{where}: {item['offset_codes']:+.2f} codes ({item['values']} values)"


def describe(result: dict) -> str:
    """One paragraph for the report (``result``: ``leftover``'s, or its JSON form)."""
    labels = [k for k in _WHAT if k in result]
    parts = [f"{_WHAT[k]}: held-out gain {result[k]['gain']:.3g} nats per value, "
             f"t = {result[k]['statistic']:.2f}, p = {result[k]['p_value']:.2g}"
             for k in labels]
    if not result["structure"]:
        return ("What the model leaves: no structure. Tested against " + "; ".join(parts)
                + (". Neither" if len(labels) == 2 else ". None")
                + " predicts the held-out blocks both significantly better and by "
                "the least gain that counts, so the extended model's mean is adequate to "
                "the precision of these data.")
    text = ("What the model leaves: structure that no effect of the vocabulary explains. "
            "Tested against " + "; ".join(parts) + ".")
    # of the alternatives by code and by pair that count, the one that gains the more says
    # where; the one by surround says what it adds beyond the code on its own
    counted = [k for k in ("by_code", "by_group") if result[k]["significant"]]
    if counted:
        label = max(counted, key=lambda k: result[k]["gain"])
        spots = [_spot(item, result["channels"]) for item in result[label]["largest"][:3]]
        causes = ("a cause outside the vocabulary (a tone curve that changes between "
                  "frames, flare, a soft knee, processing that depends on the image) or a "
                  "named effect of the wrong form")
        if label == "by_group":
            causes += (", or, where a few pairs or steps carry it, something of their own (a "
                       "pair's kernel or alignment, a frame's exposure or processing)")
        text += (" The data depart from the extended model most at " + "; ".join(spots)
                 + " (observed minus the model, by the model's estimate of the noise-free "
                 "code). At work there: " + causes + ".")
    if result.get("by_surround", {}).get("significant"):
        spots = [_spot(item, result["channels"])
                 for item in result["by_surround"]["largest"][:3]]
        text += (" The departure depends on how bright a pixel's surround is, not on its "
                 "code alone: " + "; ".join(spots) + " beyond the offset of the code. At "
                 "work there: processing that adapts to the neighbourhood, which no curve "
                 "per channel can hold: local tone mapping (a camera's shadow and highlight "
                 "correction such as Canon's Auto Lighting Optimizer, Nikon's Active "
                 "D-Lighting or Sony's DRO; a phone's HDR rendering), or charge blooming "
                 "next to clipped highlights.")
    return text
