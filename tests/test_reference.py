"""The numpy reference: invariances, the paper's equations, conventions and errors.

These tests pin the specification itself; tests/test_opencl.py checks the kernels against it.
"""

import numpy as np
import pytest

import clblur
from clblur.demo import STEP_HIGH, STEP_LOW, step_edge
from clblur.motion import sample_counts


def blur(*args, **kw):
    return clblur.blur(*args, backend="numpy", **kw)


def random_image(rng, shape, dtype):
    if np.dtype(dtype).kind == "f":
        return rng.random(shape).astype(dtype)
    top = np.iinfo(dtype).max
    return rng.integers(0, top + 1, shape).astype(dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("resp", ["linear", "exp", "gamma:2.2", "srgb"])
def test_constant_image_stays_constant(dtype, resp):
    top = 1.0 if np.dtype(dtype).kind == "f" else np.iinfo(dtype).max
    for level in (0, 0.37, 1.0):
        img = np.full((9, 13, 3), level * top, dtype=dtype)
        if np.dtype(dtype).kind != "f":
            img = np.full((9, 13, 3), round(level * top), dtype=dtype)
        flow = np.random.default_rng(1).normal(0, 4, (9, 13, 2))
        for motion in ((7.3, -2.1), flow):
            out = blur(img, motion, resp)
            if np.dtype(dtype).kind == "f":
                # Full scale under exp linearises to 1 - q/4 (q = 1/65535 for floats).
                np.testing.assert_allclose(out, img, atol=1e-9 if level < 1 else 0.26 / 65535)
            else:
                np.testing.assert_array_equal(out, img)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize("resp", ["linear", "exp", "gamma:2.2", "srgb"])
def test_zero_motion_is_identity(rng, dtype, resp):
    img = random_image(rng, (11, 7, 2), dtype)
    out = blur(img, (0, 0), resp)
    assert out.dtype == img.dtype and out.shape == img.shape
    if np.dtype(dtype).kind == "f":
        np.testing.assert_allclose(out, img, atol=1e-6 if dtype == np.float32 else 1e-12)
    else:
        np.testing.assert_array_equal(out, img)
    np.testing.assert_array_equal(blur(img, np.zeros((11, 7, 2)), resp), out)


def box_blur_rows(img, k):
    """Eq. 7: mean of f(x - j), j = 0..k-1, clamping at the left edge."""
    padded = np.concatenate([np.repeat(img[:, :1], k - 1, axis=1), img], axis=1)
    return np.mean([padded[:, k - 1 - j:k - 1 - j + img.shape[1]] for j in range(k)], axis=0)


def eq9_rows(img, k, inverse, forward):
    return forward(box_blur_rows(inverse(img), k))


@pytest.mark.parametrize("k", [2, 5, 16])
def test_linear_equals_box_blur_eq7(rng, k):
    img = rng.random((6, 40))
    out = blur(img, (k - 1, 0), "linear", anchor="start", samples=k)
    np.testing.assert_allclose(out, box_blur_rows(img, k), atol=1e-12)


@pytest.mark.parametrize("k", [2, 7, 19])
def test_eq9_reproduced_exactly(rng, k):
    """v = (K-1, 0), anchor start, N = K: the paper's Eq. 9 on integer taps, uint8 exact."""
    img = rng.integers(0, 255, (5, 50)).astype(np.uint8)  # no saturated pixels
    resp = clblur.Exp(1.0)
    expected = eq9_rows(img / 255.0, k, resp.inverse, resp.forward)
    out = blur(img, (k - 1, 0), resp, anchor="start", samples=k)
    np.testing.assert_array_equal(out, np.rint(expected * 255).astype(np.uint8))
    # The default sample count gives the same N for integer lengths.
    np.testing.assert_array_equal(blur(img, (k - 1, 0), resp, anchor="start"), out)


def test_k_cancels_in_eq9(rng):
    """With one shared exposure, k only rescales exposure: Eq. 9 does not depend on it."""
    img = rng.random((12, 30, 3))
    flow = rng.normal(0, 5, (12, 30, 2))
    a = blur(img, flow, clblur.Exp(0.05))
    b = blur(img, flow, clblur.Exp(20.0))
    np.testing.assert_allclose(a, b, atol=1e-12)
    # ... and the result is a geometric mean of (1 - f), here along a horizontal path.
    one_row = rng.random((1, 30))
    g = blur(one_row, (4, 0), "exp", anchor="start", samples=5)
    geo = 1 - np.exp(box_blur_rows(np.log1p(-one_row), 5))
    np.testing.assert_allclose(g, geo, atol=1e-12)


def test_step_edge_matches_closed_form_and_is_asymmetric():
    step = step_edge()
    v = 48
    out = blur(step, (v, 0), "exp", anchor="center")[0].astype(float)
    lo, hi = STEP_LOW / 255, STEP_HIGH / 255
    x = np.arange(step.shape[1])
    edge = step.shape[1] // 2
    # N = v + 1 integer-spaced samples at x - v/2 ... x + v/2; m of them on the bright side.
    offsets = np.arange(v + 1) - v / 2
    m = ((x[:, None] - offsets[None, :]) >= edge).sum(axis=1)
    t = m / (v + 1)
    closed = 1 - (1 - lo) ** (1 - t) * (1 - hi) ** t
    np.testing.assert_allclose(out, np.rint(closed * 255), atol=0)
    linear = blur(step, (v, 0), "linear", anchor="center")[0].astype(float)
    # Photo-consistent blur is brighter than the box blur across the whole transition ...
    transition = (x > edge - v // 2) & (x < edge + v // 2 - 1)
    assert np.all(out[transition] > linear[transition])
    # ... and asymmetric: at the geometric centre it is far above the mid level.
    mid = (STEP_LOW + STEP_HIGH) / 2
    assert out[edge] - mid > 30 and abs(linear[edge] - mid) <= 3


def test_anchors_shift_the_path(rng):
    img = rng.random((3, 40))
    start = blur(img, (6, 0), "linear", anchor="start")
    end = blur(img, (6, 0), "linear", anchor="end")
    center = blur(img, (6, 0), "linear", anchor="center")
    # start integrates [x-6, x], end [x, x+6], center [x-3, x+3].
    np.testing.assert_allclose(start[:, 12:34], end[:, 6:28], atol=1e-12)
    np.testing.assert_allclose(center[:, 12:34], start[:, 15:37], atol=1e-12)


def test_motion_direction_convention():
    """Content travels +x during the exposure: a dot smears to the right of where it started."""
    img = np.zeros((5, 30))
    img[2, 10] = 1.0
    out = blur(img, (8, 0), "linear", anchor="start")
    cols = np.nonzero(out[2])[0]
    assert cols.min() == 10 and cols.max() == 18
    down = blur(img.T.copy(), (0, 8), "linear", anchor="start")
    assert np.nonzero(down[:, 2])[0].min() == 10


def test_time_weights(rng):
    img = rng.random((4, 30))
    w = np.array([3.0, 0, 0, 0, 1.0])
    out = blur(img, (4, 0), "linear", anchor="start", weights=w)
    expected = 0.75 * img + 0.25 * np.concatenate([np.repeat(img[:, :1], 4, 1), img[:, :-4]], 1)
    np.testing.assert_allclose(out, expected, atol=1e-12)
    with pytest.raises(ValueError, match="time weights"):
        blur(img, (4, 0), weights=[1, 2], samples=3)


def test_psf_is_a_convolution(rng):
    img = rng.random((20, 25))
    k = np.zeros((5, 5))
    k[2, 4] = 1.0  # displacement (+2, 0): content moves right
    out = blur(img, k, "linear")
    np.testing.assert_allclose(out[:, 2:], img[:, :-2], atol=1e-12)
    box = np.ones((1, 5))
    np.testing.assert_allclose(blur(img, box, "linear"), blur(img, (4, 0), "linear"),
                               atol=1e-12)


def test_saturation_policy():
    img = np.zeros((3, 21), np.uint8)
    img[:, 10] = 255
    for resp in ("exp", "linear", "srgb"):
        const = np.full((4, 4), 255, np.uint8)
        np.testing.assert_array_equal(blur(const, (5, 0), resp), const)
    base = blur(img, (6, 0), "exp")
    brighter = blur(img, (6, 0), "exp", saturation=8.0)
    assert brighter[1, 10] > base[1, 10] > 0
    # saturation touches only clipped pixels
    unclipped = img.copy()
    unclipped[:, 10] = 254
    np.testing.assert_array_equal(blur(unclipped, (6, 0), "exp", saturation=8.0),
                                  blur(unclipped, (6, 0), "exp"))
    with pytest.raises(ValueError, match="saturation"):
        blur(img, (6, 0), saturation=0.5)


@pytest.mark.parametrize("resp", ["srgb", "gamma:2.2", "exp"])
def test_a_float_image_stays_within_full_scale_under_a_bounded_response(resp):
    # a full-scale float pixel given saturation 3 came back at 1.61 (srgb) and 1.65
    # (gamma 2.2), even unmoved, where the same uint8 image stays at 255
    codes = np.full((6, 20, 3), 128, np.uint8)
    codes[:, 8:11] = 255
    img = codes.astype(np.float32) / 255
    np.testing.assert_allclose(blur(img, (0, 0), resp, saturation=3.0), img, atol=1e-6)
    out = blur(img, (6, 0), resp, saturation=3.0)
    assert out.max() <= 1.0 and out[:, 8:11].min() >= 1.0 - 1e-6
    if resp != "exp":  # a finite I^-1(1): full scale is the same exposure in every dtype
        blurred = blur(codes, (6, 0), resp, saturation=3.0)
        assert np.abs(out * 255 - blurred).max() <= 0.5 + 1e-4


def test_sample_counts_exact_near_integers():
    for n in (1, 2, 5, 17, 100):
        for eps in (0.0, 1e-4, -1e-4, 3e-7, -3e-7):
            length = np.float32(n + eps)
            got = int(sample_counts(length, np.float32(0)))
            assert got == int(np.ceil(np.float64(length))) + 1
    # a diagonal of exact integer length
    assert int(sample_counts(np.float32(3), np.float32(4))) == 6


def test_linear_float_is_unbounded(rng):
    img = (rng.random((6, 8)) * 4).astype(np.float32)  # scene-linear, above 1
    out = blur(img, (3, 0), "linear")
    assert out.max() > 1.5


@pytest.mark.parametrize("bad,match", [
    (np.zeros((0, 5), np.uint8), "empty"),
    (np.zeros((4, 5), np.int32), "dtype"),
    (np.zeros((4, 5, 3, 2), np.uint8), "H x W"),
    (np.full((4, 5), np.nan), "NaN"),
    ([[1, 2]], "numpy array"),
])
def test_bad_images(bad, match):
    with pytest.raises((ValueError, TypeError), match=match):
        blur(bad, (1, 0))


def test_bad_motion_and_options():
    img = np.zeros((4, 5), np.uint8)
    with pytest.raises(ValueError, match="expected \\(4, 5, 2\\)"):
        blur(img, np.zeros((5, 4, 2)))
    flow = np.zeros((4, 5, 2))
    flow[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        blur(img, flow)
    with pytest.raises(ValueError, match="samples must be >= 1"):
        blur(img, (1, 0), samples=0)
    with pytest.raises(ValueError, match="anchor"):
        blur(img, (1, 0), anchor="middle")
    with pytest.raises(ValueError, match="unknown response"):
        blur(img, (1, 0), "cubic")
    with pytest.raises(ValueError, match="backend"):
        clblur.blur(img, (1, 0), backend="cuda")
    with pytest.raises(ValueError, match="PSF weights sum to zero"):
        blur(img, np.zeros((3, 3)))


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_check_flow_refuses_exactly_the_bad_components(dtype, rng):
    """The two-reduction fast path of ``check_flow`` lets through exactly what the counting
    does: one bad component anywhere (first, last, middle) is refused with its count, and
    the bounds +-FLOW_LIMIT themselves are accepted."""
    from clblur.motion import FLOW_LIMIT, check_flow

    flow = rng.uniform(-40, 40, (9, 11, 2)).astype(dtype)
    check_flow(flow)
    check_flow(flow[:0])  # empty: nothing to refuse
    if dtype != np.float16:  # a half cannot hold the limit's neighbours
        edge = flow.copy()
        edge[0, 0, 0], edge[-1, -1, 1] = -FLOW_LIMIT, FLOW_LIMIT
        check_flow(edge)
    bad_values = [np.nan, np.inf, -np.inf]
    if dtype != np.float16:
        bad_values += [np.nextafter(dtype(FLOW_LIMIT), dtype(np.inf)), dtype(-1e9)]
    for value in bad_values:
        for at in ((0, 0, 0), (4, 5, 1), (8, 10, 1)):
            bad = flow.copy()
            bad[at] = value
            kind = "NaN or infinite" if not np.isfinite(value) else "beyond"
            with pytest.raises(ValueError, match=f"contains 1 {kind}|contains 1 value\\(s\\) "
                                                 f"{kind}"):
                check_flow(bad)


@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_far_flow_with_fixed_samples_reads_the_edge(backend, rng, request):
    """A 1e9 px flow pixel with a fixed sample count equals any other vector that leaves the
    image from every sample but the anchor's (so the limit clip is exact), on both backends."""
    if backend == "opencl":
        request.getfixturevalue("opencl")
    img = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    flow = rng.uniform(-3, 3, (24, 32, 2)).astype(np.float32)
    flow[5, 7] = (1e9, -3e8)
    far = flow.copy()
    far[5, 7] = (5e4, -5e4)  # also beyond the image from every non-anchor sample
    got = clblur.blur(img, flow, "srgb", samples=4, backend=backend)
    want = clblur.blur(img, far, "srgb", samples=4, backend=backend)
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="beyond"):  # default N = ceil(|v|) + 1: refused
        clblur.blur(img, flow, "srgb", backend=backend)


def test_sample_weights_of_both_exposures_sum_to_one():
    from clblur.motion import sample_weight, trapezoid_weights

    for n in range(1, 40):
        j = np.arange(n)
        for continuous in (False, True):
            assert np.isclose(sample_weight(j, np.full(n, n), continuous).sum(), 1.0)
        w = trapezoid_weights(n)
        if n > 2:
            assert w[0] == w[-1] == 0.5 * w[1] and np.all(w[1:-1] == w[1])
    assert trapezoid_weights(1).tolist() == [1.0]


@pytest.mark.parametrize("anchor", ["start", "center", "end"])
def test_continuous_exposure_integrates_the_interpolant_exactly(rng, anchor):
    """Samples on whole pixels (an integer axis-aligned vector, the default count) with
    exposure="continuous": the trapezoid rule on the bilinear interpolant, which is linear
    between the samples, i.e. the exact mean over the path (away from the image's edges,
    where the clamp bends it).  "frames" (equal weights, Eq. 9, the samples' mean E) differs
    from it by the first-order end term ((f_0 + f_N-1) / 2 - E) / (N - 1)."""
    row = rng.random((1, 60))
    k = 10  # a vector of 10 px: 11 samples, on whole pixels for every anchor
    a = {"start": 0.0, "center": 0.5, "end": 1.0}[anchor]
    x = np.arange(60.0)
    # the mean of the interpolant over [x - a k, x + (1 - a) k] (content moves right by k:
    # p reads p - v (s - a)), by a fine midpoint rule on the piecewise-linear interpolant
    s = (np.arange(20000) + 0.5) / 20000
    pos = np.clip(x[:, None] - k * (s[None, :] - a), 0, 59)
    exact = np.interp(pos, x, row[0]).mean(axis=1)
    inside = slice(k, 60 - k)
    got = blur(row, (k, 0), "linear", anchor=anchor, exposure="continuous")[0]
    np.testing.assert_allclose(got[inside], exact[inside], atol=1e-7)
    frames = blur(row, (k, 0), "linear", anchor=anchor)[0]
    taps = np.clip(x[:, None] - (np.arange(k + 1) - a * k)[None, :], 0, 59).astype(int)
    end_term = (0.5 * (row[0][taps[:, 0]] + row[0][taps[:, -1]]) - frames) / k
    np.testing.assert_allclose(frames, got + end_term, atol=1e-12)
    assert np.abs(frames - exact)[inside].max() > 1e-3


def test_continuous_exposure_refuses_what_it_cannot_mean(rng):
    img = rng.random((8, 9))
    with pytest.raises(ValueError, match="exposure must be one of"):
        blur(img, (3, 0), "linear", exposure="trapezoid")
    with pytest.raises(ValueError, match="not both"):
        blur(img, (3, 0), "linear", exposure="continuous", weights=[1, 2, 1])
    with pytest.raises(ValueError, match="PSF"):
        blur(img, np.ones((3, 3)), "linear", exposure="continuous")
    # a uniform motion, a uniform field and a fixed count are the same integral
    field = np.broadcast_to(np.float32([4.5, -2.0]), (8, 9, 2)).copy()
    a = blur(img, (4.5, -2.0), "srgb", exposure="continuous")
    np.testing.assert_array_equal(blur(img, field, "srgb", exposure="continuous"), a)
    np.testing.assert_array_equal(blur(img, field, "srgb", exposure="continuous", samples=6),
                                  a)
