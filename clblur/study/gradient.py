"""The likelihood's gradient in the study's parameters, in closed form.

A fit (``clblur.study.crossfit``) minimises the penalised negative log-likelihood with
L-BFGS-B.  Its gradient was taken by forward differences, one likelihood per free parameter
per step: on an exposure series, which frees an exposure per inner image and a white
balance per inner image and channel beside the response's shape, those differences were
85 % of a study's time (cProfile, 2026-12-03).

Every parameter but the geometric variants reaches a value's likelihood through a few
per-entry numbers of ``model.predict``: the linear exposure ``x = m e`` (``e`` the average
of the inverse table ``T`` over the source codes, ``m`` the factors), ``m`` itself (which
the source's share of the variance carries squared), the source's variance ``source``, the
response ``v`` and its slope at ``x``, and the noise coefficients.  With

    pred = 255 beta + scale v(x),   s = scale v'(x),   scale = 255 (1 - beta),
    var  = 1/12 + nc + s^2 (na x + nb) + (s m)^2 source,

the likelihood's derivatives in ``pred`` and ``var`` (``model.gaussian_nll``'s
``partials``) chain onto what each parameter moves:

* ``gain``, ``cg{c}``, ``lt:I``, ``lw:I:c``: ``ln m`` (the last two through the row's source
  and target image; ``cg`` and ``lw`` normalised to a geometric mean of 1);
* ``vig``: ``ln m`` through ``-2 ln(1 + vig r^2)``, ``ln e`` through the vignetting
  histograms' weights ``2 vig`` and ``vig^2``; ``t1``, ``t2``: ``ln e`` through the time
  histograms and their norm;
* ``na``, ``nb``, ``nc``: the variance; ``qoff`` (``clblur.study.variants``): ``pred``;
* the response (``gamma``, ``rho``, ``w1``..``w4``, ``ce{c}``, ``black*``, ``sat``): the
  table ``T`` (so ``e`` and ``source``, one sparse product per histogram) and the forward
  ``v``, ``v'`` at fixed ``x``, from the log inverse ``L(w) = ln x``: ``dw = -L_theta /
  L_w`` (``_forward_partials``, ``_table_partials``).

The slope's own derivative in ``ln x`` is a central difference.  The geometric variants
(``sx``, ``sy``, ``pscale``, ``ovar``) change the taps, piecewise linearly, and keep
forward differences (``is_analytic``).  The closed form agrees with central differences
to 1e-5 of each derivative, and to 3e-4 for the response's parameters on a warped curve
(its forward is an interpolant, whose derivative in the parameters departs from the
curve's by that much) (``tests/test_study_gradient.py``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from clblur.responses import warp_basis_slopes
from clblur.responses.families import _GRID
from clblur.study.model import TOP, WARP_KEYS, Group, _forward, code_step, gaussian_nll
from clblur.study.variants import predict

__all__ = ["ANALYTIC", "is_analytic", "nll_gradient"]

# parameters whose derivative is taken in closed form (besides the indexed ``cg``, ``ce``,
# ``black``, ``lt:``, ``lw:``); the rest, the geometric variants, by differences
# (``clblur.study.crossfit``)
ANALYTIC = ("gain", "vig", "t1", "t2", "na", "nb", "nc", "qoff", "gamma", "rho", "sat",
            *WARP_KEYS)
_INDEXED = ("cg", "ce", "black", "lt:", "lw:")
# the response shape's parameters, as the partials of one channel's curve name them
_SHAPE = ("gamma", "rho", "sat", "black", *WARP_KEYS)
# the step in ln x of the slope's central difference: its truncation error (step^2 / 6 of
# the third derivative, relative) and its rounding error (1e-16 / step) are both below
# 1e-8 of the slope
_LOG_STEP = 1e-4


def is_analytic(name: str) -> bool:
    """Whether ``nll_gradient`` differentiates the likelihood in parameter ``name``."""
    return name in ANALYTIC or name.startswith(_INDEXED)


def nll_gradient(g: Group, p: dict[str, float], names: list[str]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``g``'s negative log-likelihood per target pixel under ``p`` (as
    ``variants.pixel_nll``, bit for bit) and the derivative of its sum in each parameter of
    ``names`` (every one ``is_analytic``).

    Returns:
        ``(nll, grad)``: (n,) per pixel, and (len(names),).
    """
    parts: dict = {}
    pred, var = predict(g, p, parts=parts)
    nll, d_pred, d_var = gaussian_nll(g, pred, var, partials=True)
    grad = np.zeros(len(names))
    if not names:
        return nll, grad
    h = parts["group"]  # the group model.predict read (the variants' mixture, if any)
    x, m, s, source = parts["x"], parts["m"], parts["s"], parts["source"]
    d_var = np.where(parts["live"], d_var, 0.0)  # the variance's floor holds it there
    nc = x.shape[1]
    # d s / d ln x, from the slope a little below and above each exposure
    _, below = _forward(parts["curves"], parts["factors"], x * np.exp(-_LOG_STEP),
                        parts["only"])
    _, above = _forward(parts["curves"], parts["factors"], x * np.exp(_LOG_STEP),
                        parts["only"])
    ds = parts["scale"] * (above - below) / (2.0 * _LOG_STEP)
    na, nb = p["na"], p["nb"]
    from_source = m * m * source  # the source's variance term over s^2
    # the likelihood's derivative in each entry's ln x (m held) and in its ln m
    by_lnx = d_pred * s * x + d_var * (2.0 * s * ds * (na * x + nb + from_source)
                                       + s * s * na * x)
    by_lnm = by_lnx + d_var * 2.0 * s * s * from_source
    tables = [parts["tables"][key] for key in parts["channel_keys"]]
    shape = None  # the response's partials per channel, once asked for
    by_image = None  # by_lnm's per-image sums, once asked for
    for j, name in enumerate(names):
        if name == "gain":
            grad[j] = by_lnm.sum()
        elif name.startswith("cg"):
            per_channel = by_lnm.sum(axis=0)
            grad[j] = per_channel[int(name[2:])] - per_channel.sum() / nc
        elif name.startswith(("lt:", "lw:")):
            if by_image is None:
                by_image = _image_sums(h, by_lnm)
            if name.startswith("lt:"):
                image = int(name[3:])
                grad[j] = by_image[image].sum() if image < len(by_image) else 0.0
            else:
                image, c = (int(v) for v in name[3:].split(":"))
                per_channel = by_image[image] if image < len(by_image) else np.zeros(nc)
                grad[j] = per_channel[c] - per_channel.sum() / nc
        elif name == "vig":
            r2 = h.r2[:, None]
            grad[j] = (by_lnm * (-2.0 * r2 / (1.0 + p["vig"] * r2))).sum() + (
                by_lnx * _vignetting_log_slope(h, p, parts, tables)).sum()
        elif name in ("t1", "t2"):
            grad[j] = (by_lnx * _time_log_slope(h, p, parts, tables, int(name[1]))).sum()
        elif name == "nc":
            grad[j] = d_var.sum()
        elif name in ("na", "nb"):
            table = (lambda t: t) if name == "na" else np.ones_like
            through = np.stack([h.product(("sq", c), h.hist_sq[c], table(tables[c][0]))
                                for c in range(nc)], axis=1)
            own = s * s * (x if name == "na" else 1.0)
            grad[j] = (d_var * (own + (s * m) ** 2 * through)).sum()
        elif name == "qoff":
            grad[j] = d_pred.sum()
        elif name in _SHAPE or name.startswith(("ce", "black")):
            if shape is None:
                wanted = {"gamma" if n.startswith("ce") else "black" if n.startswith("black")
                          else n for n in names if n in _SHAPE or n.startswith(("ce", "black"))}
                shape = _shape_gradient(h, p, parts, tables, d_pred, d_var, ds, wanted)
            grad[j] = _from_channels(name, shape, parts, nc)
        else:
            raise ValueError(f"no closed-form derivative in {name!r} (is_analytic)")
    return nll, grad


