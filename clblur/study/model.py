"""The study's forward model: the paper's Eq. 9 with every effect of the vocabulary.

Conventions
-----------
All three data kinds reduce to one form: a *target* pixel ``p`` (blurred image, long exposure,
or the next image of an exposure series) is predicted from 8-bit *source* codes (static image,
short frames, previous exposure) as

    E(p)    = sum_q M(p, q) T[code(q)] / V(q)          (linear-domain average, Eq. 8)
    pred(p) = 255 * (beta + (1 - beta) I(m(p) E(p))),   m = ratio * gain * gain_c * V(p) * X

with ``T`` the inverse response table over the 256 codes and ``X = exp(lt_t - lt_s)`` the
factor an exposure series' target and source images put on their nominal ratio with
exposures of their own (``effects``' ``lt:I``; ``Group.images``), times, per channel, the
factor of their own white balance (``lw:I:c``).  Because ``T`` acts per code,
``M @ onehot(code)`` collapses to a *code histogram* ``H[p, c]`` (weight of source code ``c``
in pixel ``p``'s average).  Non-uniform time weights and vignetting enter linearly in a few
extra histograms (time weights ``P1 = 2s - 1``, ``P2 = 6s^2 - 6s + 1``; ``1/V = 1 + 2c r^2 +
c^2 r^4``), so every model evaluation is a handful of sparse ``n x 256`` products, however long
the motion path.

Noise model of the residual ``y - pred`` (code values), Gaussian with variance
``1/12 + nc + s^2 (na x_t + nb) + (s m)^2 sum_q M^2 (T'^2/12 + na T + nb)``:
target quantisation, noise added to the coded values, target noise and source
quantisation plus noise propagated through the average (``s`` the response slope at the
prediction, ``T'`` the table's code step).

Censoring.  A target at code 0 or at the clip code (255, or a camera's lower clip) says only
that its value lies at or beyond that end, and its likelihood is that of the tail:
``P(y < 0.5)`` or ``P(y > top - 0.5)`` under the same Gaussian (``Group.censored``).  Left
out instead, the pixels that noise pushed over an end would be missing from one side of
every prediction near it, so the values kept there read as a curve that bends away from
the ends (dark values too bright, bright ones too dark): a hidden black level, exposures
and white balances of their own.  An sRGB bracket of a real radiance map with shot and read
noise read as all three with the ends left out, and as none with their tails
(docs/studies/method.md).  Residuals of the values
kept are measured against their mean given that they were kept (``observed_mean``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy import special

from clblur.responses import ExpShape
from clblur.study.effects import (
    PARAMS,
    balance_deviations,
    black_levels,
    channel_exponents,
    channel_gains,
    exposure_deviations,
)

__all__ = ["CODES", "TOP", "WARP_KEYS", "Group", "censored_ends", "forward", "inverse_table",
           "null_params", "gaussian_nll", "observed_mean", "predict", "shape", "time_ok"]

CODES = 256
# Free-shape warp coefficients of the response (``clblur.responses.ExpShape``); absent keys
# are 0, so the paper's Eq. 3 stays the null of ``response_shape``.
WARP_KEYS = ("w1", "w2", "w3", "w4")
TOP = 1.0 - 1.0 / (4 * 255)  # largest normalised value linearised as is (clblur.pixels)
_LOG2PI = float(np.log(2 * np.pi))
# predictions whose tables' products a group remembers (Group.product): the point a
# gradient is taken at and the step being tried
_PRODUCTS_KEPT = 2


@dataclass
class Group:
    """Target pixels of one pair/stack/exposure step and their source histograms."""

    name: str
    target: np.ndarray  # (n, C) observed target codes, float64
    valid: np.ndarray  # (n, C) bool: not censored
    rows: np.ndarray  # (n,) target pixel row
    cols: np.ndarray  # (n,) target pixel column
    shape: tuple[int, int]  # target image H, W
    ratio: float | np.ndarray  # nominal exposure ratio target / source (per row when packed)
    hist: dict[tuple[int, int], list[sp.csr_matrix]]  # (time term, vignette power) -> per channel
    hist_sq: list[sp.csr_matrix]  # squared weights (uniform time, no vignetting)
    r2: np.ndarray  # (n,) normalised radius^2 of the target pixels
    block: np.ndarray = field(default=None)  # (n,) global block id
    fold: np.ndarray = field(default=None)  # (n,) 0 or 1
    source_clipped: bool = False
    # (n, 2) int: each row's source and target image in its exposure series (manifest
    # indices), for the images' own exposures and white balance (``effects``' ``lt:I``,
    # ``lw:I:c``); None outside a series
    images: np.ndarray | None = None
    # (n, C) int8: -1 where the target is at code 0, +1 where it is at the clip code ``top``
    # and the pixel is otherwise usable (its likelihood is the tail beyond that end), else 0;
    # None: nothing censored
    censored: np.ndarray | None = None
    top: float = 255.0  # the clip code of the targets
    # (n,) the brightness of each target pixel's surround: the mean code of the target image
    # over a wide neighbourhood (``clblur.calibration.surround.surround_codes``), for the
    # leftover test's alternative by surround (``clblur.study.leftover``); None: not known
    surround: np.ndarray | None = None

    def time_norm(self, i: int, variant: tuple | None = None) -> np.ndarray:
        """Row sums of time term ``i``'s path weights (the same in every channel) (n,), of
        the plain histograms or of a geometric variant's, ``(effect, key)``, remembered.

        They are part of the group's data, not only a cache: a pooled group
        (``clblur.study.compact``) keeps each channel's rows in that channel's histograms
        alone, so it holds the sums its rows had in full; and a prediction with variants
        mixed in (``clblur.study.variants.predict``) holds the mixture's."""
        cache = self.__dict__.setdefault("_norms", {})
        key = (variant, i)
        if key not in cache:
            hist = self.hist if variant is None else \
                self.__dict__["variants"][variant[0]][variant[1]]
            cache[key] = _rowsum(hist[(i, 0)][0])
        return cache[key]

    def product(self, slot: tuple, h, table: np.ndarray) -> np.ndarray:
        """``h @ table`` for the histogram ``h`` at ``slot``, remembered for the last few
        tables.  Why: a fit's finite-difference gradient moves one parameter at a time, and
        most of them (gains, noise, time weights, shifts) leave the code tables as they were,
        so the sparse products, most of a blur pair's time, repeat; a remembered product is
        the same array, bit for bit.  ``h`` not a sparse matrix (a mix of them,
        ``clblur.study.variants``): not remembered here (its parts are)."""
        if not sp.issparse(h):
            return h @ table
        cache = self.__dict__.setdefault("_products", {})
        key = table.tobytes()
        held = cache.pop(key, None)  # re-inserted last: the least recently used goes first
        if held is None:
            held = {}
            # a prediction reads up to two tables per channel (values, source variance),
            # its gradient one more (ones: the source's row sums, clblur.study.gradient)
            if len(cache) >= _PRODUCTS_KEPT * (2 * self.channels + 1):
                del cache[next(iter(cache))]
        cache[key] = held
        hit = held.get(slot)
        if hit is None:
            hit = held[slot] = h @ table
        return hit

    def __getstate__(self) -> dict:
        """Pickled (to a fold worker) without the remembered products and factors."""
        state = dict(self.__dict__)
        state.pop("_products", None)
        state.pop("_factors", None)
        return state

    @property
    def channels(self) -> int:
        return self.target.shape[1]

    def subset(self, keep: np.ndarray) -> Group:
        idx = np.flatnonzero(keep)
        ratio = self.ratio[idx] if np.ndim(self.ratio) else self.ratio
        return Group(self.name, self.target[idx], self.valid[idx], self.rows[idx],
                     self.cols[idx], self.shape, ratio,
                     {k: [h[idx] for h in v] for k, v in self.hist.items()},
                     [h[idx] for h in self.hist_sq], self.r2[idx], self.block[idx],
                     self.fold[idx], self.source_clipped,
                     None if self.images is None else self.images[idx],
                     None if self.censored is None else self.censored[idx], self.top,
                     None if self.surround is None else self.surround[idx])


