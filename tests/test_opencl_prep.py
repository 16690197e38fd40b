"""Host-side preparation for the OpenCL kernels (pure numpy; runs without a device).

Each table the kernels read is checked against the reference definition it replaces:
rasterised taps against bilinear sampling, code-boundary thresholds and their bucket index
against ``rint(I(E) * Imax)``, the half-storage decision against its stated bound.
"""

from __future__ import annotations

import numpy as np
import pytest

from clblur import reference
from clblur.opencl import half_float, quantisation, response_pack, taps
from clblur.opencl.constants import GRID_SEARCH, QHEAD, RESP_STRIDE
from clblur.pixels import imax, linearisation_table
from clblur.request import make_plan
from clblur.responses import Gamma, Table, response

RESPONSES = ["linear", "exp", "exp:3", "gamma:2.2", "srgb",
             Table.from_response(Gamma(1.8), n=64)]


def apply_taps(lin: np.ndarray, tap_set: taps.IntegerTaps) -> np.ndarray:
    """sum_t w_t L(clamp(p + d_t)) in float64: what integrate_taps computes."""
    h, w = lin.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    acc = np.zeros_like(lin)
    for dx, dy, wt in zip(tap_set.dx, tap_set.dy, tap_set.w, strict=True):
        acc += wt * lin[np.clip(yy + dy, 0, h - 1), np.clip(xx + dx, 0, w - 1)]
    return acc


@pytest.mark.parametrize("motion", [(4.6, -2.3), (-7.25, 3.5), (0.3, 0.0), (12.0, 5.0),
                                    (-40.0, 60.0)])
@pytest.mark.parametrize("anchor", ["start", "center", "end"])
def test_rasterised_uniform_motion_equals_bilinear_sampling(rng, motion, anchor):
    lin = rng.random((23, 31, 2))
    plan = make_plan(lin, motion, "linear", anchor=anchor)
    tap_set = taps.space_invariant_taps(plan)
    np.testing.assert_allclose(apply_taps(lin, tap_set), reference.integrate(lin, plan),
                               rtol=0, atol=1e-12)
    assert np.isclose(tap_set.w.sum(), 1.0)


def test_psf_taps_read_f_of_p_minus_s(rng):
    lin = rng.random((19, 21, 1))
    kernel = rng.random((5, 3))
    plan = make_plan(lin, kernel, "linear")
    np.testing.assert_allclose(apply_taps(lin, taps.space_invariant_taps(plan)),
                               reference.integrate(lin, plan), rtol=0, atol=1e-12)


def test_box_detection():
    def taps_of(motion, **kw):
        return taps.space_invariant_taps(make_plan(np.zeros((4, 4)), motion, **kw))

    assert taps_of((24.0, 0.0)).box() == (0, -12, 12, False)  # N = 25, centred, integer steps
    assert taps_of((0.0, -8.0), anchor="start").box() == (1, 0, 8, False)
    assert taps_of((8.0, 0.0), anchor="end").box() == (0, 0, 8, False)
    # half-integer offsets split bilinearly into whole pixels: 1/8, 1/4, 1/4, 1/4, 1/8, a
    # box with half-weight ends (the same weights, summed by the box kernels)
    assert taps_of((3.0, 0.0)).box() == (0, -2, 2, True)
    assert taps_of((3.0, 0.0), anchor="start").box() == (0, -3, 0, False)
    assert taps_of((6.0, 6.0)).box() is None
    assert taps_of((6.0, 0.0), weights=[1, 2, 3, 4, 5, 6, 7]).box() is None
    assert taps_of(np.ones((1, 5))).box() == (0, -2, 2, False)
    assert taps_of(np.ones((4, 1))).box() == (1, -1, 2, False)
    # the continuous exposure's trapezoid rule: a box with half-weight ends
    assert taps_of((24.0, 0.0), exposure="continuous").box() == (0, -12, 12, True)
    assert taps_of((0.0, -8.0), anchor="start", exposure="continuous").box() == (1, 0, 8, True)
    assert taps_of((2.5, 0.0)).box() is None  # quarter-pixel fractions: unequal weights
    assert taps_of((6.0, 0.0), weights=[1, 2, 2, 2, 2, 2, 1.5]).box() is None


@pytest.mark.parametrize("spec", RESPONSES, ids=str)
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_thresholds_and_buckets_quantise_like_rint(rng, spec, dtype):
    resp = response(spec)
    full = imax(dtype)
    top = float(linearisation_table(resp, dtype, 2.0).max())
    e = np.concatenate([rng.uniform(0, top, 20000), rng.uniform(0, top / 500, 5000),
                        [0.0, top]]).astype(np.float32)
    exact = np.clip(resp.forward(e.astype(np.float64)), 0, 1) * full
    want = np.rint(exact)
    # boundaries are float32: 2^-24 relative, up to 0.004 codes of uint16 (1.5e-5 of uint8)
    margin = 1e-3 if dtype == np.uint8 else 1e-2
    away = np.abs(exact - np.floor(exact) - 0.5) > margin
    t = quantisation.quantisation_thresholds([resp], dtype)
    bits = 8 if dtype == np.uint8 else 16
    assert t.shape == (1, (1 << bits) + quantisation.THRESHOLD_PAD)
    assert np.all(t[0, 1:] >= t[0, :-1]) and np.isposinf(t[0, int(full):]).all()
    by_search = np.searchsorted(t[0], e, side="left")  # count of boundaries below e
    assert np.array_equal(by_search[away], want[away])
    # the kernel's search: bucket start, then `steps` halvings (clblur/opencl/response.cl)
    b = quantisation.quantisation_buckets(t)
    shift, base, nb, steps, stride = (int(v) for v in b[:QHEAD])
    assert stride == t.shape[1] and 1 <= steps <= max(quantisation.BUCKET_MAX_STEPS, bits)
    assert nb > 1  # these responses are well-behaved enough to get real buckets
    idx = np.clip((e.view(np.uint32) >> shift).astype(np.int64) - base, 0, nb - 1)
    q = b[QHEAD:][idx].astype(np.int64)
    step = 1 << (steps - 1)
    while step:
        q += np.where(t[0][q + step - 1] < e, step, 0)
        step >>= 1
    assert np.array_equal(q, by_search)


