"""Exact compression of a group for the likelihood fits: pixels that predict alike, pooled.

A target pixel's prediction depends on its source codes (its histogram rows), the exposure
ratio (and its image pair, where the images have exposures of their own) and its position
only through vignetting.  In an exposure series every pixel reads one
source code per channel, so among tens of thousands of pixels there are only a few hundred
distinct predictions per channel and ratio.  The Gaussian likelihood of pixels sharing one
prediction ``mu`` and variance ``s2`` needs only their count ``N``, sum ``S1`` and sum of
squares ``S2``: ``sum (y - mu)^2 = S2 - 2 mu S1 + N mu^2``.  So the fits (thousands of
likelihood evaluations) run on pooled rows and give the same likelihood to rounding; the
per-block scores, which need the pixels, use the group itself.

Conventions
-----------
A compact group keeps ``C`` channels; its rows come in channel blocks, block ``c`` valid only
in channel ``c`` (the histogram rows of the other channels are empty), so the per-channel
gains apply unchanged.  ``Group.__dict__["stats"]`` holds ``(N, S1, S2)`` as ``(n, C)``
arrays (``model.gaussian_nll`` reads them); censored values pool in rows of their own
(``Group.censored`` set, ``valid`` not), whose count weighs the tail.  Pixels whose
histogram rows hold more than one code (motion) stay single rows.  For models with a
geometric variant the variants' rows are part of what must be identical (``geometric``).
Where pooling would leave more than ``_WORTH`` of the values (pairs and stacks: rows hold
motion) the group is used as it is.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from clblur.study.model import Group

__all__ = ["compact"]

# pool only when it leaves at most this fraction of the valid pixel values as rows: each
# pooled row is evaluated in every channel, so a weak pooling would cost more than it saves
_WORTH = 0.3


def compact(g: Group, position_matters: bool, geometric: bool = False,
            images_matter: bool = False) -> Group:
    """``g`` with pixels of identical prediction pooled (cached on ``g``), or ``g`` itself
    where that would not pay.

    Parameters
    ----------
    g : Group
        The group to compress.
    position_matters : bool
        True when the model can depend on the pixel position (vignetting free or nonzero):
        then the normalised radius is part of what must be identical.
    geometric : bool
        True when a geometric variant (misregistration, psf_scale, psf_orientation) is free
        or active: then its rows must be identical too, and the pooled group keeps them.
        Otherwise the pooled group has no variants.
    images_matter : bool
        True when the series' images have exposures or white balances of their own
        (``effects``' ``lt:I``, ``lw:I:c`` free or nonzero): then rows of different image
        pairs with the same nominal ratio predict apart, and the pair is part of what must
        be identical.
    """
    cache = g.__dict__.setdefault("_compact", {})
    images_matter = images_matter and g.images is not None
    key = (position_matters, geometric, images_matter)
    if key not in cache:
        cache[key] = _compact(g, position_matters, geometric, images_matter)
    return cache[key]


def _compact(g: Group, position_matters: bool, geometric: bool,
             images_matter: bool) -> Group:
    n, nc = g.target.shape
    ratio = np.broadcast_to(np.asarray(g.ratio, np.float64), (n,))
    keys = sorted(g.hist)
    variants = g.__dict__.get("variants", {}) if geometric else {}
    blocks = []
    for c in range(nc):
        mats = [g.hist[k][c] for k in keys] + [g.hist_sq[c]] + [
            hs[c] for e in sorted(variants) for v in sorted(variants[e])
            for _, hs in sorted(variants[e][v].items(), key=lambda kv: str(kv[0]))]
        cols, vals, single = [], [], np.ones(n, bool)
        for m in mats:
            m = m.tocsr()
            nnz = np.diff(m.indptr)
            single &= nnz == 1
            first = np.minimum(m.indptr[:-1], max(m.nnz - 1, 0))
            cols.append(np.where(nnz == 1, m.indices[first] if m.nnz else 0, -1))
            vals.append(np.where(nnz == 1, m.data[first] if m.nnz else 0.0, 0.0))
        fields = [*cols, *vals, ratio]
        if position_matters:
            fields.append(g.r2)
        if images_matter:
            fields += [g.images[:, 0], g.images[:, 1]]
        table = np.column_stack([np.asarray(f, np.float64) for f in fields])
        # multi-code rows stay apart: a unique last column
        table = np.column_stack([table, np.where(single, -1.0, np.arange(n, dtype=np.float64))])
        # censored values pool apart from observed ones (their likelihood is a tail's), by
        # end: the censoring state is part of the key
        ends = np.zeros(n, np.int8) if g.censored is None else g.censored[:, c]
        rows = np.flatnonzero(g.valid[:, c] | (ends != 0))
        if rows.size == 0:
            continue
        _, first, inverse = np.unique(np.column_stack([table[rows], ends[rows]]), axis=0,
                                      return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        y = g.target[rows, c]
        count = np.bincount(inverse, minlength=first.size).astype(np.float64)
        s1 = np.bincount(inverse, y, minlength=first.size)
        s2 = np.bincount(inverse, y * y, minlength=first.size)
        blocks.append((c, rows[first], count, s1, s2, ends[rows[first]]))
    if sum(b[1].size for b in blocks) > _WORTH * int(g.valid.sum()):
        return g  # rows hold motion: pooling would not pay for the channel blocks
    return _assemble(g, blocks, nc, variants)


def _assemble(g: Group, blocks: list, nc: int, variants: dict) -> Group:
    total = sum(b[1].size for b in blocks)
    stats = [np.zeros((total, nc)) for _ in range(3)]
    valid = np.zeros((total, nc), bool)
    censored = np.zeros((total, nc), np.int8)
    target = np.zeros((total, nc))
    take, chan = [], []
    at = 0
    for c, rows, count, s1, s2, ends in blocks:
        sl = slice(at, at + rows.size)
        for arr, v in zip(stats, (count, s1, s2), strict=True):
            arr[sl, c] = v
        valid[sl, c] = ends == 0
        censored[sl, c] = ends
        target[sl, c] = s1 / count
        take.append(rows)
        chan.append(np.full(rows.size, c))
        at += rows.size
    take = np.concatenate(take) if take else np.zeros(0, np.intp)
    chan = np.concatenate(chan) if chan else np.zeros(0, np.intp)

    def per_channel(mats: list[sp.csr_matrix]) -> list[sp.csr_matrix]:
        # row block c keeps channel c's rows; the other channels' rows are empty
        out = []
        for c, m in enumerate(mats):
            keep = sp.diags((chan == c).astype(np.float64))
            out.append((keep @ m.tocsr()[take]).tocsr())
        return out

    ratio = (np.broadcast_to(np.asarray(g.ratio, np.float64), g.rows.shape)[take]
             if np.ndim(g.ratio) else g.ratio)
    out = Group(g.name, target, valid, g.rows[take], g.cols[take], g.shape, ratio,
                {k: per_channel(hs) for k, hs in g.hist.items()}, per_channel(g.hist_sq),
                g.r2[take], g.block[take] if g.block is not None else None,
                g.fold[take] if g.fold is not None else None, g.source_clipped,
                None if g.images is None else g.images[take],
                None if g.censored is None else censored, g.top,
                None if g.surround is None else g.surround[take])
    out.__dict__["stats"] = stats
    out.__dict__["variants"] = {
        e: {v: {key: per_channel(hs) for key, hs in hist.items()} for v, hist in d.items()}
        for e, d in variants.items()}
    # path weight sums are the same in every channel: read them from the full rows (the
    # pooled ones are empty outside their channel), the variants' too (a prediction that
    # mixes them in sums theirs)
    out.__dict__["_norms"] = {
        (v, i): g.time_norm(i, v)[take]
        for v in (None, *((e, k) for e in variants for k in variants[e]))
        for i, k in g.hist if k == 0}
    for k in ("darkest", "gid", "inner_images", "clipped_left_out"):
        if k in g.__dict__:
            out.__dict__[k] = g.__dict__[k]
    return out
