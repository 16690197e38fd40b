"""clblur.dask_array.blur equals the in-memory blur bit for bit, whatever the chunking."""

from __future__ import annotations

import numpy as np
import pytest

import clblur
from clblur.errors import InputError

da = pytest.importorskip("dask.array")
cdask = pytest.importorskip("clblur.dask_array")


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("CLBLUR_QUIET", "1")


@pytest.fixture
def image(rng):
    return rng.integers(0, 256, (61, 47, 3), dtype=np.uint8)


def _flow(rng, h, w):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    flow = np.stack([8.0 * np.sin(yy / 9.0), 5.0 * np.cos(xx / 6.0) - 2.0], axis=-1)
    return (flow + rng.normal(0, 1.0, flow.shape)).astype(np.float32)


@pytest.mark.parametrize("chunks", [(10, 9, 3), (30, 20, 1), (4, 3, 3)])
@pytest.mark.parametrize("kind", ["uniform", "flow", "dask-flow", "psf"])
def test_equals_in_memory(rng, image, chunks, kind):
    h, w = image.shape[:2]
    motion = {"uniform": (7.5, -3.0), "flow": _flow(rng, h, w), "psf": rng.random((4, 7)),
              "dask-flow": _flow(rng, h, w)}[kind]
    ref = clblur.blur(image, motion, anchor="end", backend="numpy")
    if kind == "dask-flow":
        motion = da.from_array(motion, chunks=(13, 11, 2))  # chunks unlike the image's
    x = da.from_array(image, chunks=chunks)
    out = cdask.blur(x, motion, anchor="end", backend="numpy")
    assert out.shape == image.shape and out.dtype == image.dtype
    np.testing.assert_array_equal(out.compute(scheduler="sync"), ref)


def test_continuous_exposure_equals_in_memory(rng, image):
    flow = _flow(rng, *image.shape[:2])
    ref = clblur.blur(image, flow, "srgb", backend="numpy", exposure="continuous")
    out = cdask.blur(da.from_array(image, chunks=(10, 9, 3)), flow, "srgb", backend="numpy",
                     exposure="continuous")
    np.testing.assert_array_equal(out.compute(scheduler="sync"), ref)


def test_grey_float_image_and_depth_beyond_chunks(rng):
    img = rng.random((40, 30)).astype(np.float32)
    ref = clblur.blur(img, (1.0, 25.0), response="srgb", backend="numpy")
    out = cdask.blur(da.from_array(img, chunks=5), (1.0, 25.0), response="srgb",
                     backend="numpy")
    np.testing.assert_array_equal(out.compute(scheduler="sync"), ref)


@pytest.mark.parametrize("shape, chunks, motion", [
    ((34, 6, 3), (13, 22, 3), (25.0, 4.0)),  # a halo of 15 columns beyond 6
    ((7, 68), (9, 17), (3.0, -20.0)),  # grey, a halo of 12 rows beyond 7
    ((1, 38, 1), (21, 26, 1), "flow"),  # one row, a flow and its bound
    ((27, 56), (14, 8), "flow"),  # grey, a flow and its bound
])
def test_halos_beyond_the_image_and_grey_images(rng, shape, chunks, motion):
    """A motion longer than the image (its halo clipped to the image: map_overlap refuses a
    depth beyond the array) and a grey image beside a 3-D flow with ``max_displacement``
    (map_overlap takes arrays of one rank): both refused before, bit for bit now."""
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    opts = {}
    if motion == "flow":
        motion = rng.normal(0, 15, shape[:2] + (2,)).astype(np.float32)
        opts["max_displacement"] = tuple(np.abs(motion).reshape(-1, 2).max(axis=0))
    ref = clblur.blur(img, motion, "srgb", backend="numpy")
    out = cdask.blur(da.from_array(img, chunks=chunks), motion, "srgb", backend="numpy",
                     **opts)
    assert out.shape == img.shape
    np.testing.assert_array_equal(out.compute(scheduler="sync"), ref)


def test_max_displacement_given_and_too_small(rng, image):
    flow = _flow(rng, *image.shape[:2])
    x = da.from_array(image, chunks=(16, 16, 3))
    ref = clblur.blur(image, flow, backend="numpy")
    most = tuple(np.abs(flow).reshape(-1, 2).max(axis=0))
    ok = cdask.blur(x, flow, backend="numpy", max_displacement=most)
    np.testing.assert_array_equal(ok.compute(scheduler="sync"), ref)
    # an understated bound gives a too-small halo, and the chunk seams came out wrong
    # without a word: each chunk now checks its own vectors against the bound
    low = cdask.blur(x, flow, backend="numpy", max_displacement=(1.0, 1.0))
    with pytest.raises(InputError, match=r"exceeds max_displacement=\(1, 1\)"):
        low.compute(scheduler="sync")


def test_bad_input(image):
    with pytest.raises(TypeError, match="dask array"):
        cdask.blur(image, (1, 0))
    x = da.from_array(image, chunks=16)
    with pytest.raises(ValueError, match="flow field has shape"):
        cdask.blur(x, da.zeros((5, 5, 2), chunks=5))
    with pytest.raises(ValueError, match="backend"):
        cdask.blur(x, (1, 0), backend="cuda")
    bad = np.zeros(image.shape[:2] + (2,), np.float32)
    bad[40, 30, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):  # found by the pass that sizes the halos
        cdask.blur(x, da.from_array(bad, chunks=16))
    with pytest.raises(ValueError):
        cdask.blur(x, (1, 0), response="nonsense")


def test_flow_file_is_read_per_chunk(rng, image, tmp_path):
    flow = _flow(rng, *image.shape[:2])
    np.save(tmp_path / "flow.npy", flow)
    out = cdask.blur(da.from_array(image, chunks=(20, 16, 3)), str(tmp_path / "flow.npy"),
                     backend="numpy")
    np.testing.assert_array_equal(out.compute(scheduler="sync"),
                                  clblur.blur(image, flow, backend="numpy"))


def test_each_chunk_reads_only_its_own_halo(rng, monkeypatch):
    """A flow's halo is per chunk: one fast corner grows only its own chunk's window (the
    result is still the in-memory blur bit for bit)."""
    img = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    flow = np.zeros((64, 96, 2), np.float32)
    flow[:16, :16] = (40.0, 0.0)  # reaches 20 px either way (anchor centre); the rest is still
    seen = {}
    real = cdask._blur_window

    def spy(image, motion, **kw):
        seen[kw["chunk"]] = image.shape[:2]
        return real(image, motion, **kw)

    monkeypatch.setattr(cdask, "_blur_window", spy)
    out = cdask.blur(da.from_array(img, chunks=(16, 16, 3)), flow, backend="numpy")
    np.testing.assert_array_equal(out.compute(scheduler="sync"),
                                  clblur.blur(img, flow, backend="numpy"))
    assert len(seen) == 4 * 6
    assert seen[(0, 0, 16, 16)] == (16 + 2, 16 + 22)  # halo ceil(20) + 2 across, 2 down
    assert seen[(32, 48, 16, 16)] == (2 + 16 + 2, 2 + 16 + 2)  # a still chunk: the margin