def shape(p: dict[str, float], factor: float = 1.0) -> ExpShape:
    """The response curve above the black level (``black = 0``): Eq. 3 generalised by
    ``gamma``, ``rho`` and the warp coefficients (``clblur.responses.ExpShape``);
    ``factor``: a channel's factor on the exponent (``effects.channel_exponents``).

    The same parameters give the same instance (a small cache): a fit's finite differences
    in the other parameters then reuse the curve's sampled and interpolation tables."""
    warp = tuple(float(p.get(k, 0.0)) for k in WARP_KEYS)
    return _shape(float(p["gamma"]) * factor, float(p["rho"]), warp if any(warp) else ())


@functools.lru_cache(maxsize=64)
def _shape(gamma: float, rho: float, warp: tuple[float, ...]) -> ExpShape:
    return ExpShape(0.0, gamma, rho, warp)


def inverse_table(p: dict[str, float], curve: ExpShape | None = None,
                  beta: float | None = None) -> np.ndarray:
    """``T[code]``: exposure of each source code under black level, shape and saturation.

    ``beta``: the channel's normalised black level (``effects.black_levels``); default the
    first channel's, ``p["black"]``."""
    curve = shape(p) if curve is None else curve
    return _code_tables(curve, p["black"] if beta is None else beta, p["rho"], p["sat"])[0].copy()


