"""Tiled blur == untiled blur, bit for bit; files are streamed and written atomically."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

import clblur
from clblur import halo, io, tiling
from clblur.io import MappedRaster, describe_size, read_image, write_flow, write_image
from clblur.tiling import blur_file, blur_tiled, choose_tile


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("CLBLUR_QUIET", "1")


def _image(rng, shape=(37, 53, 3), dtype=np.uint8):
    if np.dtype(dtype).kind == "f":
        return rng.random(shape).astype(dtype)
    return rng.integers(0, np.iinfo(dtype).max + 1, shape, dtype=dtype)


def _cross_tile_flow(rng, h, w):
    """Smooth large motion (reaching across several 8-pixel tiles) plus noise."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    flow = np.stack([9.0 * np.sin(yy / 7.0) + 2.0, -6.0 * np.cos(xx / 11.0)], axis=-1)
    return (flow + rng.normal(0, 1.5, flow.shape)).astype(np.float32)


MOTIONS = {
    "uniform": lambda rng, h, w: (7.3, -2.5),
    "flow": _cross_tile_flow,
    "psf": lambda rng, h, w: rng.random((5, 9)),  # off-centre-free but asymmetric extent
}


@pytest.mark.parametrize("kind", MOTIONS)
@pytest.mark.parametrize("anchor", ["start", "center", "end"])
def test_tiled_equals_untiled_bitwise(rng, kind, anchor):
    img = _image(rng)
    motion = MOTIONS[kind](rng, *img.shape[:2])
    ref = clblur.blur(img, motion, anchor=anchor, backend="numpy")
    for tile in (8, (5, 13), 200):  # halos cross the border; 200: one tile, whole image
        out = np.zeros_like(img)
        blur_tiled(img, out, motion, anchor=anchor, backend="numpy", tile=tile)
        np.testing.assert_array_equal(out, ref, err_msg=f"tile {tile}")


def test_options_pass_through_tiles(rng):
    img = _image(rng, (29, 31), np.uint16)
    flow = _cross_tile_flow(rng, 29, 31)
    kw = dict(response="gamma:2.2", samples=5, weights=[1, 2, 3, 2, 1], saturation=2.0)
    ref = clblur.blur(img, flow, backend="numpy", **kw)
    out = np.zeros_like(img)
    blur_tiled(img, out, flow, backend="numpy", tile=(6, 7), **kw)
    np.testing.assert_array_equal(out, ref)


def test_continuous_exposure_passes_through_tiles(rng):
    """Each tile keeps its pixels' counts and end weights: bit for bit the untiled blur."""
    img = _image(rng, (29, 31), np.uint8)
    flow = _cross_tile_flow(rng, 29, 31)
    for kw in (dict(exposure="continuous"), dict(exposure="continuous", samples=6)):
        ref = clblur.blur(img, flow, "srgb", backend="numpy", **kw)
        out = np.zeros_like(img)
        blur_tiled(img, out, flow, "srgb", backend="numpy", tile=(6, 7), **kw)
        np.testing.assert_array_equal(out, ref)
    # and the option is in effect (the same fixed count, equal weights)
    assert not np.array_equal(ref, clblur.blur(img, flow, "srgb", backend="numpy", samples=6))


def test_halo_too_small_breaks_equality(rng, monkeypatch):
    """The equality tests can fail: without a halo the tile edges differ."""
    img = _image(rng)
    ref = clblur.blur(img, (7.3, -2.5), backend="numpy")
    monkeypatch.setattr(halo, "halo_for_reach", lambda reach: 0)
    out = np.zeros_like(img)
    blur_tiled(img, out, (7.3, -2.5), backend="numpy", tile=8)
    assert (out != ref).any()


def test_flow_halo_is_per_tile(rng):
    img = _image(rng, (24, 40, 3))
    flow = np.zeros((24, 40, 2), np.float32)
    flow[:, 30:, 0] = 20.0  # large motion only in the right part
    out = np.zeros_like(img)
    run = blur_tiled(img, out, flow, backend="numpy", tile=(24, 10))
    np.testing.assert_array_equal(out, clblur.blur(img, flow, backend="numpy"))
    assert run.halo == (2, 12)  # ceil(20 * 0.5) + 2 across, 0 + 2 down
    assert run.tiles == 4


