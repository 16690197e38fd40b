"""The device distance transforms (``clblur/opencl/nearest.py``) against scipy and OpenCV.

``nearest_transform``'s distances equal ``scipy.ndimage.distance_transform_edt`` bit for bit;
its indices may differ from scipy's between equally near pixels, so each is checked to be a
feature pixel at exactly the squared distance scipy's own nearest pixel lies at.
``distance`` equals ``clblur.layer_planes.distance_to`` bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from clblur.layer_planes import distance_to

SHAPES = [(1, 1), (1, 37), (41, 1), (2, 3), (257, 301), (400, 500)]
DENSITIES = [0.5, 0.05, 0.002]  # of feature pixels


def assert_exact(outside: np.ndarray, dist: np.ndarray, flat: np.ndarray) -> None:
    """``dist`` is scipy's bit for bit; ``flat`` indexes feature pixels at scipy's exact
    squared distance (computed from scipy's indices, in integers)."""
    h, w = outside.shape
    ref, (ir, ic) = distance_transform_edt(outside, return_indices=True)
    assert dist.shape == (h, w) and dist.dtype == np.float64
    assert np.array_equal(dist.view(np.uint64), ref.view(np.uint64))
    assert flat.shape == (h, w) and flat.dtype == np.int64
    assert flat.min() >= 0 and flat.max() < h * w
    fr, fc = np.divmod(flat, w)
    assert not outside[fr, fc].any(), "an index points at an outside pixel"
    rr, cc = np.indices((h, w), dtype=np.int64)
    got_d2 = (rr - fr) ** 2 + (cc - fc) ** 2
    ref_d2 = (rr - ir) ** 2 + (cc - ic) ** 2
    assert np.array_equal(got_d2, ref_d2)
    own = np.flatnonzero(~outside)
    assert np.array_equal(flat.ravel()[own], own), "a feature pixel is not its own nearest"


def check(outside: np.ndarray) -> None:
    from clblur.opencl.nearest import distance, nearest_transform

    outside = np.asarray(outside, bool)
    dist, flat = nearest_transform(outside)
    assert_exact(outside, dist, flat)
    inside = ~outside
    ref = distance_to(inside)
    got = distance(inside)
    assert np.array_equal(got.view(np.uint64), ref.view(np.uint64))
    assert np.array_equal(got.view(np.uint64), dist.view(np.uint64))


def random_outside(rng, shape, density: float) -> np.ndarray:
    outside = rng.random(shape) >= density
    if outside.all():
        outside[rng.integers(shape[0]), rng.integers(shape[1])] = False
    return outside


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("density", DENSITIES)
def test_random_masks(opencl, rng, shape, density):
    for _ in range(3):
        check(random_outside(rng, shape, density))


@pytest.mark.parametrize("shape", SHAPES)
def test_single_feature_pixel(opencl, rng, shape):
    h, w = shape
    for r, c in {(0, 0), (h - 1, w - 1), (h // 2, w // 3), (0, w - 1), (h - 1, 0)}:
        outside = np.ones(shape, bool)
        outside[r, c] = False
        check(outside)


@pytest.mark.parametrize("shape", [(1, 37), (41, 1), (257, 301), (400, 500)])
def test_full_row_column_and_border(opencl, shape):
    h, w = shape
    for part in [np.s_[h // 2, :], np.s_[:, w // 2], np.s_[-1, :], np.s_[:, 0]]:
        outside = np.ones(shape, bool)
        outside[part] = False
        check(outside)
    border = np.ones(shape, bool)
    border[[0, -1], :] = False
    border[:, [0, -1]] = False
    check(border)
    # only some border pixels: every interior column's nearest feature row is far
    sparse = np.ones(shape, bool)
    sparse[0, ::7] = False
    sparse[-1, 3::11] = False
    check(sparse)


@pytest.mark.parametrize("shape", SHAPES)
def test_all_features(opencl, shape):
    from clblur.opencl.nearest import nearest_transform

    outside = np.zeros(shape, bool)
    dist, flat = nearest_transform(outside)
    assert np.array_equal(dist, np.zeros(shape)) and not np.signbit(dist).any()
    assert np.array_equal(flat, np.arange(outside.size).reshape(shape))
    check(outside)


def test_disc_hole_and_half_planes(opencl):
    h, w = 400, 500
    rr, cc = np.indices((h, w))
    check((rr - 190) ** 2 + (cc - 260) ** 2 < 150 ** 2)  # a disc-shaped hole
    check(cc > rr)  # a diagonal half-plane: many equidistant pairs
    check((rr + cc) % 5 != 0)  # diagonal lines


def test_long_distances(opencl):
    """Farther than OpenCV's float32 answer is trusted (distance_to falls back to scipy), up
    to the largest side taken (squared distances near 2^30)."""
    from clblur.opencl.nearest import MAX_SIDE

    outside = np.ones((3, MAX_SIDE), bool)
    outside[0, 0] = False
    outside[2, MAX_SIDE - 1] = False
    check(outside)
    outside = np.ones((MAX_SIDE, 2), bool)
    outside[MAX_SIDE - 1, 1] = False
    check(outside)


def test_non_bool_masks(opencl, rng):
    from clblur.opencl.nearest import distance, nearest_transform

    outside = random_outside(rng, (33, 47), 0.05)
    dist, flat = nearest_transform(outside.astype(np.uint8) * 7)
    assert_exact(outside, dist, flat)
    ref = distance_to(~outside)
    got = distance((~outside).astype(np.float32))
    assert np.array_equal(got.view(np.uint64), ref.view(np.uint64))


@pytest.mark.parametrize("shape", [(257, 301), (1, 37), (1, 1)])
def test_distance_at(opencl, rng, shape):
    from clblur.opencl.nearest import distance

    inside = ~random_outside(rng, shape, 0.01)
    n = 50
    at = (rng.integers(shape[0], size=n), rng.integers(shape[1], size=n))
    ref = distance_to(inside, at)
    got = distance(inside, at)
    assert got.shape == ref.shape == (n,)
    assert np.array_equal(got.view(np.uint64), ref.view(np.uint64))
    # the pixels of a boolean selection, as the layered code passes them
    at = np.nonzero(rng.random(shape) < 0.3)
    assert np.array_equal(distance(inside, at).view(np.uint64),
                          distance_to(inside, at).view(np.uint64))


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (20, 30)])
def test_no_feature_raises(opencl, shape):
    from clblur.opencl.nearest import distance, nearest_transform

    with pytest.raises(ValueError, match="no feature"):
        nearest_transform(np.ones(shape, bool))
    with pytest.raises(ValueError, match="no inside pixel"):
        distance(np.zeros(shape, bool))


def test_bad_shapes_raise(opencl):
    from clblur.opencl.nearest import MAX_SIDE, nearest_transform

    with pytest.raises(ValueError, match="2-D"):
        nearest_transform(np.zeros((3, 4, 2), bool))
    with pytest.raises(ValueError, match="larger than"):
        nearest_transform(np.zeros((1, MAX_SIDE + 1), bool))


def test_program_is_built_once(opencl):
    from clblur.opencl import runtime
    from clblur.opencl.nearest import nearest_transform

    outside = np.ones((5, 6), bool)
    outside[2, 3] = False
    nearest_transform(outside)
    rt = runtime(None)
    keys = [k for k in rt.programs if k and k[0] == "nearest.cl"]
    assert len(keys) == 1
    program = rt.programs[keys[0]]
    nearest_transform(outside)
    assert rt.programs[keys[0]] is program
