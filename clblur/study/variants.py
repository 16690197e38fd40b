"""Geometric and storage effects on top of the study's forward model (``model.predict``).

Conventions
-----------
The paper's model reads each target pixel's source codes through fixed taps (``Group.hist``).
Four effects change the taps, one changes how the target was stored:

* ``misregistration`` (``sx``, ``sy``, pixels, each in [-1, 1]): target pixel ``p`` sees the
  source at ``p - s``.  Histograms are built for the four unit shifts; a sub-pixel shift
  mixes them, ``H(s) = H0 + |sx| (H(sign sx, 0) - H0) + |sy| (H(0, sign sy) - H0)``, which is
  exactly bilinear interpolation along each axis (taps on whole pixels, as in stacks and
  series) and its first-order form otherwise.
* ``psf_orientation`` (``flip:G`` in {0, 1} per group ``G``): the motion is rotated by 180
  degrees (a PSF ``h[::-1, ::-1]``, a flow or vector negated): correlation instead of
  convolution.  Chosen per group (per pair), because a data set can mix both conventions.
* ``psf_scale`` (``pscale`` in [0.8, 1.25]): the motion resampled by that factor (a PSF
  zoomed about its centre, a vector or flow scaled).  Histograms are built at 0.8 and 1.25;
  between them the mixture is piecewise linear in the factor (exact at 0.8, 1, 1.25).
* ``optical_blur`` (``ovar``, px^2 in [0, 2]): the target's light blurred further by an
  isotropic kernel of that variance per axis (defocus, another lens, a resampling step).
  Histograms are built with the taps spread by binomial kernels of variance 0.5, 1 and 2
  (``OPTICAL_VARIANCES``: orders 2, 4 and 8 per axis, a Gaussian's discrete analogue);
  between them, and between 0 and the first, the mixture is linear in ``ovar``.  A mixture
  of centred kernels has the mixture of their variances, so the blur added has variance
  ``ovar`` exactly, and its shape is a Gaussian's to within the mixing of two neighbours.
* ``quantisation`` (``qoff``, code values in [-1, 1]): a constant offset of the stored target
  codes, e.g. -0.5 when values were truncated (floor) instead of rounded.

All five are nested: at ``sx = sy = 0``, ``flip = 0``, ``pscale = 1``, ``ovar = 0``,
``qoff = 0`` the
prediction is ``model.predict``'s.  Variant histograms combine additively (a flipped and
shifted PSF uses the shift deltas of the unflipped one: a first-order approximation).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import scipy.sparse as sp

from clblur.study.model import Group, gaussian_nll
from clblur.study.model import predict as _model_predict

__all__ = ["OPTICAL_VARIANCES", "attach", "binomial_offsets", "darkest_codes", "geometric",
           "has_variant", "pack", "pixel_nll", "predict", "subset"]

SCALES = (0.8, 1.25)  # psf_scale histograms besides 1
SHIFTS = ((1, 0), (-1, 0), (0, 1), (0, -1))  # misregistration histograms besides (0, 0)
OPTICAL_VARIANCES = (0.5, 1.0, 2.0)  # optical_blur histograms besides 0 (px^2 per axis)


def binomial_offsets(variance: float) -> list[tuple[int, int, float]]:
    """(dy, dx, weight) of the 2-D binomial kernel of ``variance`` per axis (order
    ``4 variance``, an even integer: 0.5, 1, 2, ...), centred, weights summing to 1."""
    order = round(4 * variance)
    if order < 2 or order % 2 or abs(order - 4 * variance) > 1e-9:
        raise ValueError(f"a binomial kernel has variance order / 4 with an even order; "
                         f"got {variance}")
    w = np.array([math.comb(order, i) for i in range(order + 1)], np.float64) / 2.0 ** order
    r = order // 2
    return [(i - r, j - r, float(w[i] * w[j])) for i in range(order + 1)
            for j in range(order + 1)]


def attach(g: Group, variants: dict[str, dict], darkest,
           with_target: bool = True) -> None:
    """Store variant histograms (``{effect: {key: hist}}``) and the darkest source code of
    each channel (``darkest``: one code, or one per channel; with ``with_target``, or the
    group's darkest target code of the channel if darker)."""
    g.__dict__["variants"] = variants
    nc = g.target.shape[1]
    dark = np.broadcast_to(np.asarray(darkest, np.float64), (nc,)).copy()
    if with_target and g.target.size:
        dark = np.minimum(dark, g.target.min(axis=0))
    g.__dict__["darkest"] = dark


def darkest_codes(g: Group) -> np.ndarray:
    """Darkest code of each channel seen in the group's source images or target pixels
    (the bound of that channel's black level; float: an exposure series bounds it by a mean,
    ``clblur.study.series``)."""
    nc = g.target.shape[1]
    if "darkest" in g.__dict__:
        return np.broadcast_to(np.asarray(g.__dict__["darkest"], np.float64), (nc,))
    if not g.target.size:
        return np.zeros(nc)
    return g.target.min(axis=0).astype(np.float64)


def has_variant(groups: list[Group], effect: str) -> bool:
    return any(effect in g.__dict__.get("variants", {}) for g in groups)


def subset(g: Group, keep: np.ndarray) -> Group:
    """``g.subset(keep)`` keeping the variant histograms, the group index and darkest code."""
    out = g.subset(keep)
    idx = np.flatnonzero(keep)
    out.__dict__["variants"] = {
        e: {k: {key: [h[idx] for h in hs] for key, hs in hist.items()} for k, hist in d.items()}
        for e, d in g.__dict__.get("variants", {}).items()}
    for k in ("darkest", "gid", "inner_images"):
        if k in g.__dict__:
            out.__dict__[k] = g.__dict__[k]
    return out


def pack(groups: list[Group]) -> list[Group]:
    """The groups concatenated wherever they share one histogram layout.

    A fit sums the likelihood over every group thousands of times; with a few thousand pixels
    per group that sum is bound by per-call overhead, not arithmetic, so one group of
    ``6 n`` rows costs little more than one of ``n``.  Rows keep their block, fold and
    exposure ratio (``Group.ratio`` becomes per row), so sums and per-block scores are
    unchanged.  Groups with a ``psf_orientation`` variant keep their own flip (one per
    group) and stay apart, as do groups of different clip codes (``Group.top``).
    """
    def layout(g: Group):
        var = g.__dict__.get("variants", {})
        if "psf_orientation" in var:
            return None
        return (g.channels, g.top, tuple(sorted(g.hist)),
                tuple((e, tuple((k, tuple(sorted(h, key=str))) for k, h in sorted(d.items())))
                      for e, d in sorted(var.items())))

    bins: dict = {}
    out: list[Group] = []
    for g in groups:
        key = layout(g)
        if key is None:
            out.append(g)
        else:
            bins.setdefault(key, []).append(g)
    for members in bins.values():
        out.append(members[0] if len(members) == 1 else _concat(members))
    return out


def _concat(gs: list[Group]) -> Group:
    def stack(get):
        return [sp.vstack([get(g)[c] for g in gs]).tocsr() for c in range(gs[0].channels)]

    first = gs[0]
    g = Group("+".join(g.name for g in gs), np.concatenate([g.target for g in gs]),
              np.concatenate([g.valid for g in gs]), np.concatenate([g.rows for g in gs]),
              np.concatenate([g.cols for g in gs]), first.shape,
              np.concatenate([np.broadcast_to(np.asarray(g.ratio, np.float64), g.rows.shape)
                              for g in gs]),
              {key: stack(lambda g, key=key: g.hist[key]) for key in first.hist},
              stack(lambda g: g.hist_sq), np.concatenate([g.r2 for g in gs]),
              np.concatenate([g.block for g in gs]), np.concatenate([g.fold for g in gs]),
              any(g.source_clipped for g in gs),
              np.concatenate([g.images for g in gs])
              if all(g.images is not None for g in gs) else None,
              _censored(gs), first.top,
              np.concatenate([g.surround for g in gs])
              if all(g.surround is not None for g in gs) else None)
    var = first.__dict__.get("variants", {})
    g.__dict__["variants"] = {
        e: {k: {key: stack(lambda g, e=e, k=k, key=key: g.__dict__["variants"][e][k][key])
                for key in hist} for k, hist in d.items()} for e, d in var.items()}
    g.__dict__["darkest"] = np.min([darkest_codes(m) for m in gs], axis=0)
    inner = {i for m in gs for i in m.__dict__.get("inner_images", ())}
    if inner:
        g.__dict__["inner_images"] = tuple(sorted(inner))
    return g


def geometric(names: list[str], p: dict) -> bool:
    """Whether a geometric variant is free (in ``names``) or active in ``p``: then the
    prediction reads the variant histograms, not only ``Group.hist``."""
    return any(n in ("sx", "sy", "pscale", "ovar") for n in names) or bool(
        p.get("sx", 0.0) or p.get("sy", 0.0) or p.get("pscale", 1.0) != 1.0
        or p.get("ovar", 0.0)
        or any(k.startswith("flip:") and v for k, v in p.items()))


def _terms(g: Group, p: dict) -> list[tuple[float, tuple]]:
    """(weight, variant key) pairs; the prediction uses H0 + sum w (H_v - H0)."""
    var = g.__dict__.get("variants", {})
    out = []
    sx, sy = p.get("sx", 0.0), p.get("sy", 0.0)
    if "misregistration" in var and (sx or sy):
        if sx:
            out.append((abs(sx), ("misregistration", (1 if sx > 0 else -1, 0))))
        if sy:
            out.append((abs(sy), ("misregistration", (0, 1 if sy > 0 else -1))))
    s = p.get("pscale", 1.0)
    if "psf_scale" in var and s != 1.0:
        lo, hi = SCALES
        if s > 1.0:
            out.append(((s - 1.0) / (hi - 1.0), ("psf_scale", hi)))
        else:
            out.append(((1.0 - s) / (1.0 - lo), ("psf_scale", lo)))
    ov = p.get("ovar", 0.0)
    if "optical_blur" in var and ov > 0.0:
        # linear between neighbouring levels (0 the plain histogram); beyond the last, the
        # last (the parameter's bound is the last level)
        levels = (0.0, *OPTICAL_VARIANCES)
        i = min(int(np.searchsorted(levels, ov)), len(levels) - 1)
        lo, hi = levels[i - 1], levels[i]
        u = min((ov - lo) / (hi - lo), 1.0)
        out.append((u, ("optical_blur", hi)))
        if lo > 0.0:
            out.append((1.0 - u, ("optical_blur", lo)))
    flip = p.get(f"flip:{g.__dict__.get('gid', 0)}", 0.0)
    if "psf_orientation" in var and flip:
        out.append((flip, ("psf_orientation", "flip")))
    return out


class _Mix:
    """``sum_v w_v H_v`` as far as ``model.predict`` uses a histogram, ``@`` a code table
    (its row sums are the group's time norms, ``Group.time_norm``): products of the parts,
    never a new sparse matrix per evaluation.  ``parts``: (weight, histogram, slot); the
    parts' products are remembered by ``owner`` (``Group.product``), since a shift's step
    changes the weights, not the products."""

    def __init__(self, parts: list[tuple[float, sp.csr_matrix, tuple]], owner: Group):
        self.parts = parts
        self.owner = owner
        self.shape = parts[0][1].shape

    def __matmul__(self, t: np.ndarray) -> np.ndarray:
        """``sum_v w_v (H_v @ t)``, added in the parts' order."""
        w, h, slot = self.parts[0]
        out = w * self.owner.product(slot, h, t)
        for w, h, slot in self.parts[1:]:
            out = out + w * self.owner.product(slot, h, t)
        return out


def _censored(gs: list[Group]) -> np.ndarray | None:
    """The packed rows' ``Group.censored`` (zeros for a group that censors nothing)."""
    if all(g.censored is None for g in gs):
        return None
    return np.concatenate([np.zeros(g.target.shape, np.int8) if g.censored is None
                           else g.censored for g in gs])


def predict(g: Group, p: dict, source_share: bool = False,
            parts: dict | None = None) -> tuple[np.ndarray, ...]:
    """``model.predict`` with the geometric variants mixed in and the storage offset added
    (``source_share``, ``parts``: as there)."""
    terms = _terms(g, p)
    if terms:
        var = g.__dict__["variants"]
        w0 = 1.0 - sum(w for w, _ in terms)
        # slots: the plain histogram's as in model.predict, so both share its products
        hist = {key: [_Mix([(w0, h, (*key, c))]
                           + [(w, var[e][k][key][c], (e, k, *key, c)) for w, (e, k) in terms],
                           g)
                      for c, h in enumerate(hs)]
                for key, hs in g.hist.items()}
        # each variant carries its own squared weights: a blurred, scaled or shifted path
        # reads other source pixels, as many or more, and so carries its own share of the
        # source's noise (groups built before variants held them: the plain ones)
        hist_sq = [_Mix([(w0, h, ("sq", c))]
                        + [(w, var[e][k]["sq"][c], (e, k, "sq", c)) if "sq" in var[e][k]
                           else (w, h, ("sq", c)) for w, (e, k) in terms], g)
                   for c, h in enumerate(g.hist_sq)]
        mixed = dataclasses.replace(g, hist=hist, hist_sq=hist_sq)
        # one memory of products for both (Group.product): hist_sq is the group's own
        mixed.__dict__["_products"] = g.__dict__.setdefault("_products", {})
        # the mixture's path weight sums, from the parts' (Group.time_norm: a pooled group's
        # rows are empty outside their channel, so they are not the mixed rows' own sums)
        norms = {}
        for i, k in g.hist:
            if k == 0:
                norm = w0 * g.time_norm(i)
                for w, variant in terms:
                    norm = norm + w * g.time_norm(i, variant)
                norms[(None, i)] = norm
        mixed.__dict__["_norms"] = norms
        g = mixed
    pred, *rest = _model_predict(g, p, source_share, parts)
    q = p.get("qoff", 0.0)
    return (pred + q if q else pred), *rest


def pixel_nll(g: Group, p: dict) -> np.ndarray:
    """Gaussian negative log-likelihood per target pixel (summed over valid channels)."""
    return gaussian_nll(g, *predict(g, p))
