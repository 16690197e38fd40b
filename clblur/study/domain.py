"""The domain the fitted response averages in: code values, gamma 2.2, sRGB or the paper's Eq. 3.

Why: the blur ``g = I(mean I^-1(f))`` depends on the response only through how it mixes
codes, and an exposure scale cancels in it.  A dataset whose blurred images were made as a
mean of pixel values (the conventional blur, the paper's Eq. 7) or shot by a linear (raw)
sensor fits a linear response; one averaged in gamma-2.2 values (Nah et al., CVPR 2017, the
GoPro dataset) a power law 2.2.  The study fits its curve family and names an *effect*
(``response_imax`` at its linear limit, ``response_shape``); what a deblurring researcher
asks is the domain, and this module reads it off the final model's curve.

How: for every pair of source codes ``a, b`` the data show and mixing fractions 1/4, 1/2 and
3/4, the code the fitted curve gives the mix, ``I(f I^-1(a) + (1 - f) I^-1(b))`` with the
model's black level, shape and per-channel exponent (``study.model``), against the code each
standard curve gives it (``clblur.responses``: ``linear``, ``gamma:2.2``, ``srgb``, ``exp``).
The difference is averaged over the pairs weighted by how often the data show each code
(per channel, the product of the two codes' shares) and its largest value is taken over the
codes that make up at least ``MIN_SHARE`` of the values each.  A domain is named where the
mean lies under ``SAME_MEAN_CODES``: averaged over the data's mixes, the two curves' blurs
differ by less than the rounding of one stored code.  Code 255 is left out (clipped: the
saturation factor's business).
"""

from __future__ import annotations

import numpy as np

from clblur.study.effects import black_levels, channel_exponents
from clblur.study.model import CODES, Group, inverse_table, shape

__all__ = ["DOMAINS", "FRACTIONS", "MIN_SHARE", "SAME_MEAN_CODES", "code_shares", "describe",
           "mixing_domain"]

# (name in the report, response spec of clblur.responses)
DOMAINS = (("code values", "linear"), ("gamma 2.2", "gamma:2.2"), ("sRGB", "srgb"),
           ("the paper's Eq. 3", "exp"))
FRACTIONS = (0.25, 0.5, 0.75)
SAME_MEAN_CODES = 0.5  # half a code: below the rounding of one stored 8-bit code
MIN_SHARE = 1e-3  # a code this rare is left out of the largest difference (not the mean)

_TOP = CODES - 1  # codes 0 .. 254 (255 is clipped)


def code_shares(groups: list[Group], channels: int) -> np.ndarray:
    """How often the data's sources show each code, per channel (channels x 255, rows sum to
    1; a channel without values: all 0): the column sums of the groups' plain histograms
    over their valid rows."""
    total = np.zeros((channels, _TOP))
    for g in groups:
        hists = g.hist.get((0, 0))
        if hists is None:
            continue
        for c in range(min(channels, len(hists))):
            keep = g.valid[:, c]
            if keep.any():
                col = np.asarray(hists[c][np.flatnonzero(keep)].sum(axis=0)).ravel()
                total[c] += col[:_TOP]
    sums = total.sum(axis=1, keepdims=True)
    return np.divide(total, sums, out=np.zeros_like(total), where=sums > 0)


def _fitted_mixes(p: dict, c: int, channels: int, a: np.ndarray, b: np.ndarray
                  ) -> list[np.ndarray]:
    """The code the final model's curve of channel ``c`` gives each mix (one array per
    fraction)."""
    factor = channel_exponents(p, channels)[c]
    beta = black_levels(p, channels)[c]
    curve = shape(p, factor)
    t = inverse_table(p, curve, beta)
    return [255.0 * (beta + (1.0 - beta) * curve.forward(f * t[a] + (1.0 - f) * t[b]))
            for f in FRACTIONS]


