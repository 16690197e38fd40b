"""Response models: monotonicity, round trips, JSON, spec parsing, validation."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import clblur
from clblur.responses import SRGB, Exp, Gamma, Linear, Table, per_channel, response

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