def _image_sums(g: Group, values: np.ndarray) -> np.ndarray:
    """``values`` (n, C) summed, per image ``I``, over the rows whose target is ``I`` less
    those whose source is (images x C; none outside a series): the derivative of the rows'
    factor ``exp(dev_target - dev_source)`` in each image's log factor ``dev``.  One pass
    for every image (a series fit asks for each image's exposure and white balance)."""
    if g.images is None:
        return np.zeros((0, values.shape[1]))
    source, target = g.images[:, 0], g.images[:, 1]
    span = int(g.images.max(initial=-1)) + 1
    return np.stack([np.bincount(target, values[:, c], minlength=span)
                     - np.bincount(source, values[:, c], minlength=span)
                     for c in range(values.shape[1])], axis=1)


def _linear_sum(h: Group, parts: dict, tables: list, weights) -> np.ndarray:
    """``sum over (i, k) of weights(i, k) * H_ik @ T`` per channel (n, C), 0 where no
    histogram carries a weight."""
    n, nc = parts["x"].shape
    out = np.zeros((n, nc))
    for (i, k), hs in h.hist.items():
        w = weights(i, k)
        if w:
            for c in range(nc):
                out[:, c] += w * h.product((i, k, c), hs[c], tables[c][0])
    return out


def _log_of_average(parts: dict, numerator: np.ndarray, col=slice(None)) -> np.ndarray:
    """``d ln e`` from ``d`` of the average's numerator ``e * norm`` (0 where ``e`` is), of
    every channel or of channel ``col`` (``numerator``: n, or n x q for q parameters of
    that channel)."""
    total = (parts["e"] * np.maximum(parts["norm"], 1e-12)[:, None])[:, col]
    if numerator.ndim > total.ndim:
        total = total[:, None]
    return np.divide(numerator, total, out=np.zeros(np.broadcast_shapes(
        numerator.shape, total.shape)), where=total > 0)