def _standard_mixes(spec: str, a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    from clblur.responses import response

    r = response(spec)
    u = r.inverse(np.arange(_TOP, dtype=np.float64) / 255.0)
    return [255.0 * r.forward(f * u[a] + (1.0 - f) * u[b]) for f in FRACTIONS]


def mixing_domain(p: dict, channels: int, shares: np.ndarray) -> dict | None:
    """How far the fitted curve's mixes lie from each standard domain's (module docstring).

    Args:
        p: the final model's parameters (``Selection.params``).
        channels: colour channels of the data.
        shares: channels x 255 code shares (:func:`code_shares`).

    Returns:
        None where no channel has values; else ``{"domains": {name: {"mean_codes",
        "max_codes"}}, "closest": name, "named": bool, "codes": [lowest, highest]}``,
        ``named``: the closest domain's mean difference is under ``SAME_MEAN_CODES``;
        ``codes``: the range of codes at ``MIN_SHARE`` or more in any channel.
    """
    seen = shares >= MIN_SHARE
    if not seen.any():
        return None
    a, b = np.meshgrid(np.arange(_TOP), np.arange(_TOP), indexing="ij")
    present = [c for c in range(channels) if seen[c].any()]
    # the fitted curve's mixes once per channel, each pair's weight and whether it counts
    # for the largest difference: the same for every domain
    fitted = {c: _fitted_mixes(p, c, channels, a, b) for c in present}
    weight = {c: shares[c][:, None] * shares[c][None, :] for c in present}
    counted = {c: seen[c][:, None] & seen[c][None, :] for c in present}
    out: dict = {}
    for name, spec in DOMAINS:
        standard = _standard_mixes(spec, a, b)
        mean_sum, weight_sum, largest = 0.0, 0.0, 0.0
        for c in present:
            w, both = weight[c], counted[c]
            for fit, std in zip(fitted[c], standard, strict=True):
                d = np.abs(fit - std)
                mean_sum += float((w * d).sum())
                weight_sum += float(w.sum())
                largest = max(largest, float(d[both].max()))
        out[name] = {"mean_codes": mean_sum / weight_sum, "max_codes": largest}
    closest = min(out, key=lambda n: out[n]["mean_codes"])
    codes = np.flatnonzero(seen.any(axis=0))
    return {"domains": out, "closest": closest,
            "named": bool(out[closest]["mean_codes"] < SAME_MEAN_CODES),
            "codes": [int(codes[0]), int(codes[-1])]}


_MEANING = {  # what averaging in a domain means for blur data (pairs, stacks)
    "code values": "means of pixel values, not of light: a linear (raw) sensor's data, or "
                   "blur made in pixel values (the conventional blur, the paper's Eq. 7)",
    "gamma 2.2": "means taken in gamma-2.2 linear values (how Nah et al. 2017 made the "
                 "GoPro dataset's blur)",
    "sRGB": "means of light through the sRGB curve (photo-consistent for an sRGB camera)",
    "the paper's Eq. 3": "means of light through the paper's Eq. 3 response",
}
_CURVE = {  # the same domains as a camera's curve (exposure series)
    "code values": "a linear curve (a raw sensor's)",
    "gamma 2.2": "the gamma-2.2 curve",
    "sRGB": "the sRGB curve",
    "the paper's Eq. 3": "the paper's Eq. 3",
}


def describe(dom: dict, series: bool) -> str:
    """One paragraph on the domain (``series``: the data are an exposure series, whose
    curve is the camera's, not a blur's domain)."""
    d = dom["domains"]
    lo, hi = dom["codes"]
    close = sorted(d, key=lambda n: d[n]["mean_codes"])
    first, second = close[0], close[1]
    numbers = (f"mixes of two codes differ from those of {first} by "
               f"{d[first]['mean_codes']:.2f} codes on average (largest "
               f"{d[first]['max_codes']:.2f}) and from those of {second} by "
               f"{d[second]['mean_codes']:.2f}, over the source codes the data show "
               f"({lo} - {hi})")
    if not dom["named"]:
        return (f"Averaging domain: none of {', '.join(n for n, _ in DOMAINS)}. The fitted "
                f"curve is closest to {first}, but its {numbers}.")
    alike = [n for n in close[1:] if d[n]["mean_codes"] < SAME_MEAN_CODES]
    also = ("" if not alike else
            " Within half a code on average as well: "
            + ", ".join(f"{n} ({d[n]['mean_codes']:.2f}, largest {d[n]['max_codes']:.2f})"
                        for n in alike)
            + "; on average a blur through these curves differs by less than the rounding of "
              "a stored code.")
    if series:
        return (f"Averaging domain: the fitted curve is {_CURVE[first]}, up to the exposure "
                f"scale: its {numbers}.{also}")
    return (f"Averaging domain: {first}. The fitted curve's {numbers}. So the blurred "
            f"images are {_MEANING[first]}.{also}")