def test_memory_budget_sets_tile_and_stays_equal(rng):
    img = _image(rng, (90, 120, 3))
    per_px = tiling.window_bytes_per_px(3, 1, False)
    budget = 45 * 45 * per_px
    out = np.zeros_like(img)
    run = blur_tiled(img, out, (3.0, 0.0), backend="numpy", memory_budget=budget)
    hy, hx = run.halo
    th, tw = run.tile
    assert (th + 2 * hy) * (tw + 2 * hx) * per_px <= budget
    assert (th + 1 + 2 * hy) * (tw + 1 + 2 * hx) * per_px > budget  # the largest that fits
    assert run.tiles > 1
    np.testing.assert_array_equal(out, clblur.blur(img, (3.0, 0.0), backend="numpy"))


def test_choose_tile_rejects_budget_below_halo():
    with pytest.raises(ValueError, match="too small for a halo"):
        choose_tile((100, 100), (50, 50), 400, 1000)
    # a budget that leaves tiles of a few pixels beside the halo is refused too: 200 KiB on
    # a 3000 x 2000 uint16 frame ran for more than 12 minutes
    per_px = tiling.window_bytes_per_px(3, 2, False)
    with pytest.raises(ValueError, match="tiles of 32 px a side need"):
        choose_tile((2000, 3000), (9, 15), per_px, 200 * 2**10)
    assert choose_tile((2000, 3000), (9, 15), per_px, (32 + 18) * (32 + 30) * per_px) == (32, 32)
    assert choose_tile((10, 12), (9, 15), per_px, 10 * 12 * per_px) == (10, 12)  # whole


def test_grey_image_and_zarr_arrays(rng):
    zarr = pytest.importorskip("zarr")
    img = _image(rng, (33, 27), np.float32)
    src = zarr.create_array(store={}, shape=img.shape, chunks=(10, 10), dtype=img.dtype)
    src[:] = img
    dst = zarr.create_array(store={}, shape=img.shape, chunks=(7, 9), dtype=img.dtype)
    blur_tiled(src, dst, (0.0, 4.5), response="srgb", backend="numpy", tile=9)
    np.testing.assert_array_equal(dst[:], clblur.blur(img, (0.0, 4.5), response="srgb",
                                                       backend="numpy"))


def test_memmap_flow_is_read_window_by_window(rng, tmp_path):
    img = _image(rng, (30, 20, 3))
    flow = _cross_tile_flow(rng, 30, 20)
    np.save(tmp_path / "f.npy", flow.astype(np.float16))
    mapped = np.load(tmp_path / "f.npy", mmap_mode="r")
    assert isinstance(io.as_array_like(mapped), MappedRaster)
    out = np.zeros_like(img)
    blur_tiled(img, out, mapped, backend="numpy", tile=7)
    ref = clblur.blur(img, flow.astype(np.float16).astype(np.float32), backend="numpy")
    np.testing.assert_array_equal(out, ref)


@pytest.mark.parametrize("bad, err", [
    (lambda img: np.zeros((3, 3, 2), np.float32), ValueError),  # flow of the wrong size
    (lambda img: "no-such-flow.npy", ValueError),
    (lambda img: np.full(img.shape[:2] + (2,), np.nan, np.float32), ValueError),
])
def test_bad_motion_is_rejected(rng, bad, err):
    img = _image(rng, (12, 12, 3))
    with pytest.raises(err):
        blur_tiled(img, np.zeros_like(img), bad(img), backend="numpy")


def test_mismatched_destination_is_rejected(rng):
    img = _image(rng, (12, 12, 3))
    with pytest.raises(ValueError, match="does not match"):
        blur_tiled(img, np.zeros((12, 12, 3), np.uint16), (1, 0), backend="numpy")
    with pytest.raises(ValueError, match="tile"):
        blur_tiled(img, np.zeros_like(img), (1, 0), backend="numpy", tile=0)