def _vignetting_log_slope(h: Group, p: dict, parts: dict, tables: list) -> np.ndarray:
    """``d ln e / d vig``: the vignetting histograms carry weights ``2 vig`` and ``vig^2``."""
    time_c = (1.0, p["t1"], p["t2"])
    slope = {1: 2.0, 2: 2.0 * p["vig"]}
    return _log_of_average(parts, _linear_sum(
        h, parts, tables, lambda i, k: time_c[i] * slope.get(k, 0.0)))


def _time_log_slope(h: Group, p: dict, parts: dict, tables: list, term: int) -> np.ndarray:
    """``d ln e / d t{term}``: the term's histograms over the norm's share of them."""
    if (term, 0) not in h.hist:
        return np.zeros_like(parts["x"])
    vig_c = (1.0, 2.0 * p["vig"], p["vig"] ** 2)
    numerator = _linear_sum(h, parts, tables, lambda i, k: vig_c[k] if i == term else 0.0)
    norm = np.maximum(parts["norm"], 1e-12)
    return _log_of_average(parts, numerator) - (h.time_norm(term) / norm)[:, None]


def _from_channels(name: str, shape: list[dict], parts: dict, nc: int) -> float:
    """A shape parameter's derivative from each channel's partials in its own curve's
    ``gamma`` (the shared exponent times the channel's factor), ``rho``, warp, saturation
    and black level."""
    factors = parts["factors"]
    if name == "gamma":  # channel c's exponent is gamma * f_c
        return sum(factors[c] * shape[c]["gamma"] for c in range(nc))
    if name.startswith("ce"):  # f_c = exp(ce_c - mean): d ln f_c / d ce_j = [c = j] - 1/C
        j = int(name[2:])
        gammas = [parts["curves"][factors[c]].gamma for c in range(nc)]
        return sum(gammas[c] * shape[c]["gamma"] * ((c == j) - 1.0 / nc) for c in range(nc))
    if name.startswith("black"):
        c = int(name[5:] or 0)
        return shape[c]["black"] if c < nc else 0.0
    return sum(shape[c][name] for c in range(nc))


