"""``read_image`` applies the EXIF Orientation tag (0x0112) as Pillow's ``exif_transpose`` does.

Cameras store portrait shots sideways and set the tag; OpenCV's ``IMREAD_UNCHANGED`` and
tifffile ignore it, so without this a bracket mixes turned and upright frames.  Pillow is the
reference: each file is written with Pillow (or tifffile) and read back both ways.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from PIL import Image, ImageOps

from clblur.io import probe_image, read_image

H, W = 5, 7  # not square, so a wrong turn changes the shape


def _exif(orientation: int) -> Image.Exif:
    exif = Image.Exif()
    exif[0x0112] = orientation
    return exif


def _reference(path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(ImageOps.exif_transpose(im))


def _rgb(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_png_rgb_each_orientation(tmp_path, orientation):
    path = tmp_path / f"o{orientation}.png"
    Image.fromarray(_rgb(orientation)).save(path, exif=_exif(orientation))
    got = read_image(path)
    want = _reference(path)
    assert got.shape == want.shape
    assert got.dtype == np.uint8
    assert got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)
    if orientation >= 5:
        assert got.shape[:2] == (W, H)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_png_grey_each_orientation(tmp_path, orientation):
    path = tmp_path / f"g{orientation}.png"
    grey = np.random.default_rng(10 + orientation).integers(0, 256, (H, W), dtype=np.uint8)
    Image.fromarray(grey, mode="L").save(path, exif=_exif(orientation))
    got = read_image(path)
    assert got.ndim == 2
    np.testing.assert_array_equal(got, _reference(path))


@pytest.mark.parametrize("orientation", range(1, 9))
def test_png_16bit_each_orientation(tmp_path, orientation):
    path = tmp_path / f"w{orientation}.png"
    deep = np.random.default_rng(20 + orientation).integers(0, 65536, (H, W), dtype=np.uint16)
    im = Image.fromarray(deep)
    if im.mode != "I;16":
        pytest.skip(f"this Pillow makes mode {im.mode} from uint16, not I;16")
    try:
        im.save(path, exif=_exif(orientation))
    except (OSError, ValueError) as e:
        pytest.skip(f"this Pillow cannot write a 16-bit PNG with EXIF: {e}")
    with Image.open(path) as check:
        if check.getexif().get(0x0112) != orientation:
            pytest.skip("this Pillow drops EXIF from 16-bit PNGs")
    got = read_image(path)
    assert got.dtype == np.uint16
    want = _reference(path).astype(np.uint16)  # Pillow's I;16 array: uint16 (native order)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_webp_lossless(tmp_path, orientation):
    path = tmp_path / f"o{orientation}.webp"
    Image.fromarray(_rgb(30 + orientation)).save(path, exif=_exif(orientation), lossless=True)
    np.testing.assert_array_equal(read_image(path), _reference(path))


@pytest.mark.parametrize("orientation", [2, 6, 7])
def test_tiff_orientation_tag(tmp_path, orientation):
    tifffile = pytest.importorskip("tifffile")
    path = tmp_path / f"o{orientation}.tif"
    tifffile.imwrite(path, _rgb(40 + orientation), photometric="rgb",
                     extratags=[(0x0112, "H", 1, orientation, True)])
    np.testing.assert_array_equal(read_image(path), _reference(path))


def test_jpeg_rotated_90_clockwise(tmp_path):
    path = tmp_path / "o6.jpg"
    Image.fromarray(_rgb(50)).save(path, exif=_exif(6), quality=95)
    stored = probe_image(path)
    assert (stored.height, stored.width) == (H, W)  # the header: the stored, sideways size
    got = read_image(path)
    assert got.shape == (W, H, 3)
    want = _reference(path)
    assert want.shape == got.shape
    # JPEG decoders (OpenCV's libjpeg-turbo, Pillow's) may differ by a code
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1


def test_png_exif_after_image_data(tmp_path):
    """An eXIf chunk after IDAT (allowed by the first eXIf specification) still counts."""
    path = tmp_path / "late.png"
    Image.fromarray(_rgb(60)).save(path, exif=_exif(8))
    data = path.read_bytes()
    chunks, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        chunks.append(data[pos:pos + 12 + length])
        pos += 12 + length
    exif = [c for c in chunks if c[4:8] == b"eXIf"]
    rest = [c for c in chunks if c[4:8] != b"eXIf"]
    assert len(exif) == 1 and rest[-1][4:8] == b"IEND"
    path.write_bytes(data[:8] + b"".join(rest[:-1]) + exif[0] + rest[-1])
    got = read_image(path)
    assert got.shape == (W, H, 3)
    np.testing.assert_array_equal(got, np.rot90(_rgb(60), 1))


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


@pytest.mark.parametrize("value", [0, 9, 300])
def test_out_of_range_orientation_is_ignored(tmp_path, value):
    path = tmp_path / f"v{value}.png"
    Image.fromarray(_rgb(70)).save(path, exif=_exif(value))
    np.testing.assert_array_equal(read_image(path), _rgb(70))


def test_corrupt_exif_reads_quietly(tmp_path, recwarn, capfd):
    path = tmp_path / "corrupt.jpg"
    Image.fromarray(_rgb(80)).save(path, exif=_exif(6), quality=95)
    data = bytearray(path.read_bytes())
    tiff = data.find(b"Exif\0\0") + 6  # the TIFF header: byte order, 42, IFD0's offset
    order = ">" if data[tiff:tiff + 2] == b"MM" else "<"
    data[tiff + 4:tiff + 8] = struct.pack(order + "I", 0x7FFFFF00)
    path.write_bytes(bytes(data))
    # the corruption is real: Pillow itself warns (on open or on getexif) and finds no tag
    with pytest.warns(UserWarning, match="Corrupt EXIF"), Image.open(path) as im:
        assert im.getexif().get(0x0112) is None
    recwarn.clear()
    capfd.readouterr()
    got = read_image(path)
    assert got.shape == (H, W, 3)  # no orientation: as stored
    assert not [str(w.message) for w in recwarn]
    out, err = capfd.readouterr()
    assert err == "" and out == ""


def test_truncated_exif_chunk_reads_quietly(tmp_path, recwarn, capfd):
    """A PNG eXIf chunk holding a torn TIFF header: no orientation, nothing printed."""
    ihdr = struct.pack(">IIBBBBB", W, H, 8, 2, 0, 0, 0)
    raw = b"".join(b"\0" + row.tobytes() for row in _rgb(90))
    path = tmp_path / "torn.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr)
                     + _png_chunk(b"eXIf", b"MM\0*\0\0")
                     + _png_chunk(b"IDAT", zlib.compress(raw)) + _png_chunk(b"IEND", b""))
    capfd.readouterr()
    np.testing.assert_array_equal(read_image(path), _rgb(90))
    assert not [str(w.message) for w in recwarn]
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("layout", ["contiguous", "tiled"])
@pytest.mark.parametrize("orientation", range(1, 9))
def test_tiff_windows_read_upright(tmp_path, orientation, layout):
    # open_image (the window-by-window path of large images) turns a TIFF as read_image does,
    # window by window: mapped (uncompressed) and through zarr (tiled, compressed)
    tifffile = pytest.importorskip("tifffile")
    if layout == "tiled":
        pytest.importorskip("zarr")
    from clblur.io import open_image

    stored = np.random.default_rng(orientation).integers(0, 65536, (40, 56, 3), np.uint16)
    path = tmp_path / f"o{orientation}.tif"
    extra = {"tile": (16, 16), "compression": "zlib"} if layout == "tiled" else {}
    tifffile.imwrite(path, stored, photometric="rgb", **extra,
                     extratags=[(0x0112, "H", 1, orientation, True)])
    whole = read_image(path)
    raster = open_image(path)
    assert tuple(raster.shape) == whole.shape and np.dtype(raster.dtype) == whole.dtype
    windows = [(slice(None), slice(None)), (slice(3, 17), slice(5, 30)),
               (slice(0, 1), slice(-9, None)), (slice(20, 20), slice(2, 9)),
               (7, slice(4, 11)), (slice(1, 6), -2), (slice(2, 13), slice(3, 8), 1),
               (slice(2, 13), slice(3, 8), slice(0, 2))]
    for key in windows:
        np.testing.assert_array_equal(raster[key], whole[key], err_msg=str(key))