def test_blur_file_bigtiff_streams_and_matches(rng, tmp_path):
    img = _image(rng, (45, 38, 3))
    src = tmp_path / "in.tif"
    tifffile.imwrite(src, img, photometric="rgb")
    flow = _cross_tile_flow(rng, 45, 38)
    write_flow(tmp_path / "f.npy", flow)
    assert isinstance(io.open_image(src), MappedRaster)
    run = blur_file(src, tmp_path / "out.tif", str(tmp_path / "f.npy"), backend="numpy",
                    tile=16)
    assert run.tiles == 9
    np.testing.assert_array_equal(read_image(tmp_path / "out.tif"),
                                  clblur.blur(img, flow, backend="numpy"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.npy", "in.tif", "out.tif"]


def test_blur_file_compressed_tiff_and_png(rng, tmp_path):
    img = _image(rng, (40, 36, 3))
    tifffile.imwrite(tmp_path / "z.tif", img, photometric="rgb", compression="zlib",
                     tile=(16, 16))
    write_image(tmp_path / "p.png", img)
    ref = clblur.blur(img, (2.0, 5.0), backend="numpy")
    blur_file(tmp_path / "z.tif", tmp_path / "z_out.png", (2.0, 5.0), backend="numpy", tile=12)
    blur_file(tmp_path / "p.png", tmp_path / "p_out.tif", (2.0, 5.0), backend="numpy", tile=12)
    np.testing.assert_array_equal(read_image(tmp_path / "z_out.png"), ref)
    np.testing.assert_array_equal(read_image(tmp_path / "p_out.tif"), ref)
    # the response is the fourth argument, as in clblur.blur and blur_tiled
    blur_file(tmp_path / "p.png", tmp_path / "s_out.png", (2.0, 5.0), "srgb", backend="numpy")
    np.testing.assert_array_equal(read_image(tmp_path / "s_out.png"),
                                  clblur.blur(img, (2.0, 5.0), "srgb", backend="numpy"))


def test_blur_file_turns_a_sideways_tiff_window_by_window(rng, tmp_path):
    # a TIFF stored sideways (Orientation 6: rotate 90 clockwise) is blurred upright, as the
    # in-memory blur of read_image sees it, with the flow given in the upright frame
    stored = _image(rng, (38, 45, 3))
    src = tmp_path / "side.tif"
    tifffile.imwrite(src, stored, photometric="rgb", extratags=[(0x0112, "H", 1, 6, True)])
    upright = read_image(src)
    assert upright.shape == (45, 38, 3)
    flow = _cross_tile_flow(rng, 45, 38)
    write_flow(tmp_path / "f.npy", flow)
    run = blur_file(src, tmp_path / "out.tif", str(tmp_path / "f.npy"), backend="numpy",
                    tile=16)
    assert run.tiles == 9
    np.testing.assert_array_equal(read_image(tmp_path / "out.tif"),
                                  clblur.blur(upright, flow, backend="numpy"))


def test_blur_file_failure_leaves_no_output(rng, tmp_path):
    img = _image(rng, (20, 20, 3))
    tifffile.imwrite(tmp_path / "in.tif", img)
    with pytest.raises(ValueError, match="response"):
        blur_file(tmp_path / "in.tif", tmp_path / "out.tif", (1, 1), response="nonsense",
                  backend="numpy")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.tif"]
    with pytest.raises(ValueError, match="refusing to overwrite"):
        blur_file(tmp_path / "in.tif", tmp_path / "in.tif", (1, 1), backend="numpy")


def test_opencl_tiled_equals_untiled(opencl, rng):
    img = _image(rng, (64, 80, 3))
    flow = _cross_tile_flow(rng, 64, 80)
    hdr = (rng.random((64, 80, 3)) * 0.2).astype(np.float32)
    hdr[:12, :12] = 40.0  # scene-linear highlights in one tile only
    for image, response in ((img, "exp"), (hdr, "linear")):
        for motion in ((7.3, -2.5), (5.0, 0.0), flow, rng.random((5, 9))):
            ref = clblur.blur(image, motion, response, backend="opencl")
            out = np.zeros_like(image)
            blur_tiled(image, out, motion, response, backend="opencl", tile=(16, 24))
            np.testing.assert_array_equal(out, ref, err_msg=f"{response} {motion!r:.40}")


@pytest.mark.parametrize("text, expected", [("2G", 2**31), ("500M", 500 * 2**20),
                                            ("1.5GiB", 3 * 2**29), (4096, 4096)])
def test_memory_budget_sizes(text, expected):
    assert tiling.parse_size(text) == expected


@pytest.mark.parametrize("nbytes, text", [(100, "100 B"), (5 * 2**10, "5.0 KiB"),
                                           (300 * 2**10, "300 KiB"), (512 * 2**20, "512 MiB"),
                                           (int(1.5 * 2**30), "1.5 GiB")])
def test_sizes_in_messages_keep_their_figures(nbytes, text):
    # a budget below 1 MiB used to print as "0 MiB"
    assert describe_size(nbytes) == text


@pytest.mark.parametrize("bad", ["lots", "-1G", 0, True])
def test_bad_memory_budget(bad):
    with pytest.raises((ValueError, TypeError), match="memory budget"):
        tiling.parse_size(bad)


def test_unsupported_or_corrupt_tiff_is_rejected(rng, tmp_path):
    tifffile.imwrite(tmp_path / "planar.tif", _image(rng, (3, 20, 30)), photometric="rgb",
                     planarconfig="separate")
    with pytest.raises(ValueError, match="unsupported TIFF layout"):
        blur_file(tmp_path / "planar.tif", tmp_path / "out.tif", (1, 0), backend="numpy")
    (tmp_path / "junk.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(ValueError, match="cannot read image"):
        blur_file(tmp_path / "junk.tif", tmp_path / "out.tif", (1, 0), backend="numpy")
    assert not (tmp_path / "out.tif").exists()


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 24), w=st.integers(1, 24), th=st.integers(1, 10),
       tw=st.integers(1, 10), anchor=st.sampled_from(["start", "center", "end"]),
       dx=st.floats(-15, 15), dy=st.floats(-15, 15), per_pixel=st.booleans(),
       seed=st.integers(0, 2**16))
def test_tiled_equals_untiled_property(h, w, th, tw, anchor, dx, dy, per_pixel, seed):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    motion = (dx, dy)
    if per_pixel:  # random vectors up to (dx, dy) in size: neighbours point anywhere
        motion = (rng.uniform(-1, 1, (h, w, 2)) * [dx, dy]).astype(np.float32)
    out = np.zeros_like(img)
    blur_tiled(img, out, motion, anchor=anchor, backend="numpy", tile=(th, tw))
    np.testing.assert_array_equal(out, clblur.blur(img, motion, anchor=anchor,
                                                   backend="numpy"))


@pytest.mark.parametrize("layout, channels", [
    ({"tile": (16, 16), "compression": "lzw"}, 1),
    ({"tile": (16, 16), "compression": "lzw"}, 3),
    ({"rowsperstrip": 7, "compression": "zlib"}, 1),
    ({"rowsperstrip": 7, "compression": "zlib"}, 3),
    ({"tile": (16, 32), "compression": "jpeg"}, 3),
    ({"rowsperstrip": 5, "compression": "packbits"}, 1),
    ({"rowsperstrip": 5, "compression": "packbits"}, 3),
])
def test_compressed_tiff_windows_equal_the_whole_decode(rng, tmp_path, layout, channels):
    # TiffWindows: only the segments a window touches are decoded, with any codec
    img = _image(rng, (45, 70, 3))[..., :channels].squeeze()
    path = tmp_path / "c.tif"
    tifffile.imwrite(path, img, photometric="rgb" if channels == 3 else "minisblack", **layout)
    raster = io.open_image(path)
    whole = read_image(path)
    assert isinstance(raster, io.TiffWindows) and tuple(raster.shape) == whole.shape
    for key in [(slice(None), slice(None)), (slice(3, 40), slice(17, 50)), (slice(44, 45), 5),
                (slice(10, 10), slice(0, 9)), (-1, slice(None)), (slice(0, 20), slice(66, 99))]:
        np.testing.assert_array_equal(raster[key], whole[key], err_msg=str(key))


def test_a_corrupt_tiff_segment_is_named_when_its_window_is_read(rng, tmp_path):
    img = _image(rng, (48, 48, 3))
    path = tmp_path / "c.tif"
    tifffile.imwrite(path, img, photometric="rgb", tile=(16, 16), compression="lzw")
    with tifffile.TiffFile(path) as tif:
        offset = int(tif.pages[0].dataoffsets[4])  # the middle tile
    data = bytearray(path.read_bytes())
    data[offset:offset + 40] = bytes(range(200, 240))
    path.write_bytes(bytes(data))
    raster = io.open_image(path)
    np.testing.assert_array_equal(raster[:16, :], img[:16, :])  # its neighbours still read
    with pytest.raises(ValueError, match="corrupt TIFF segment 4"):
        raster[20:30, 20:30]
    with pytest.raises(ValueError, match="c.tif"):
        blur_file(path, tmp_path / "o.tif", (3.0, 0.0), backend="numpy", tile=16)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.tif"]
