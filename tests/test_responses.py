"""Response models: monotonicity, round trips, JSON, spec parsing, validation."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import clblur
from clblur.responses import (
    RANGES,
    SRGB,
    Emor,
    Exp,
    ExpOffset,
    ExpShape,
    Gamma,
    GammaOffset,
    Linear,
    MonotoneSpline,
    Polynomial,
    Table,
    for_device,
    from_dict,
    per_channel,
    response,
)

k_values = st.floats(min_value=1e-3, max_value=1e3)
gammas = st.floats(min_value=0.2, max_value=5.0)
values = st.floats(min_value=0.0, max_value=1.0 - 1e-6)


def table_response():
    x = np.linspace(0, 3, 50)
    return Table(x, 1 - np.exp(-x) * 0.95 - 0.05 * (1 - x / 3))


@settings(max_examples=60, deadline=None)
@given(k=k_values, v=st.lists(values, min_size=2, max_size=20))
def test_exp_monotone_and_round_trip(k, v):
    r = Exp(k)
    v = np.sort(np.asarray(v))
    x = r.inverse(v)
    assert np.all(np.diff(x) >= 0)
    np.testing.assert_allclose(r.forward(x), v, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(g=gammas, v=st.lists(values, min_size=2, max_size=20))
def test_gamma_monotone_and_round_trip(g, v):
    r = Gamma(g)
    v = np.sort(np.asarray(v))
    assert np.all(np.diff(r.inverse(v)) >= 0)
    np.testing.assert_allclose(r.forward(r.inverse(v)), v, atol=1e-10)


@settings(max_examples=60, deadline=None)
@given(v=st.lists(values, min_size=2, max_size=20))
def test_srgb_table_linear_round_trip(v):
    v = np.sort(np.asarray(v))
    for r in (SRGB(), Linear(), table_response()):
        if isinstance(r, Table):
            v = np.clip(v, r.value[0], r.value[-1])
        assert np.all(np.diff(r.inverse(v)) >= 0)
        np.testing.assert_allclose(r.forward(r.inverse(v)), v, atol=1e-10)


def test_srgb_is_continuous_at_the_knee():
    r = SRGB()
    lo, hi = r.forward(np.array([r.knee - 1e-12, r.knee + 1e-12]))
    assert abs(lo - hi) < 1e-6


def test_exp_saturates_only_at_infinity():
    assert math.isinf(float(Exp(2.0).inverse(np.array(1.0))))
    assert float(Exp(2.0).forward(np.array(10.0))) < 1.0
    assert float(Exp(2.0).forward(np.array(1.0))) == pytest.approx(1 - math.exp(-2))


@pytest.mark.parametrize("r", [Linear(), Exp(0.7), Gamma(2.4), SRGB(), table_response()])
def test_json_round_trip(tmp_path, r):
    path = tmp_path / "r.json"
    r.save(path)
    back = clblur.load_response(path)
    assert back == r
    assert response(str(path)) == r
    assert response(path) == r  # a pathlib.Path too, as every other path clblur takes
    v = np.linspace(0, 0.99, 17)
    np.testing.assert_array_equal(back.inverse(v), r.inverse(v))


@pytest.mark.parametrize("spec,expected", [
    ("linear", Linear()), ("exp", Exp(1.0)), ("exp:3", Exp(3.0)), ("gamma:2.2", Gamma(2.2)),
    ("srgb", SRGB()),
])
def test_spec_parsing(spec, expected):
    assert response(spec) == expected


@pytest.mark.parametrize("spec,match", [
    ("gamma:0", "positive"), ("gamma:-1", "positive"), ("gamma:abc", "number"),
    ("gamma", "exponent"), ("nope", "unknown response"), ("exp:0", "positive"),
    # outside the accepted ranges: refused with the range named
    ("gamma:1e-10", r"within \[0.1, 10\]"), ("gamma:1e-300", r"within \[0.1, 10\]"),
    ("gamma:100", r"within \[0.1, 10\]"), ("exp:1e9", r"within \[1e-06, 1e\+06\]"),
    # with context: which spec, what was expected
    ("exp:abc", r"response spec 'exp:abc': exp k must be a number, expected exp:K"),
])
def test_bad_specs(spec, match):
    with pytest.raises(ValueError, match=match):
        response(spec)


def test_bad_response_files(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        clblur.load_response(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="cannot read"):
        clblur.load_response(bad)
    bad.write_text('{"kind": "cubic"}')
    with pytest.raises(ValueError, match="unknown response kind"):
        clblur.load_response(bad)


def test_table_validation():
    with pytest.raises(ValueError, match="strictly increasing"):
        Table([0, 1, 1], [0, 0.5, 1])
    with pytest.raises(ValueError, match="within"):
        Table([0, 1], [0, 1.5])
    with pytest.raises(ValueError, match="at least 2"):
        Table([0], [0])


def test_per_channel():
    assert per_channel("srgb", 3) == [SRGB()] * 3
    assert per_channel(["linear", "exp", "srgb"], 3)[1] == Exp()
    with pytest.raises(ValueError, match="per-channel"):
        per_channel(["linear", "exp"], 3)


FAMILIES = [
    ExpOffset(0.05, 2.0), GammaOffset(0.04, 2.4), ExpShape(0.02, 1.3, 0.4, (0.3, -0.2, 0.1)),
    ExpShape(), Polynomial((0.0, 0.3, 0.2, 0.5)),
    MonotoneSpline.from_vector(np.linspace(-1.0, 1.0, 16)),
]


@pytest.mark.parametrize("r", FAMILIES, ids=lambda r: r.kind + str(len(r.vector())))
def test_families_parameters_round_trip(r):
    v = np.linspace(0.06, 0.95, 50)
    x = r.inverse(v)
    assert np.all(np.diff(x) > 0)
    np.testing.assert_allclose(r.forward(x), v, atol=1e-6)
    again = type(r).from_vector(r.vector())
    np.testing.assert_allclose(again.inverse(v), x, rtol=1e-9)
    assert from_dict(r.to_dict()) == r
    # kernels run any family as its dense table, within 1e-5 of the formula
    t = for_device(r)
    assert t.kind == "table"
    np.testing.assert_allclose(t.forward(x), v, atol=1e-5)


def test_exp_shape_nests_the_paper_curve():
    v = np.linspace(0.0, 0.99, 40)
    np.testing.assert_allclose(ExpShape().inverse(v), Exp(1.0).inverse(v), rtol=1e-12)
    x = np.geomspace(1e-4, 10, 30)
    got, slope = ExpShape().forward_slope(x)
    np.testing.assert_allclose(got, Exp(1.0).forward(x), rtol=1e-12)
    np.testing.assert_allclose(slope, np.exp(-x), rtol=1e-9)
    # with a warp the sampled slope matches a finite difference
    r = ExpShape(0.0, 1.2, 0.5, (0.4, -0.3))
    x = np.geomspace(1e-3, 1.0, 20)
    _, s = r.forward_slope(x)
    fd = (r.forward(x * 1.001) - r.forward(x / 1.001)) / (x * 1.001 - x / 1.001)
    np.testing.assert_allclose(s, fd, rtol=0.05)


@pytest.mark.parametrize("black", [0.0, 0.03])
def test_exp_shape_warped_forward_inverts_the_inverse(black):
    # the warped forward (Hermite nodes + one Newton step) round-trips the closed-form
    # inverse to far below a code, value and slope, over the curves a fit explores
    rng = np.random.default_rng(7)
    v = np.linspace(black + 0.003, 0.995, 400)
    fine = np.linspace(black + 1e-4, 1.0 - 1e-4, 20000)
    tried = 0
    while tried < 12:
        r = ExpShape(black, rng.uniform(0.6, 2.8), rng.uniform(0.01, 1.0),
                     tuple(rng.uniform(-0.4, 0.4, 4)))
        if np.min(np.diff(np.log(r.inverse(fine))) / np.diff(fine)) < 0.3:
            continue  # nearly turning back: the fit's monotone flattening, not a curve
        tried += 1
        x = r.inverse(v)
        got, slope = r.forward_slope(x)
        np.testing.assert_allclose(got, v, atol=1e-7)
        dv = 1e-6
        dx_dv = (r.inverse(v + dv) - r.inverse(v - dv)) / (2 * dv)
        np.testing.assert_allclose(slope * dx_dv, 1.0, rtol=1e-4)


def test_emor_family_round_trip(shared_data):
    if not (shared_data / "crf" / "emor.txt").is_file():
        pytest.skip("EMoR basis not in the shared data")
    r = Emor((0.5, -0.2), emor_dir=str(shared_data / "crf"))
    v = np.linspace(0.05, 0.95, 30)
    np.testing.assert_allclose(r.forward(r.inverse(v)), v, atol=1e-9)
    assert from_dict(r.to_dict()) == r


def test_family_ranges_enforced():
    lo, hi = RANGES["black"]
    with pytest.raises(ValueError, match="black level must be within"):
        ExpOffset(hi + 0.1)
    with pytest.raises(ValueError, match="gamma exponent must be within"):
        GammaOffset(0.0, 20.0)
    with pytest.raises(ValueError, match="rho must be within"):
        ExpShape(0.0, 1.0, 2.0)
    with pytest.raises(ValueError, match="knots"):
        MonotoneSpline([0.0, 0.5, 0.9], [0.0, 0.0])


def test_a_document_key_that_would_be_ignored_is_refused(tmp_path):
    """A hand-written {"kind": "gamma", "gamma": 2.4} was read as the family's default (gamma
    2.2) without a word: keys outside a response document's own are refused, in single and
    per-channel documents, and the documents clblur writes still read."""
    import json

    from clblur.responses import Gamma, per_channel, response

    for doc in ({"kind": "gamma", "gamma": 2.4}, {"kind": "exp", "k": 3.0},
                {"kind": "table", "exposure": [0, 1], "value": [0, 1]}):
        with pytest.raises(ValueError, match="unknown key.*under 'params'"):
            response(doc)
    with pytest.raises(ValueError, match=r"per-channel response document has unknown key"):
        per_channel({"kind": "per-channel", "channels": [Gamma(2.0).to_dict()] * 3,
                     "note": "x"}, 3)
    path = tmp_path / "g.json"
    Gamma(2.4).save(path)
    assert response(str(path)) == Gamma(2.4)
    path.write_text(json.dumps({"kind": "gamma", "params": {"gamma": 2.4}}))
    assert response(str(path)) == Gamma(2.4)


@pytest.mark.parametrize("n", [0, 1, 2, 4, 6])
def test_warp_basis_slopes_are_the_legendre_terms_and_their_derivatives(n):
    # the recurrence (clblur.responses.warp_basis_slopes) against numpy's Legendre series:
    # B_m(w) = P_m(2w - 1) - 1, and its first and second derivatives in w; any shape of w
    from clblur.responses import warp_basis, warp_basis_slopes

    legendre = np.polynomial.legendre
    w = np.random.default_rng(n).random((7, 5))
    t = 2.0 * w - 1.0
    basis, slope, curvature = warp_basis_slopes(w, n)
    assert basis.shape == slope.shape == curvature.shape == (n, 7, 5)
    for m in range(1, n + 1):
        series = [0.0] * m + [1.0]
        np.testing.assert_allclose(basis[m - 1], legendre.legval(t, series) - 1.0,
                                   rtol=0, atol=1e-13)
        np.testing.assert_allclose(slope[m - 1], 2.0 * legendre.legval(
            t, legendre.legder(series)), rtol=0, atol=1e-12)
        np.testing.assert_allclose(curvature[m - 1], 4.0 * legendre.legval(
            t, legendre.legder(series, 2)), rtol=0, atol=1e-11)
    # the public basis clips to [0, 1] and is the same recurrence's values
    np.testing.assert_array_equal(warp_basis(np.array([-0.5, 0.3, 1.5]), n),
                                  warp_basis_slopes(np.array([0.0, 0.3, 1.0]), n)[0])
    if n:
        assert np.all(warp_basis(np.ones(3), n) == 0.0)  # every term vanishes at w = 1
