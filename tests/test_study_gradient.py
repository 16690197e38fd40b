"""The likelihood's closed-form gradient (``clblur.study.gradient``) against differences."""

from __future__ import annotations

import numpy as np
import pytest

from clblur.camera import Camera, random_scene
from clblur.study.compact import compact
from clblur.study.crossfit import assign_blocks
from clblur.study.effects import param_range
from clblur.study.gradient import is_analytic, nll_gradient
from clblur.study.model import null_params
from clblur.study.series import series_groups
from clblur.study.synthetic import scenario
from clblur.study.variants import pixel_nll

# every closed-form parameter of a blur pair (a series adds its images' lt and lw)
PAIR_PARAMS = ["gain", "cg1", "cg2", "vig", "t1", "t2", "na", "nb", "nc", "qoff"]
# the response's: through the inverse table and the forward
SHAPE_PARAMS = ["gamma", "rho", "w1", "w2", "w3", "w4", "black", "black1", "black2", "ce1",
                "ce2", "sat"]


def _differences(g, p: dict, names: list[str]) -> np.ndarray:
    """Central differences of the summed NLL, a millionth of each parameter's range."""
    out = []
    for n in names:
        lo, hi = param_range(n)[1:]
        h = 1e-6 * (hi - lo)
        f = [float(pixel_nll(g, {**p, n: p[n] + s}).sum()) for s in (h, -h)]
        out.append((f[0] - f[1]) / (2 * h))
    return np.array(out)


def _check(g, p: dict, names: list[str]) -> None:
    """Closed form against differences: to 1e-5 where a parameter acts on the exposure or
    variance; to 3e-4 for the response's, whose warped forward is an interpolant whose own
    derivative in the parameters departs from the curve's by that much."""
    nll, grad = nll_gradient(g, p, names)
    assert np.array_equal(nll, pixel_nll(g, p))  # the objective itself, bit for bit
    numeric = _differences(g, p, names)
    shape = np.isin(names, SHAPE_PARAMS)
    scale = np.abs(numeric).max()
    np.testing.assert_allclose(grad[~shape], numeric[~shape], rtol=1e-5, atol=1e-6 * scale)
    np.testing.assert_allclose(grad[shape], numeric[shape], rtol=3e-4, atol=1e-6 * scale)


def _series():
    rng = np.random.default_rng(3)
    cam = Camera(response="gamma:2.2", noise_a=2e-4, noise_b=2e-6)
    scene = random_scene(rng, (24, 32), 3, low=0.03, high=0.9)
    times = [2.0 ** -k for k in range(3, 9)]
    stated = [1 / 8, 1 / 15, 1 / 30, 1 / 60, 1 / 125, 1 / 250]
    groups = series_groups([cam.capture(scene * 8, t, rng=rng) for t in times], stated)
    p = {**null_params(), "gamma": 1.7, "rho": 0.3, "w1": 0.2, "w2": -0.1, "black": 0.01,
         "black1": 0.02, "black2": 0.015, "ce1": 0.05, "ce2": -0.04, "sat": 2.0,
         "na": 1e-3, "nb": 1e-5, "nc": 0.3, "gain": 0.05, "cg1": 0.03, "cg2": -0.02}
    names = ["gain", "cg1", "cg2", "na", "nb", "nc", *SHAPE_PARAMS]
    for i in (1, 2, 3, 4):
        p[f"lt:{i}"] = 0.02 * i - 0.05
        names.append(f"lt:{i}")
        for c in (1, 2):
            p[f"lw:{i}:{c}"] = 0.01 * c - 0.015 * i
            names.append(f"lw:{i}:{c}")
    return groups, p, names


@pytest.mark.parametrize("pooled", [False, True])
def test_series_gradient_matches_differences(pooled):
    """Exposures and white balances of the images, gains and noise, on a warped response
    with values clipped at both ends (their tails' derivatives too), on the rows as they
    are and pooled (``compact``)."""
    groups, p, names = _series()
    assert any(g.censored is not None and (g.censored != 0).any() for g in groups)
    for g in groups:
        _check(compact(g, False, False, True) if pooled else g, p, names)


@pytest.mark.parametrize("effects", [{"vignetting": None}, {"nonuniform_motion": None},
                                     {"quantisation": None, "misregistration": None},
                                     {"psf_scale": None, "optical_blur": None}])
def test_pair_gradient_matches_differences(effects):
    """Vignetting and time weights (through the average and the factor), noise, the
    storage offset, with the geometric variants' histograms mixed in."""
    sc = scenario(effects, np.random.default_rng(5))
    assign_blocks(sc.groups)
    p = {**null_params(), "vig": 0.4, "t1": 0.2, "t2": -0.1, "na": 1e-3, "nb": 1e-5,
         "nc": 0.2, "gain": 0.03, "qoff": -0.3, "sx": 0.3, "sy": -0.2, "pscale": 1.1,
         "ovar": 0.7, "black": 0.02, "black1": 0.01, "black2": 0.03, "gamma": 1.3,
         "rho": 0.7, "w1": 0.1, "ce1": 0.05, "ce2": -0.04, "sat": 1.5}
    for g in sc.groups:
        _check(g, p, PAIR_PARAMS + SHAPE_PARAMS)


def test_the_geometric_variants_alone_are_left_to_differences():
    assert all(is_analytic(n) for n in PAIR_PARAMS + SHAPE_PARAMS + ["lt:3", "lw:2:1"])
    assert not any(is_analytic(n) for n in ["sx", "sy", "pscale", "ovar", "flip:0"])
    with pytest.raises(ValueError, match="pscale"):
        nll_gradient(_series()[0][0], null_params(), ["pscale"])


def test_the_fit_objective_gradient_matches_its_differences():
    """What L-BFGS-B is given (``crossfit._objective_and_gradient``): the penalised NLL per
    value in the fit's unit coordinates, with the warp's ridge (a first version left its
    derivative out and stopped fits partway along the shape's valleys) and a geometric
    variant by forward differences."""
    from clblur.study.crossfit import _objective, _objective_and_gradient

    sc = scenario({"response_shape": 1.6, "misregistration": None}, np.random.default_rng(9))
    assign_blocks(sc.groups)
    names = ["na", "nc", "gamma", "rho", "w1", "w2", "sx", "gain"]
    lo = np.array([param_range(n)[1] for n in names])
    hi = np.array([param_range(n)[2] for n in names])
    z = np.array([0.02, 0.03, 0.3, 0.1, 0.6, 0.45, 0.6, 0.55])
    s0 = null_params()
    f, grad = _objective_and_gradient(sc.groups, names, lo, hi, 1000, z, s0)
    assert f == _objective(sc.groups, names, lo, hi, 1000, z, s0)
    numeric = []
    for i in range(z.size):
        step = np.zeros_like(z)
        step[i] = 1e-6
        numeric.append((_objective(sc.groups, names, lo, hi, 1000, z + step, s0)
                        - _objective(sc.groups, names, lo, hi, 1000, z - step, s0)) / 2e-6)
    np.testing.assert_allclose(grad, numeric, rtol=1e-3, atol=1e-6 * np.abs(numeric).max())
    assert abs(grad[names.index("w1")]) > 1.0  # the ridge's share is tested, not zero