def test_plain_binary_search_when_buckets_do_not_pay():
    """No positive finite boundary: one bucket, a full binary search."""
    t = np.full((2, 256 + quantisation.THRESHOLD_PAD), np.inf, np.float32)
    t[:, :100] = -np.inf
    b = quantisation.quantisation_buckets(t)
    assert b[:QHEAD].tolist() == [31, 0, 1, 8, t.shape[1]]


def test_thresholds_hold_table_ends():
    """A table flat below its first value and above its last: codes outside are constant."""
    flat = Table([0.0, 1.0, 2.0], [0.2, 0.5, 0.7])
    t = quantisation.quantisation_thresholds([flat], np.uint8)[0]
    assert np.isneginf(t[:int(0.2 * 255 - 0.5)]).all()  # levels below 0.2: always exceeded
    assert np.isposinf(t[int(0.7 * 255 + 0.5):]).all()  # above 0.7: never reached


def test_half_storage_only_where_the_bound_holds():
    exp_table = linearisation_table(response("exp"), np.uint8, 1.0)
    assert half_float.half_error_lsb(response("exp"), exp_table) < 0.1
    # a curve reaching 0.99 within 1e-5 of exposure: half rounding moves codes
    steep = Table([0.0, 1e-5, 1.0], [0.0, 0.99, 1.0])
    steep_table = linearisation_table(steep, np.uint8, 1.0)
    assert half_float.half_error_lsb(steep, steep_table) > half_float.HALF_MAX_LSB
    huge = linearisation_table(response("linear"), np.uint8, 1e5)  # beyond half's range
    assert half_float.half_error_lsb(response("linear"), huge) == np.inf
    img = np.zeros((3, 3, 1), np.uint8)
    assert half_float.half_storage_ok(make_plan(img, (1.0, 0.0), "exp"), exp_table[None])
    assert not half_float.half_storage_ok(make_plan(img.astype(np.uint16), (1.0, 0.0), "exp"),
                                    exp_table[None])


def test_fixed_point_scale_leaves_headroom():
    for top, count in ((6.93, 25), (1.0, 513), (1e4, 4096), (1e-6, 3)):
        scale = taps.fixed_point_scale(top, count)
        assert top * scale * (count + 1) < 2.0**62
        assert top * scale * (count + 2) >= 2.0**58  # and keeps precision


def test_four_channel_padding_and_response_params():
    group = [response("exp:2"), response("gamma:2.2"), Table([0, 1], [0, 1])]
    padded = response_pack.four_channels(group)
    assert len(padded) == 4 and padded[3] is group[0]
    params, tables = response_pack.response_params(group)
    rows = params.reshape(4, RESP_STRIDE)
    assert rows[0].tolist() == [1, 2.0, 0, 0]
    assert rows[1][0] == 2 and np.isclose(rows[1][1], 1 / 2.2)
    assert rows[2].tolist() == [4, 0.0, 0, 2] and tables.tolist() == [0, 1, 0, 1]


@pytest.mark.parametrize("spec", RESPONSES, ids=str)
def test_code_grid_gives_the_searchs_count(rng, spec):
    """Every exposure whose grid cell holds a code is given the search's count; only cells
    holding a boundary are left to the search, and those are few."""
    resp = response(spec)
    t = quantisation.quantisation_thresholds(response_pack.four_channels([resp]), np.uint8)
    grid = quantisation.quantisation_grid(t)
    assert grid is not None
    table, cells, scale, stride = grid
    assert stride == 0 and table.shape == (cells,)  # four equal channels share one row
    row = t[0, :255]
    top = float(row[np.isfinite(row)].max())
    finite = row[np.isfinite(row) & (row >= 0)]
    near = np.concatenate([finite, np.nextafter(finite, np.float32(np.inf)),
                           np.nextafter(finite, np.float32(-np.inf))])
    e = np.concatenate([rng.uniform(0, top * 1.5, 200000), rng.uniform(0, top / 300, 20000),
                        near, [0.0, top, 1e30]]).astype(np.float32)
    e = np.maximum(e, 0)
    code = table[quantisation.grid_cells(e, scale, cells)]
    held = (code & GRID_SEARCH) == 0
    assert np.array_equal(code[held], np.searchsorted(t[0], e[held], side="left"))
    assert np.count_nonzero(table & GRID_SEARCH) <= 255  # cells holding a boundary
    # cell starts are exact: the float32 below a cell's first exposure lies in the cell before
    starts = quantisation._cell_starts(cells, scale)
    assert np.all(np.diff(quantisation.grid_cells(starts, scale, cells)) == 1)


def test_code_grid_per_channel_and_not_for_uint16():
    t = quantisation.quantisation_thresholds(
        [response("exp"), response("gamma:2.2"), response("srgb"), response("exp")], np.uint8)
    table, cells, _, stride = quantisation.quantisation_grid(t)
    assert stride == cells and table.shape == (4 * cells,)
    t16 = quantisation.quantisation_thresholds([response("exp")] * 4, np.uint16)
    assert quantisation.quantisation_grid(t16) is None
    flat = np.full((4, 256 + quantisation.THRESHOLD_PAD), np.inf, np.float32)
    assert quantisation.quantisation_grid(flat) is None  # no boundary: nothing to index