def _shape_gradient(h: Group, p: dict, parts: dict, tables: list, d_pred: np.ndarray,
                    d_var: np.ndarray, ds: np.ndarray, wanted: set[str]) -> list[dict]:
    """Per channel, the likelihood's derivative in that channel's curve parameters
    ``wanted`` (of ``_SHAPE``; ``gamma`` its own exponent): through the inverse table (the
    linear averages and the source's variance) and through the forward at each exposure."""
    x, m, s, v, dv = parts["x"], parts["m"], parts["s"], parts["v"], parts["dv"]
    na, nb = p["na"], p["nb"]
    time_c = (1.0, p["t1"], p["t2"])
    vig_c = (1.0, 2.0 * p["vig"], p["vig"] ** 2)
    noise = na * x + nb + m * m * parts["source"]
    factors, nc = parts["factors"], x.shape[1]
    # channels that share a curve share its forward partials (elementwise: one call on
    # their columns side by side) and, with one black level, its table and the table's
    # partials; each parameter's table derivative is a column, so that a histogram meets
    # all of them in one sparse product
    forward_of = {}
    for f in dict.fromkeys(factors):
        cs = [c for c in range(nc) if factors[c] == f]
        forward_of[f] = cs, _forward_partials(parts["curves"][f], v[:, cs], dv[:, cs],
                                              x[:, cs])
    table_of = {}
    out = []
    for c in range(nc):
        curve = parts["curves"][factors[c]]
        beta = parts["betas"][c]
        key = parts["channel_keys"][c]
        if key not in table_of:
            table = tables[c][0]
            by_table = _table_partials(curve, beta, p["sat"], table)
            by_column = [name for name in wanted if name in by_table]
            d_tables = d_source = None
            if by_column:
                d_tables = np.column_stack([by_table[name] for name in by_column])
                d_source = code_step(table)[:, None] * code_step(d_tables) / 6.0 \
                    + na * d_tables  # the rounding variance's and the source noise's
            table_of[key] = by_column, d_tables, d_source
        by_column, d_tables, d_source = table_of[key]
        cs, partials = forward_of[factors[c]]
        j = cs.index(c)
        by_forward = {name: (d_w[:, j], d_slope[:, j])
                      for name, (d_w, d_slope) in partials.items()}
        col = slice(None), c
        scale = 255.0 * (1.0 - beta)
        # The derivative in a parameter is four weighted sums over the rows: of what it
        # does to the prediction at fixed x (d_pred_x), to the slope at fixed x (d_s_x),
        # to ln x (dlnx; the slope follows it by ds) and to the source's variance
        # (dsource), with the weights below (the chain rule on d_pred and d_var).
        on_pred, on_var, slope = d_pred[col], d_var[col], s[col]
        on_slope = 2.0 * on_var * slope * noise[col]
        on_lnx = (on_pred * slope * x[col] + on_slope * ds[col]
                  + on_var * slope * slope * na * x[col])
        on_source = on_var * slope * slope * m[col] * m[col]
        through_x = {}
        if by_column:
            numerator = sum(time_c[i] * vig_c[k] * _apply(hs[c], d_tables)
                            for (i, k), hs in h.hist.items() if time_c[i] * vig_c[k])
            through_x = dict(zip(by_column, _weighted(on_lnx, _log_of_average(
                parts, numerator, c)) + _weighted(on_source, _apply(h.hist_sq[c], d_source)),
                strict=True))
        found = {}
        for name in wanted:
            total = through_x.get(name, 0.0)
            if name == "black":  # pred = 255 beta + 255 (1 - beta) v
                total += 255.0 * (_weighted(on_pred, 1.0 - v[col]) - _weighted(on_slope,
                                                                                dv[col]))
            elif name in by_forward:
                d_w, d_slope = by_forward[name]
                total += scale * (_weighted(on_pred, d_w) + _weighted(on_slope, d_slope))
            found[name] = float(total)
        out.append(found)
    return out


def _weighted(weights: np.ndarray, values: np.ndarray) -> float | np.ndarray:
    """``sum_rows weights * values`` (``values``: n, or n x q for q parameters).

    Why not ``weights @ values``: BLAS's dot products round by where the arrays lie in
    memory, so two runs of one study would differ in the last bits and then, through the
    optimiser, in their reports; numpy's own sums do not."""
    if values.ndim > 1:
        return (weights[:, None] * values).sum(axis=0)
    return (weights * values).sum()


def _apply(hist, table: np.ndarray) -> np.ndarray:
    """``hist @ table``, not remembered (``Group.product`` keeps the tables of the last
    predictions; a table's derivative would push them out)."""
    if sp.issparse(hist):
        return hist @ table
    return sum(w * (part @ table) for w, part, _ in hist.parts)  # a variants mixture


