"""Netpbm (PGM / PPM) files: the header, both sample encodings, maxval, and bad files."""

from __future__ import annotations

import numpy as np
import pytest

from clblur.errors import InputError
from clblur.io import probe_image, read_image, write_image


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape,suffix", [((5, 7), ".pgm"), ((5, 7, 3), ".ppm"),
                                          ((5, 7, 3), ".pnm")])
def test_round_trip_keeps_codes_and_dtype(tmp_path, dtype, shape, suffix):
    rng = np.random.default_rng(3)
    im = rng.integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype)
    write_image(tmp_path / f"x{suffix}", im)
    header = probe_image(tmp_path / f"x{suffix}")
    assert (header.height, header.width, header.channels) == (5, 7, 1 if len(shape) == 2 else 3)
    assert header.itemsize == np.dtype(dtype).itemsize
    out = read_image(tmp_path / f"x{suffix}")
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, im)


def test_opencv_reads_what_we_write_and_we_read_what_it_writes(tmp_path):
    cv2 = pytest.importorskip("cv2")
    im = (np.arange(4 * 6 * 3) * 999 % 65536).astype(np.uint16).reshape(4, 6, 3)
    write_image(tmp_path / "ours.ppm", im)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "ours.ppm"), -1)[..., ::-1], im)
    cv2.imwrite(str(tmp_path / "theirs.ppm"), im[..., ::-1])
    np.testing.assert_array_equal(read_image(tmp_path / "theirs.ppm"), im)


def test_plain_samples_comments_and_a_12_bit_maxval(tmp_path):
    (tmp_path / "plain.ppm").write_bytes(b"P3\n# a comment\n2 1 # width height\n255\n"
                                         b"1 2 3\n4 5 6\n")
    np.testing.assert_array_equal(read_image(tmp_path / "plain.ppm"),
                                  [[[1, 2, 3], [4, 5, 6]]])
    # 12-bit codes (maxval 4095) are value / maxval of full scale: 4095 is white in uint16
    body = np.array([[0, 1, 2048, 4095]], ">u2").tobytes()
    (tmp_path / "twelve.pgm").write_bytes(b"P5 4 1 4095\n" + body)
    out = read_image(tmp_path / "twelve.pgm")
    assert out.dtype == np.uint16
    assert out.tolist() == [[0, 16, round(2048 * 65535 / 4095), 65535]]


@pytest.mark.parametrize("data,match", [
    (b"P6\n4 4\n255\n" + bytes(20), "truncated Netpbm file"),
    (b"P3\n2 1\n255\n1 2 3 4\n", "truncated Netpbm file"),
    (b"P5\n2 1\n15\n\x10\x01", "exceeds maxval 15"),
    (b"P4\n8 1\n\x00", "bilevel PBM files are not supported"),
    (b"P6\n4", "corrupt or truncated Netpbm header"),
    (b"GIF89a", "not a Netpbm file"),
    (b"P5\n0 4\n255\n", "empty size"),
])
def test_bad_files_are_named_in_one_line(tmp_path, data, match):
    (tmp_path / "bad.pgm").write_bytes(data)
    with pytest.raises(InputError, match=match) as e:
        read_image(tmp_path / "bad.pgm")
    assert "\n" not in str(e.value)


def test_what_netpbm_cannot_hold_is_refused(tmp_path):
    with pytest.raises(InputError, match="no alpha"):
        write_image(tmp_path / "a.ppm", np.zeros((2, 2, 4), np.uint8))
    with pytest.raises(InputError, match="not float32"):
        write_image(tmp_path / "f.ppm", np.zeros((2, 2, 3), np.float32))
    with pytest.raises(InputError, match=r"\.pgm holds grey"):
        write_image(tmp_path / "c.pgm", np.zeros((2, 2, 3), np.uint8))
    assert not list(tmp_path.iterdir())


def test_the_command_line_blurs_a_ppm_into_a_ppm(tmp_path):
    from clblur.cli import main

    im = np.zeros((16, 24, 3), np.uint8)
    im[6:10, 8:12] = 255
    write_image(tmp_path / "in.ppm", im)
    assert main(["blur", str(tmp_path / "in.ppm"), str(tmp_path / "out.ppm"), "--motion=6,0",
                 "--backend", "numpy"]) == 0
    import clblur

    np.testing.assert_array_equal(read_image(tmp_path / "out.ppm"),
                                  clblur.blur(im, (6, 0), backend="numpy"))