@functools.lru_cache(maxsize=256)
def _code_tables(curve: ExpShape, beta: float, rho: float, sat: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(T, T'^2 / 12)``: the inverse table (``inverse_table``) and its code step's rounding
    variance, read-only.

    Remembered per curve instance (``shape`` hands out one per parameter set) and value:
    a fit's finite differences move one parameter at a time, and most of them (gains,
    noise, time weights, exposures) leave the tables as they were.  On a series scenario
    the tables were 17 % of ``predict``'s time, 60 % of it rebuilding a table already built."""
    return _build_tables(curve, float(beta), float(rho), float(sat))


def _build_tables(curve: ExpShape, beta: float, rho: float, sat: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    v = np.arange(CODES, dtype=np.float64) / 255.0
    # Full scale as clblur.pixels (I^-1(1) where finite, else the top code bin's margin
    # for Eq. 3), blended continuously in rho: a jump at rho = 1 would let a response
    # *shape* a hair away from Eq. 3 act as a saturation factor of 2.
    top = 1.0 - rho * (1.0 - TOP)
    w = np.clip((v - beta) / (1.0 - beta), 0.0, top)
    t = curve.inverse(w)
    t[-1] = sat * curve.inverse(np.array([top]))[0]
    step = code_step(t)
    rounding = step * step / 12.0
    t.flags.writeable = False
    rounding.flags.writeable = False
    return t, rounding


def code_step(t: np.ndarray) -> np.ndarray:
    """The code step of an inverse table ``t`` whose rounding variance is ``step^2 / 12``
    (linear in ``t``: the gradient differentiates a table's derivative with it too; a
    2-D ``t`` is several tables side by side, one per column)."""
    # np.gradient's central differences (the same operations), without its per-call
    # overhead: the gradient asks for a step per curve parameter at every evaluation
    step = np.empty_like(t)
    step[1:-1] = (t[2:] - t[:-2]) / 2.0
    step[0] = t[1] - t[0]
    step[-1] = step[-2]  # a clipped code's error is the saturation factor's business
    return step


def forward(x: np.ndarray, gamma: float, rho: float, warp=()) -> tuple[np.ndarray, np.ndarray]:
    """Normalised value above the black level and its slope d v / d x at exposure ``x``."""
    return ExpShape(0.0, gamma, rho, tuple(warp)).forward_slope(x)


def time_ok(p: dict[str, float]) -> bool:
    """Time weights must stay positive along the whole path."""
    if p["t1"] == 0.0 and p["t2"] == 0.0:
        return True
    s = np.linspace(0.0, 1.0, 41)
    w = 1.0 + p["t1"] * (2 * s - 1) + p["t2"] * (6 * s * s - 6 * s + 1)
    return bool(w.min() > 0.02)


def predict(g: Group, p: dict[str, float], source_share: bool = False,
            parts: dict | None = None) -> tuple[np.ndarray, ...]:
    """Predicted target codes and residual variances (n, C); with ``source_share`` also the
    share of each variance that the source's own noise carries (``study.leftover``).

    ``parts``: a dict filled with the intermediate values the likelihood's gradient reads
    (``clblur.study.gradient``): the code tables, the linear averages, factors and slopes."""
    n, nc = g.target.shape
    gains = channel_gains(p, nc)
    time_c = (1.0, p["t1"], p["t2"])
    vig_c = (1.0, 2.0 * p["vig"], p["vig"] ** 2)
    vig_out = 1.0 / (1.0 + p["vig"] * g.r2) ** 2
    factors = channel_exponents(p, nc)
    # one instance per distinct exponent: a warped curve caches its sampled forward
    curves = {f: shape(p, f) for f in factors}
    betas = black_levels(p, nc)
    na2, nb2 = p["na"], p["nb"]  # variance coefficients: zero is not a stationary point
    # the sparse products per channel; everything elementwise once on (n, C) arrays
    e = np.empty((n, nc))
    source = np.empty((n, nc))
    norm = np.zeros(n)
    for (i, k) in g.hist:
        if k == 0 and time_c[i] != 0.0:
            norm += time_c[i] * g.time_norm(i)
    # one table per distinct (black level, exponent)
    tables: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}
    for c in range(nc):
        key = betas[c], factors[c]
        if key not in tables:
            t, rounding = _code_tables(curves[factors[c]], betas[c], p["rho"], p["sat"])
            tables[key] = t, rounding + na2 * t + nb2
        t, src_table = tables[key]
        num = np.zeros(n)
        for (i, k), hs in g.hist.items():
            coef = time_c[i] * vig_c[k]
            if coef != 0.0:
                num += coef * g.product((i, k, c), hs[c], t)
        e[:, c] = num
        source[:, c] = g.product(("sq", c), g.hist_sq[c], src_table)
    e /= np.maximum(norm, 1e-12)[:, None]
    own = {i: [d] for i, d in exposure_deviations(p).items()}
    m = ((g.ratio * np.exp(p["gain"]) * vig_out)[:, None] * np.asarray(gains)[None, :]
         * _image_factors(g, own, 1) * _image_factors(g, balance_deviations(p, nc), nc))
    x = m * e
    v, dv = _forward(curves, factors, x, _evaluated(g) if "stats" in g.__dict__ else None)
    beta = np.asarray(betas)[None, :]
    scale = 255.0 * (1.0 - beta)
    pred = 255.0 * beta + scale * v
    s = scale * dv
    # never below the stored code's own rounding variance (1/12 code^2): the optimiser
    # explores negative noise coefficients, where the sum would go to zero or below and
    # the likelihood to NaN; with physical (non-negative) coefficients this changes nothing
    from_source = (s * m) ** 2 * source
    raw = 1.0 / 12.0 + p.get("nc", 0.0) + s * s * (na2 * x + nb2) + from_source
    var = np.maximum(raw, 1.0 / 12.0)
    if parts is not None:
        parts.update(group=g, tables=tables, channel_keys=[(betas[c], factors[c])
                                                           for c in range(nc)],
                     betas=betas, norm=norm, e=e, m=m, x=x, v=v, dv=dv, s=s, scale=scale,
                     source=source,
                     live=raw > 1.0 / 12.0, curves=curves, factors=factors,
                     only=_evaluated(g) if "stats" in g.__dict__ else None)
    if source_share:
        return pred, var, np.clip(from_source / var, 0.0, 1.0)
    return pred, var


def _image_factors(g: Group, dev: dict[int, list[float]], width: int) -> float | np.ndarray:
    """Each row's factor (n, ``width``) from its two images' own log factors ``dev``
    (``{image: one per column}``): ``exp(dev_target - dev_source)``; 1 outside a series or
    where every factor is 0.  The exposures (``lt:I``) take one column, the white balance
    (``lw:I:c``) one per channel (``effects``)."""
    if g.images is None or not any(any(v) for v in dev.values()):
        return 1.0
    # remembered for the last few values, as Group.product remembers its products: a fit's
    # finite differences move one parameter at a time and most leave ``dev`` as it was (the
    # exponentials were 7 % of a Canon series study, 2026-12-03)
    cache = g.__dict__.setdefault("_factors", {})
    key = (width, tuple((i, tuple(d)) for i, d in dev.items()))
    held = cache.pop(key, None)  # re-inserted last: the least recently used goes first
    if held is None:
        # a series has few (source, target) pairs of images: one exponential per pair,
        # bit for bit the per-row values, gathered to the rows
        pairs = g.__dict__.get("_image_pairs")
        if pairs is None:
            span = int(g.images.max(initial=0)) + 1
            code, row_pair = np.unique(g.images[:, 0] * span + g.images[:, 1],
                                       return_inverse=True)
            pairs = g.__dict__["_image_pairs"] = span, code // span, code % span, row_pair
        span, source, target, row_pair = pairs
        logs = np.zeros((span, width))
        for i, d in dev.items():
            if i < span:
                logs[i] = d
        held = np.exp(logs[target] - logs[source])[row_pair]
        held.flags.writeable = False
        if len(cache) >= 2 * _PRODUCTS_KEPT:  # two widths, the last two values of each
            del cache[next(iter(cache))]
    cache[key] = held
    return held


def _forward(curves: dict, factors: list[float], x: np.ndarray,
             only: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The response above the black level and its slope at exposures ``x`` (n, C), channel
    ``c`` through ``curves[factors[c]]``.  ``only``: evaluate just these entries (n, C bool),
    the rest left 0: a pooled group's rows hold one channel each
    (``clblur.study.compact``), and evaluating the warped forward on the empty two thirds
    was a third of a series fit's time."""
    if only is None and len(curves) == 1:
        return curves[factors[0]].forward_slope(x)
    v, dv = np.zeros_like(x), np.zeros_like(x)
    for f, curve in curves.items():  # one call per curve: its channels' entries together
        mask = np.zeros(x.shape, bool)
        mask[:, [c for c in range(x.shape[1]) if factors[c] == f]] = True
        if only is not None:
            mask &= only
        v[mask], dv[mask] = curve.forward_slope(x[mask])
    return v, dv


def _rowsum(h: sp.csr_matrix) -> np.ndarray:
    return np.asarray(h.sum(axis=1)).ravel()


def gaussian_nll(g: Group, pred: np.ndarray, var: np.ndarray, partials: bool = False
                 ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian negative log-likelihood of ``g``'s targets under ``(pred, var)`` (n, C), per
    target pixel, summed over its valid channels and its censored ones (the tail's).

    ``partials``: also its derivatives in each entry's ``pred`` and ``var`` (n, C; 0 where
    an entry is not read), which the likelihood's gradient chains on
    (``clblur.study.gradient``)."""
    stats = g.__dict__.get("stats")
    if stats is not None:  # pooled rows (``clblur.study.compact``): count, sum, sum of squares
        count, s1, s2 = stats
        square = s2 - 2.0 * pred * s1 + count * pred * pred
        nll = 0.5 * (count * (_LOG2PI + np.log(var)) + square / var)
    else:
        count, s1 = 1.0, g.target
        res = g.target - pred
        square = res * res
        nll = 0.5 * (_LOG2PI + np.log(var) + square / var)
    out = np.where(g.valid, nll, 0.0).sum(axis=1)
    if partials:
        d_pred = np.where(g.valid, (count * pred - s1) / var, 0.0)
        d_var = np.where(g.valid, 0.5 * (count / var - square / (var * var)), 0.0)
    if g.censored is not None:
        # the tails, P(y < 0.5) at code 0 and P(y > top - 0.5) at the clip code, on the
        # censored entries alone (a few percent: on all, the tails cost more than the rest)
        r, c = np.nonzero(g.censored)
        if r.size:
            mu = pred[r, c]
            side = g.censored[r, c]
            z = np.where(side < 0, 0.5 - mu, mu - (g.top - 0.5))
            sd = np.sqrt(var[r, c])
            log_tail = special.log_ndtr(z / sd)
            weight = count[r, c] if stats is not None else 1.0
            out = out + np.bincount(r, -log_tail * weight, minlength=out.size)
            if partials:
                # d(-ln Phi(u))/du = -phi(u) / Phi(u), u = z / sd
                u = z / sd
                hazard = -np.exp(-0.5 * u * u - 0.5 * _LOG2PI - log_tail) * weight
                d_pred[r, c] += hazard * np.where(side < 0, -1.0, 1.0) / sd
                d_var[r, c] += hazard * (-0.5 * u / var[r, c])
    if partials:
        return out, d_pred, d_var
    return out


def observed_mean(g: Group, pred: np.ndarray, var: np.ndarray) -> np.ndarray:
    """The mean of a target value given that it was kept (neither end): ``pred`` moved by the
    truncated Gaussian's shift, ``sd (phi(a) - phi(b)) / (Phi(b) - Phi(a))`` with ``a, b`` the
    ends ``0.5`` and ``top - 0.5`` in standard units.

    Why: the residuals of kept values near an end are not centred on the prediction even when
    the model is true (the values noise pushed over the end are the ones missing); measured
    against this mean, they are.  ``pred`` itself where ``g`` censors nothing."""
    if g.censored is None:
        return pred
    sd = np.sqrt(var)
    a = (0.5 - pred) / sd
    b = (g.top - 0.5 - pred) / sd
    # only values within a few deviations of an end move; elsewhere the shift underflows
    near = (a > -8.0) | (b < 8.0)
    if not near.any():
        return pred
    a, b, s = a[near], b[near], sd[near]
    kept = np.maximum(special.ndtr(b) - special.ndtr(a), 1e-300)
    out = pred.copy()
    out[near] = pred[near] + s * (_phi(a) - _phi(b)) / kept
    return out


def _phi(z: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi)


def censored_ends(target: np.ndarray, usable: np.ndarray, top: float) -> np.ndarray:
    """``Group.censored`` of targets ``target`` (codes) whose pixels are ``usable``: -1 at
    code 0, +1 at or above the clip code ``top``."""
    out = np.zeros(target.shape, np.int8)
    out[usable & (target <= 0)] = -1
    out[usable & (target >= top)] = 1
    return out


def _evaluated(g: Group) -> np.ndarray:
    """The (n, C) entries whose prediction the likelihood reads: valid or censored."""
    return g.valid if g.censored is None else g.valid | (g.censored != 0)


def null_params() -> dict[str, float]:
    return {k: v[0] for k, v in PARAMS.items()}