def _log_inverse_terms(curve, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """At values ``w`` above the black level: ``L_w``, ``L_ww`` of the log inverse
    ``L = gamma ln(-ln(1 - rho w) / rho) + sum_m c_m B_m(w)`` and, per parameter,
    ``(L_theta, L_w theta)``."""
    gamma, rho, warp = curve.gamma, curve.rho, curve.warp
    with np.errstate(divide="ignore", invalid="ignore"):
        one = 1.0 - rho * w
        u = -np.log1p(-rho * w)
        ell = np.log(u / rho)
        ell_1 = rho / (one * u)
        ell_2 = (rho / one) ** 2 / u - ell_1 * ell_1
        ell_rho = w / (one * u) - 1.0 / rho
        ell_1_rho = (1.0 / u - rho * w / (u * u)) / (one * one)
    l_w, l_ww = gamma * ell_1, gamma * ell_2
    terms = {"gamma": (ell, ell_1), "rho": (gamma * ell_rho, gamma * ell_1_rho)}
    basis, slope, curvature = warp_basis_slopes(w, len(WARP_KEYS))
    for k, key in enumerate(WARP_KEYS):
        terms[key] = (basis[k], slope[k])
        if k < len(warp) and warp[k]:
            l_w = l_w + warp[k] * slope[k]
            l_ww = l_ww + warp[k] * curvature[k]
    return l_w, l_ww, terms


def _forward_partials(curve, w: np.ndarray, slope: np.ndarray, x: np.ndarray) -> dict:
    """``(d w / d theta, d w' / d theta)`` at fixed exposures ``x``, ``w`` the forward's
    value and ``w'`` its slope there: from ``L(w) = ln x``, ``d w = -L_theta / L_w`` and
    ``w' = 1 / (x L_w)``.  0 where the forward is flat (clipped).

    A warped curve's forward outside its interpolation nodes (``ExpShape._log_nodes``:
    below a hundredth of a code, the darkest values) is the sampled grid's segment between
    the exposures ``X(G_j)``; there the derivatives are the segment's, whose ends move by
    ``d X(G_j) = X(G_j) L_theta(G_j)``."""
    moving = (slope > 0) & (w > 0) & (w < 1)
    out = {}
    if not moving.any():
        return out
    x = np.maximum(x, 1e-12)  # the forward's own floor
    segment = np.zeros_like(moving)
    if curve.warp:
        lo, step, nodes, _, grid_x = curve._log_nodes()
        u = (np.log(x) - lo) / step
        segment = moving & ~((u >= 0.0) & (u <= nodes.size - 1))
        moving &= ~segment
    wm, xm = w[moving], x[moving]
    l_w, l_ww, terms = _log_inverse_terms(curve, wm)
    d = {name: (np.zeros_like(w), np.zeros_like(w)) for name in terms}
    for name, (l_t, l_wt) in terms.items():
        d_w, d_slope = d[name]
        d_w[moving] = -l_t / l_w
        d_slope[moving] = -(l_wt + l_ww * d_w[moving]) / (xm * l_w * l_w)
    if segment.any():
        xs = x[segment]
        j = np.clip(np.searchsorted(grid_x, xs, side="right") - 1, 0, grid_x.size - 2)
        ends = np.unique(np.concatenate([j, j + 1]))
        width = grid_x[j + 1] - grid_x[j]
        a = (xs - grid_x[j]) / width
        rise = _GRID[j + 1] - _GRID[j]
        inner = ends < grid_x.size - 1  # the last exposure is a stand-in, 2 X + 1
        _, _, at_ends = _log_inverse_terms(curve, _GRID[ends[inner]])
        for name, (l_t, _) in at_ends.items():
            moves = np.zeros(grid_x.size)
            with np.errstate(invalid="ignore"):  # X = 0 at the first: L = -inf there
                moves[ends[inner]] = np.where(grid_x[ends[inner]] > 0,
                                              grid_x[ends[inner]] * l_t, 0.0)
            moves[-1] = 2.0 * moves[-2]
            d_w, d_slope = d[name]
            d_w[segment] = rise / width * (-(1.0 - a) * moves[j] - a * moves[j + 1])
            d_slope[segment] = -rise * (moves[j + 1] - moves[j]) / (width * width)
    return d


def _table_partials(curve, beta: float, sat: float, table: np.ndarray) -> dict:
    """Each curve parameter's derivative of the inverse table ``T`` (``model._code_tables``:
    ``T[k] = X(w_k)``, ``w_k = (k / 255 - beta) / (1 - beta)`` clipped to [0, top],
    ``top = 1 - rho (1 - TOP)``, and ``T[255] = sat X(top)``), ``d T = T d ln X``."""
    rho = curve.rho
    codes = np.arange(table.size, dtype=np.float64) / 255.0
    top = 1.0 - rho * (1.0 - TOP)
    raw = (codes - beta) / (1.0 - beta)
    w = np.clip(raw, 0.0, top)
    w[-1] = top
    inside = (raw > 0.0) & (raw < top)
    inside[-1] = False
    lit = table > 0
    l_w, _, terms = _log_inverse_terms(curve, np.where(lit, w, 0.5))
    out = {}
    for name, (l_t, _) in terms.items():
        d_log = l_t.copy()
        if name == "rho":  # the values clipped at the top move with it
            d_log = d_log + np.where(inside, 0.0, l_w * -(1.0 - TOP))
        out[name] = np.where(lit, table * d_log, 0.0)
    d_w = np.where(inside, (codes - 1.0) / (1.0 - beta) ** 2, 0.0)
    out["black"] = np.where(lit, table * l_w * d_w, 0.0)
    out["sat"] = np.zeros_like(table)
    out["sat"][-1] = table[-1] / sat
    return out
