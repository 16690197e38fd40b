"""Families fitted in the forward direction (least squares on code values).

``exp`` (the paper's Eq. 3), ``exp-offset``, ``gamma-offset`` and ``emor``: the curve's
parameters and one radiance per sample are fitted jointly; every curve is evaluated through
its ``clblur.responses`` class (this module fits parameters, it writes no curve formula).
Also the pieces every family shares: ``FamilyFit``, the fitted-value floors and the
uncertain-shutter-time model (``time_deviation_basis``).

Conventions
-----------
* ``tau``: nominal relative exposures, longest = 1.  Values normalised to [0, 1].
* ``refine_times`` re-estimates one exposure per image, tied to the nominal value by a
  Gaussian prior (``TIME_SIGMA`` in log units) with the mean and the overall trend of
  ``ln tau`` held at their nominal values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from clblur.errors import InputError, InputTypeError
from clblur.responses import (
    Emor,
    EmorBasis,
    Exp,
    ExpOffset,
    GammaOffset,
    Response,
    Table,
)

__all__ = ["FamilyFit", "ForwardFamily", "ExpFamily", "ExpOffsetFamily", "GammaOffsetFamily",
           "EmorFamily", "time_deviation_basis", "TABLE_SIZE", "FLOOR_LOW", "CURVE_LOW",
           "TIME_SIGMA", "TIME_PRIOR_SCALE"]


TABLE_SIZE = 1024
# Default low end of the fitted values.  The offset families model the black level, so they
# see values down to just above code 0.  The free curves do not model it; near the black level
# (13..25 DN on the Memorial stack, and not constant from image to image) they would bend to
# follow its drift, so they are fitted from 10 % of full scale up (measured: held-out 4-stop
# RMSE 9.6 -> 5.6 DN for nonparametric on Memorial, docs/studies/memorial-calibration.md).
FLOOR_LOW = 0.02
CURVE_LOW = 0.1
# Uncertain shutter times: prior standard deviation of ln(tau) around the nominal value, and
# the residual size (log exposure for the inverse fits) a one-sigma time error is worth.
TIME_SIGMA = 0.1
TIME_PRIOR_SCALE = 0.02


@dataclass(frozen=True)
class FamilyFit:
    response: Response
    params: dict
    n_shape_params: int
    tau: np.ndarray  # relative exposures the curve was fitted with


def _strictly_increasing(y: np.ndarray) -> np.ndarray:
    """Monotone non-decreasing samples -> strictly increasing (tiny ramp, far below 1 DN)."""
    y = np.maximum.accumulate(y)
    span = max(float(y[-1] - y[0]), 1e-12)
    return y + np.linspace(0.0, 1e-7 * span, y.size)


def _table(exposure: np.ndarray, value: np.ndarray, family: str, params: dict) -> Table:
    """A Table with exposure scaled so the top sample is 1 (the scale is arbitrary).

    ``value`` must already be strictly increasing (it is always a grid here)."""
    x = _strictly_increasing(np.maximum(exposure, 0.0))
    return Table(x / x[-1], value,
                 meta={"family": family, "params": params})


def time_deviation_basis(log_tau: np.ndarray) -> np.ndarray:
    """Orthonormal columns spanning the exposure deviations that can be learnt.

    A common offset of ``ln tau`` is the radiance scale and a common stretch is the curve's
    exponent (``g -> g**a`` with ``tau -> tau**a`` fits equally well, down to the all-equal,
    flat-curve solution), so neither can come from the data: refined exposures are
    ``ln tau = ln tau_nominal + B z`` with ``B`` orthogonal to both (n x (n - 2)).
    """
    n = log_tau.size
    if n < 3:
        raise InputError("refine_times needs at least 3 exposures")
    fixed = np.stack([np.ones(n), log_tau - log_tau.mean()], axis=1)
    q, _ = np.linalg.qr(fixed, mode="complete")
    return q[:, 2:]


def _n_time_params(tau: np.ndarray, refine_times: bool) -> int:
    return tau.size - 2 if refine_times else 0


def _refined_tau(tau: np.ndarray, basis: np.ndarray, z: np.ndarray) -> np.ndarray:
    t = tau * np.exp(basis @ z)
    return t / t.max()


class ForwardFamily:
    """A closed-form curve ``v = F(x; theta)`` fitted jointly with per-sample radiances.

    Exposure convention: ``x = E_p * tau_i`` with the curve's own unit (``k = 1`` for the
    exponentials, full scale at ``x = 1`` for the power law).
    """

    name = ""
    default_low = FLOOR_LOW
    theta0: tuple[float, ...] = ()
    lower: tuple[float, ...] = ()
    upper: tuple[float, ...] = ()

    def forward(self, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def inverse(self, v: np.ndarray, theta: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def named(self, theta: np.ndarray) -> dict:
        return {}

    def export(self, theta: np.ndarray) -> Response:
        raise NotImplementedError

    def fit(self, samples, tau: np.ndarray, *, full_scale: float, refine_times: bool = False,
            **opts) -> FamilyFit:
        if opts:
            raise InputTypeError(f"unknown option(s) for the {self.name} model: {sorted(opts)}")
        theta, log_e, log_tau = _joint_forward_fit(self, samples, tau, full_scale, refine_times)
        return FamilyFit(self.export(theta), self.named(theta),
                         len(self.theta0) + _n_time_params(tau, refine_times), np.exp(log_tau))


def _joint_forward_fit(family: ForwardFamily, samples, tau, full_scale, refine_times,
                       time_sigma: float = TIME_SIGMA):
    """Least squares on code values over (curve parameters, log radiance per sample[, log
    exposure per image]); returns ``(theta, log_e, log_tau)`` with ``max(tau) == 1``."""
    v, ok = samples.values, samples.valid
    n_s, n_e = v.shape
    m = len(family.theta0)
    theta0 = np.asarray(family.theta0, dtype=np.float64)
    log_tau0 = np.log(tau)
    with np.errstate(divide="ignore", invalid="ignore"):
        guess = np.log(np.maximum(family.inverse(np.clip(v, 1e-6, 1 - 1e-6), theta0), 1e-12))
    guess = guess - log_tau0[None, :]
    log_e0 = np.array([np.median(g[o]) for g, o in zip(guess, ok, strict=True)])
    log_e0 = np.where(np.isfinite(log_e0), log_e0, np.log(1e-12))
    pi, ii = np.nonzero(ok)
    target = v[pi, ii]
    basis = time_deviation_basis(log_tau0) if refine_times else np.zeros((n_e, 0))
    n_t = basis.shape[1]
    prior_w = 1.0 / time_sigma  # a one-sigma deviation costs as much as a 1-DN residual

    def unpack(p):
        return p[:m], p[m:m + n_s], log_tau0 + basis @ p[m + n_s:]

    def residuals(p):
        theta, log_e, lt = unpack(p)
        r = (family.forward(np.exp(log_e[pi] + lt[ii]), theta) - target) * full_scale
        return np.concatenate([r, prior_w * p[m + n_s:]]) if n_t else r

    n_res = target.size + n_t
    rows = np.arange(target.size)
    blocks = [sp.csr_matrix((np.ones(target.size), (rows, pi)), shape=(n_res, n_s))]
    if m:
        blocks.insert(0, sp.csr_matrix(np.vstack([np.ones((target.size, m)),
                                                  np.zeros((n_t, m))])))
    if n_t:
        blocks.append(sp.csr_matrix(np.ones((n_res, n_t))))
    sparsity = sp.hstack(blocks).tocsr()
    p0 = np.concatenate([theta0, log_e0, np.zeros(n_t)])
    lower = np.concatenate([family.lower, np.full(n_s + n_t, -np.inf)])
    upper = np.concatenate([family.upper, np.full(n_s + n_t, np.inf)])
    sol = least_squares(residuals, p0, jac_sparsity=sparsity, bounds=(lower, upper),
                        method="trf", tr_solver="lsmr", x_scale="jac", max_nfev=200)
    theta, log_e, log_tau = unpack(sol.x)
    shift = log_tau.max()  # keep the longest exposure at 1; radiances absorb the shift
    return theta, log_e + shift, log_tau - shift


class ExpFamily(ForwardFamily):
    """The paper's Eq. 3 (``clblur.responses.Exp`` with ``k = 1``): no shape parameter once k is
    absorbed in x."""

    name = "exp"

    def forward(self, x, theta):
        return Exp(1.0).forward(x)

    def inverse(self, v, theta):
        return Exp(1.0).inverse(v)

    def export(self, theta):
        return Exp(1.0)  # k is set on the paper's normalised axis by clblur.calibration.fit


class ExpOffsetFamily(ForwardFamily):
    """Eq. 3 above a black level ``b``: fits the parameters of ``clblur.responses.ExpOffset``."""

    name = "exp-offset"
    theta0, lower, upper = (0.02,), (0.0,), (0.5,)

    def curve(self, theta) -> ExpOffset:
        return ExpOffset(black=float(theta[0]), k=1.0)

    def forward(self, x, theta):
        return self.curve(theta).forward(x)

    def inverse(self, v, theta):
        return self.curve(theta).inverse(v)

    def named(self, theta):
        return {"black_level": float(theta[0])}

    def export(self, theta):
        return _export(self.curve(theta), self.name, self.named(theta))


class GammaOffsetFamily(ForwardFamily):
    """A power law above a black level: fits the parameters of ``clblur.responses.GammaOffset``."""

    name = "gamma-offset"
    theta0, lower, upper = (0.02, 2.2), (0.0, 0.2), (0.5, 10.0)

    def curve(self, theta) -> GammaOffset:
        return GammaOffset(black=float(theta[0]), gamma=float(theta[1]))

    def forward(self, x, theta):
        return self.curve(theta).forward(x)

    def inverse(self, v, theta):
        return self.curve(theta).inverse(v)

    def named(self, theta):
        return {"black_level": float(theta[0]), "gamma": float(theta[1])}

    def export(self, theta):
        return _export(self.curve(theta), self.name, self.named(theta))


def _export(curve: Response, family: str, params: dict) -> Table:
    """A fitted family as the dense ``Table`` the kernels run (exposure top scaled to 1)."""
    t = curve.as_table(TABLE_SIZE)
    return _table(t.exposure, t.value, family, params)



class _EmorCurve(ForwardFamily):
    name = "emor"

    def __init__(self, basis: EmorBasis, components: int, emor_dir=None):
        self.basis, self.m, self.emor_dir = basis, components, emor_dir
        self.theta0 = (0.0,) * components
        self.lower, self.upper = (-np.inf,) * components, (np.inf,) * components

    def curve(self, theta) -> Emor:
        return Emor(tuple(theta), emor_dir=self.emor_dir)

    def forward(self, x, theta):
        # unconstrained during the fit (the least-squares steps need a smooth model)
        return np.interp(x, self.basis.grid, self.curve(theta).raw_curve())

    def inverse(self, v, theta):
        return self.curve(theta).inverse(v)

    def named(self, theta):
        return {"components": self.m, "coefficients": [float(t) for t in theta]}

    def export(self, theta):
        c = self.curve(theta)
        return _table(self.basis.grid, c.forward(self.basis.grid), self.name, self.named(theta))


class EmorFamily:
    """Grossberg & Nayar's EMoR: mean curve plus ``components`` principal components.

    Fitted in the forward direction like the closed-form families (coefficients and one
    radiance per sample, least squares on code values).  Exposure convention: full scale at
    exposure 1, as in the basis.
    """

    name = "emor"
    default_low = CURVE_LOW

    def fit(self, samples, tau, *, full_scale, refine_times=False, components: int = 5,
            emor_dir=None, **opts) -> FamilyFit:
        if opts:
            raise InputTypeError(f"unknown option(s) for the emor model: {sorted(opts)}")
        if not isinstance(components, (int, np.integer)) or not 1 <= components <= 25:
            raise InputError(f"EMoR components must be an integer in 1..25, got {components!r}")
        curve = _EmorCurve(EmorBasis.load(emor_dir), int(components),
                           None if emor_dir is None else str(emor_dir))
        theta, _, log_tau = _joint_forward_fit(curve, samples, tau, full_scale, refine_times)
        return FamilyFit(curve.export(theta), curve.named(theta),
                         int(components) + _n_time_params(tau, refine_times), np.exp(log_tau))
