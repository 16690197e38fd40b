"""``clblur.opencl.fill.harmonic_fill`` against the host specification
``clblur.layer_planes.harmonic_fill``.

Tolerance: known pixels bit for bit; elsewhere ``max |device - host| <= TOL`` for values in
[0, 1].  The kernels repeat the reference's float32 operations in its order, and pyrUp and the
Jacobi sweeps match cv2 bit for bit; cv2.pyrDown sums its five taps in one order in its
vectorised loops and another at border and tail pixels, which the kernel cannot follow
everywhere, so pyramid pixels differ by an ulp there and the fill, a convex combination of
them, by a few ulps of 1: at most 1.8e-7 measured over these cases, on PoCL and on an H100
alike, and 2.4e-7 over 300 random shapes, masks and channel counts on PoCL (2026-12); the
bound is 1e-6, about 8 ulps of 1.
"""

from __future__ import annotations

import numpy as np
import pytest

from clblur import layer_planes

TOL = 1e-6


def _disc_hole(h: int, w: int, radius: float) -> np.ndarray:
    y, x = np.mgrid[:h, :w]
    return (y - (h - 1) / 2) ** 2 + (x - (w - 1) / 2) ** 2 > radius ** 2


def _known(kind: str, h: int, w: int, rng) -> np.ndarray:
    """A mask of kind ``kind`` (True: known), with at least one known pixel."""
    if kind == "disc":  # one round hole, a third of the short side across
        known = _disc_hole(h, w, max(min(h, w) / 3, 1.0))
    elif kind == "band":  # a thin hole, two pixels across
        known = np.ones((h, w), bool)
        if h > 2:
            known[h // 3:h // 3 + 2] = False
        else:
            known[:, w // 3:w // 3 + 2] = False
    elif kind == "scattered":  # known pixels scattered, one in a hundred
        known = rng.random((h, w)) < 0.01
    elif kind == "single":  # one known pixel: the deepest pyramid
        known = np.zeros((h, w), bool)
        known[rng.integers(h), rng.integers(w)] = True
    elif kind == "holes":  # random holes of several sizes
        known = np.ones((h, w), bool)
        y, x = np.mgrid[:h, :w]
        for _ in range(6):
            r = rng.uniform(0.5, max(min(h, w) / 4, 1.0))
            known &= (y - rng.uniform(0, h)) ** 2 + (x - rng.uniform(0, w)) ** 2 > r * r
    else:
        raise ValueError(kind)
    if not known.any():
        known[0, 0] = True
    return known


def _check(values: np.ndarray, known: np.ndarray) -> float:
    """Compare the device and host fills; return the worst difference."""
    from clblur.opencl.fill import harmonic_fill

    host = layer_planes.harmonic_fill(values, known)
    dev = harmonic_fill(values, known)
    assert dev.dtype == np.float32 and dev.shape == values.shape
    # known pixels: the input's bits
    assert np.array_equal(dev[known].view(np.uint32), values[known].view(np.uint32))
    worst = float(np.abs(dev.astype(np.float64) - host).max())
    assert worst <= TOL, f"max |device - host| = {worst:.3g} > {TOL}"
    hole = ~known
    if hole.any():  # the fill did something: a device that returned its input would fail
        assert not np.array_equal(dev[hole], values[hole])
    return worst


SHAPES = [(1, 53), (53, 1), (2, 3), (37, 53), (300, 400)]
KINDS = ["disc", "band", "scattered", "single", "holes"]


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_matches_host(opencl, rng, shape, kind, channels):
    h, w = shape
    values = rng.random((h, w, channels), dtype=np.float32)
    _check(values, _known(kind, h, w, rng))


def test_disc_hole_radius_60(opencl, rng):
    """The benchmark case: 300 x 400 x 3, a disc hole of radius 60 (a 6-level pyramid)."""
    values = rng.random((300, 400, 3), dtype=np.float32)
    _check(values, _disc_hole(300, 400, 60))


def test_most_channels(opencl, rng):
    from clblur.opencl.fill import MAX_CHANNELS

    values = rng.random((37, 53, MAX_CHANNELS), dtype=np.float32)
    _check(values, _known("holes", 37, 53, rng))


def test_linear_ramp_is_filled_smoothly(opencl):
    """A ramp with a hole comes back close to the ramp (the fill is a smooth interpolant),
    and identical to the host's: guards against a fill that is wrong the same way twice."""
    from clblur.opencl.fill import harmonic_fill

    h, w = 64, 96
    ramp = np.broadcast_to(np.linspace(0, 1, w, dtype=np.float32), (h, w))[..., None].copy()
    known = _disc_hole(h, w, 12)
    dev = harmonic_fill(ramp, known)
    assert np.abs(dev - ramp).max() < 0.02
    assert np.abs(dev - layer_planes.harmonic_fill(ramp, known)).max() <= TOL


def test_pyramid_shapes_match_reference(rng):
    """The depth decided from the mask alone equals the reference's, decided from its
    float32 weights (pure numpy, no device)."""
    import cv2

    from clblur.opencl.fill import pyramid_shapes

    for shape in SHAPES + [(1, 1), (5, 3), (64, 64)]:
        for kind in KINDS:
            known = _known(kind, *shape, rng)
            level = known.astype(np.float32)
            shapes = [level.shape]
            while min(level.shape) > 1 and not (level > 0).all():
                level = cv2.pyrDown(level).reshape(-1, -(-level.shape[1] // 2))
                shapes.append(level.shape)
            assert pyramid_shapes(known) == shapes, (shape, kind)


def test_group_and_launched_sweeps_agree(opencl, rng, monkeypatch):
    """All levels swept by one work-group, or each sweep launched: the same bits."""
    from clblur.opencl import fill

    values = rng.random((75, 101, 3), dtype=np.float32)
    known = _known("holes", 75, 101, rng)
    results = []
    for pixels in (0, 1 << 30):
        monkeypatch.setattr(fill, "_GROUP_PIXELS_CPU", pixels)
        monkeypatch.setattr(fill, "_GROUP_PIXELS_GPU", pixels)
        results.append(fill.harmonic_fill(values, known))
    assert np.array_equal(results[0].view(np.uint32), results[1].view(np.uint32))


@pytest.mark.parametrize("sweeps", [1, 2, 5])
def test_group_kernel_parity(opencl, rng, sweeps):
    """fill_sweeps_group leaves its result in a after an even count, in b after an odd one,
    as the same number of fill_sweep launches would."""
    from clblur.opencl import runtime
    from clblur.opencl.device import pyopencl_module
    from clblur.opencl.fill import _program

    cl = pyopencl_module()
    rt = runtime(None)
    lh, lw, c = 9, 14, 3
    level = rng.random((lh, lw, c + 1), dtype=np.float32)
    start = rng.random((lh, lw, c), dtype=np.float32)
    mf = cl.mem_flags

    def buf(a):
        return cl.Buffer(rt.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=a.copy())

    got = []
    with rt.lock:
        program = _program(rt, c)
        lv = buf(level)
        a, b = buf(start), buf(start)
        program.run("fill_sweeps_group", rt.queue, (32, 1), (32, 1), level=lv, off=0, lh=lh,
                    lw=lw, a=a, b=b, sweeps=sweeps)
        x, y = buf(start), buf(start)
        for _ in range(sweeps):
            program.run("fill_sweep", rt.queue, (16, 16), None, level=lv, off=0, lh=lh, lw=lw,
                        src=x, dst=y)
            x, y = y, x
        for src in ((b if sweeps % 2 else a), x):
            out = np.empty_like(start)
            cl.enqueue_copy(rt.queue, out, src, is_blocking=True)
            got.append(out)
    assert np.array_equal(got[0], got[1])
    assert not np.array_equal(got[0], start)


def test_rejects_bad_input(opencl):
    from clblur.opencl.fill import harmonic_fill

    values = np.zeros((4, 5, 3), np.float32)
    with pytest.raises(ValueError, match="known pixel"):
        harmonic_fill(values, np.zeros((4, 5), bool))
    with pytest.raises(ValueError, match="channels"):
        harmonic_fill(np.zeros((4, 5, 16), np.float32), np.ones((4, 5), bool))
    with pytest.raises(ValueError, match="known must be"):
        harmonic_fill(values, np.ones((5, 4), bool))
