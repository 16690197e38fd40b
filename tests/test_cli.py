"""The command line: blur, info, demo, and clear one-line errors with exit code 2."""

import subprocess
import sys

import numpy as np
import pytest

import clblur
from clblur.cli import main
from clblur.errors import InputError
from clblur.io import read_image, write_flow, write_image


@pytest.fixture
def scene(tmp_path, rng):
    img = rng.integers(0, 256, (24, 32, 3)).astype(np.uint8)
    path = tmp_path / "in.png"
    write_image(path, img)
    return path, img


def run(*argv):
    return main([str(a) for a in argv])


def test_blur_motion_matches_api(tmp_path, scene):
    import clblur

    src, img = scene
    out = tmp_path / "out.png"
    assert run("blur", src, out, "--motion=-6,2", "--response", "srgb",
               "--backend", "numpy") == 0
    expected = clblur.blur(img, (-6, 2), "srgb", backend="numpy")
    np.testing.assert_array_equal(read_image(out), expected)
    assert not list(tmp_path.glob(".*part*")), "temp files left behind"


@pytest.mark.parametrize("suffix", [".npy", ".flo"])
def test_blur_flow_files(tmp_path, scene, suffix):
    import clblur

    src, img = scene
    flow = np.random.default_rng(3).normal(0, 3, (24, 32, 2)).astype(np.float32)
    fpath = tmp_path / f"flow{suffix}"
    write_flow(fpath, flow)
    out = tmp_path / "out.png"
    assert run("blur", src, out, "--flow", fpath, "--backend", "numpy") == 0
    np.testing.assert_array_equal(read_image(out), clblur.blur(img, flow, backend="numpy"))


def test_blur_psf_and_response_file(tmp_path, scene):
    import clblur

    src, img = scene
    k = np.zeros((5, 5), np.uint8)
    k[2, :] = 255
    write_image(tmp_path / "k.png", k)
    clblur.Gamma(1.8).save(tmp_path / "r.json")
    out = tmp_path / "out.png"
    assert run("blur", src, out, "--psf", tmp_path / "k.png", "--response",
               tmp_path / "r.json", "--backend", "numpy") == 0
    np.testing.assert_array_equal(read_image(out),
                                  clblur.blur(img, (4, 0), "gamma:1.8", backend="numpy"))


@pytest.mark.parametrize("args,message", [
    (["--motion", "3"], "DX,DY"),
    (["--motion", "3,1", "--response", "gamma:-1"], "positive"),
    (["--motion", "3,1", "--response", "nope"], "unknown response"),
    (["--motion", "3,1", "--samples", "0"], "samples"),
    (["--flow", "missing.npy"], "not found"),
])
def test_bad_input_exit_2(tmp_path, scene, capsys, args, message):
    src, _ = scene
    assert run("blur", src, tmp_path / "o.png", *args, "--backend", "numpy") == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_bad_files_exit_2(tmp_path, scene, capsys):
    src, _ = scene
    notimg = tmp_path / "not.png"
    notimg.write_text("hello")
    assert run("blur", notimg, tmp_path / "o.png", "--motion", "1,0") == 2
    assert "cannot read image" in capsys.readouterr().err
    flow = tmp_path / "f.npy"
    np.save(flow, np.zeros((5, 5, 2), np.float32))
    assert run("blur", src, tmp_path / "o.png", "--flow", flow, "--backend", "numpy") == 2
    assert "expected (24, 32, 2)" in capsys.readouterr().err
    nan = tmp_path / "nan.npy"
    f = np.zeros((24, 32, 2), np.float32)
    f[3, 4] = np.nan
    np.save(nan, f)
    assert run("blur", src, tmp_path / "o.png", "--flow", nan, "--backend", "numpy") == 2
    assert "NaN" in capsys.readouterr().err
    trunc = tmp_path / "t.flo"
    write_flow(trunc, np.zeros((24, 32, 2), np.float32))
    trunc.write_bytes(trunc.read_bytes()[:100])
    assert run("blur", src, tmp_path / "o.png", "--flow", trunc) == 2
    assert "truncated" in capsys.readouterr().err


def test_refuses_to_overwrite_input(scene, capsys):
    src, img = scene
    before = src.read_bytes()
    assert run("blur", src, src, "--motion", "4,0") == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert src.read_bytes() == before


def test_demo_renders_figures(tmp_path):
    assert run("demo", "--out", tmp_path, "--backend", "numpy") == 0
    for name in ("figure3_step_edge.png", "figure4_ball.png", "side_by_side.png",
                 "ball_exp.png"):
        img = read_image(tmp_path / name)
        assert img.shape[0] > 100 and img.std() > 5


def test_info_runs_as_a_script():
    r = subprocess.run([sys.executable, "-m", "clblur.cli", "info"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "clblur" in r.stdout and "pyopencl" in r.stdout


def test_huge_motion_on_a_small_image_matches_the_api(tmp_path, scene):
    """Issue 10, item 3: the halo is capped at the image size in the tiled path."""
    import clblur

    src, img = scene
    out = tmp_path / "o.png"
    assert run("blur", src, out, "--motion=1e9,0", "--samples", "4", "--backend", "numpy",
               "--memory-budget", "1M") == 0
    np.testing.assert_array_equal(read_image(out),
                                  clblur.blur(img, (1e9, 0), samples=4, backend="numpy"))


def test_a_named_device_that_does_not_exist_is_an_error(tmp_path, scene, capsys):
    src, _ = scene
    assert run("blur", src, tmp_path / "o.png", "--motion=2,0", "--device", "9:9") == 2
    err = capsys.readouterr().err
    assert "9:9" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.png").exists()


def test_nan_columns_say_why():
    from clblur.calibration.compare import nan_reasons

    lines = nan_reasons({"n_pairs": {1: 0, 4: 3, 2: 2}, "n_values": {1: 0, 4: 0, 2: 100}})
    assert len(lines) == 2
    assert "1-stop" in lines[0] and "no two exposures" in lines[0]
    assert "4-stop" in lines[1] and "--eval-low" in lines[1]


def test_library_never_imports_the_command_line():
    """Issue 12: ``clblur.cli`` is the front; no library module imports it."""
    import ast
    from pathlib import Path

    root = Path(__file__).parents[1] / "clblur"
    offenders = []
    for path in root.rglob("*.py"):
        if "cli" in path.relative_to(root).parts[:1]:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n == "clblur.cli" or n.startswith("clblur.cli.") for n in names):
                offenders.append(str(path.relative_to(root)))
    assert offenders == []


def test_depth_exr_channel_is_never_overwritten(tmp_path, scene, capsys):
    """``--depth FILE.exr:CHANNEL`` names FILE.exr as an input: OUT = FILE.exr is refused."""
    exr = pytest.importorskip("clblur.io.exr")
    pytest.importorskip("OpenEXR")
    src, img = scene
    depth = tmp_path / "d.exr"
    exr.write_channels(depth, {"Z": np.ones(img.shape[:2], np.float32)})
    before = depth.read_bytes()
    assert run("blur", src, depth, "--motion=3,0", "--depth", f"{depth}:Z",
               "--backend", "numpy") == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert depth.read_bytes() == before


def test_images_written_in_what_their_format_holds(tmp_path, capsys):
    """OpenCV saturates 16-bit codes into an 8-bit format (a 16-bit photo blurred to .jpg came
    out white), writes no grey + alpha layout and drops alpha from JPEG without a word: 16-bit
    codes are scaled to the nearest 8-bit ones, grey + alpha goes out as RGBA, and alpha to
    JPEG is refused (exit 2 from the command line)."""
    from clblur.errors import InputError

    ramp = np.linspace(0, 65535, 12 * 16 * 3).reshape(12, 16, 3).astype(np.uint16)
    for suffix in (".bmp", ".webp", ".jpg"):  # BMP and lossless-enough: the codes, scaled
        write_image(tmp_path / f"r{suffix}", ramp)
        back = read_image(tmp_path / f"r{suffix}").astype(np.int64)
        tol = 0 if suffix == ".bmp" else 12  # JPEG and lossy WebP: their own compression
        assert np.abs(back - np.rint(ramp / 257.0)).max() <= tol, suffix
    grey_alpha = np.stack([np.arange(12 * 16).reshape(12, 16) % 256,
                           np.full((12, 16), 200)], axis=-1).astype(np.uint8)
    write_image(tmp_path / "ga.png", grey_alpha)
    back = read_image(tmp_path / "ga.png")
    assert back.shape == (12, 16, 4)
    assert np.array_equal(back[..., :3], grey_alpha[..., [0, 0, 0]])
    assert np.array_equal(back[..., 3], grey_alpha[..., 1])
    with pytest.raises(InputError, match="JPEG cannot hold alpha"):
        write_image(tmp_path / "ga.jpg", grey_alpha)
    write_image(tmp_path / "p16.png", ramp)
    assert main(["blur", str(tmp_path / "p16.png"), str(tmp_path / "o.jpg"),
                 "--motion=3,0", "--backend", "numpy"]) == 0
    out = read_image(tmp_path / "o.jpg")
    assert out.dtype == np.uint8 and (out == 255).mean() < 0.05  # a ramp, not white
    assert 100 < out.mean() < 155
    write_image(tmp_path / "rgba.png", np.dstack([ramp[..., :3] // 257,
                                                  np.full((12, 16), 255)]).astype(np.uint8))
    capsys.readouterr()
    assert main(["blur", str(tmp_path / "rgba.png"), str(tmp_path / "a.jpg"),
                 "--motion=3,0", "--backend", "numpy"]) == 2
    assert "JPEG cannot hold alpha" in capsys.readouterr().err
    assert not (tmp_path / "a.jpg").exists()


def test_a_per_channel_response_is_checked_against_the_image(tmp_path, capsys):
    """clblur blur checks a per-channel document against the image's colour channels (it
    named 1 channel for an RGB image, the first count it had tried)."""
    import json

    from clblur.responses import Gamma

    write_image(tmp_path / "rgb.png", np.zeros((8, 10, 3), np.uint8))
    doc = tmp_path / "two.json"
    doc.write_text(json.dumps({"kind": "per-channel", "channels": [Gamma(2.0).to_dict()] * 2}))
    assert main(["blur", str(tmp_path / "rgb.png"), str(tmp_path / "o.png"), "--motion=2,0",
                 "--response", str(doc)]) == 2
    assert "got 2 per-channel responses for an image with 3 channel(s)" in capsys.readouterr().err
    # clblur video checks before it reads a frame: the counts an image can have, not one
    (tmp_path / "frames").mkdir()
    assert main(["video", str(tmp_path / "frames"), str(tmp_path / "out"),
                 "--response", str(doc)]) == 2
    err = capsys.readouterr().err
    assert "got 2 per-channel responses; a per-channel document needs one per colour " \
           "channel of the images (1, 3 or 4)" in err and "1 channel" not in err


def test_a_calibrated_colour_set_blurs_an_rgba_image(tmp_path, capsys, rng):
    """Coverage takes no response, so the three curves of a calibrated RGB camera serve an
    RGBA image; it was refused unless a fourth (ignored) curve was added, while clblur
    blur's own check of the document had passed it."""
    import json

    from clblur.responses import SRGB, Exp, Gamma

    img = rng.integers(0, 256, (12, 16, 4), dtype=np.uint8)
    write_image(tmp_path / "rgba.png", img)
    curves = [SRGB(), Gamma(2.2), Exp()]
    doc = tmp_path / "rgb.json"
    doc.write_text(json.dumps({"kind": "per-channel", "channels": [c.to_dict() for c in curves]}))
    assert main(["blur", str(tmp_path / "rgba.png"), str(tmp_path / "o.png"), "--motion=3,1",
                 "--response", str(doc), "--backend", "numpy"]) == 0
    out = read_image(tmp_path / "o.png")
    for c, curve in enumerate(curves):  # each colour channel through its own curve
        one = clblur.blur(img, (3, 1), curve, alpha=True, backend="numpy")
        np.testing.assert_array_equal(out[..., c], one[..., c])
        np.testing.assert_array_equal(out[..., 3], one[..., 3])
    with pytest.raises(InputError, match="3 colour channel"):
        clblur.blur(img, (3, 1), [*curves, Exp()], alpha=True)


@pytest.mark.parametrize("extra, message", [
    (["--motion=3,0", "--vectors", "blender"], "no --flow was given"),
    (["--motion=3,0", "--vector-shutter", "-1"], "--vector-shutter applies"),
    (["--flow", "{flow}", "--vectors", "nuke", "--vector-shutter", "-1"], "positive number"),
    (["--motion=3,0", "--alpha", "yes"], "--alpha yes"),
])
def test_an_option_that_would_be_ignored_is_an_error(tmp_path, scene, capsys, extra, message):
    # --vectors without a --flow, a shutter without a renderer's convention and --alpha yes
    # on an RGB image (its blue read as coverage) were taken silently
    src, _ = scene
    write_flow(tmp_path / "f.npy", np.zeros((24, 32, 2), np.float32))
    argv = [a.replace("{flow}", str(tmp_path / "f.npy")) for a in extra]
    assert run("blur", src, tmp_path / "o.png", *argv, "--backend", "numpy") == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o.png").exists()


@pytest.mark.parametrize("fault", ["nan", "shape"])
def test_a_bad_flow_file_is_named(tmp_path, scene, capsys, fault):
    src, _ = scene
    flow = np.zeros((20, 32, 2) if fault == "shape" else (24, 32, 2), np.float32)
    flow[3, 3, 0] = np.nan if fault == "nan" else 0.0
    write_flow(tmp_path / "f.npy", flow)
    assert run("blur", src, tmp_path / "o.png", "--flow", tmp_path / "f.npy") == 2
    err = capsys.readouterr().err
    assert f"flow {tmp_path / 'f.npy'}:" in err and len(err.strip().splitlines()) == 1, err


def test_a_library_warning_is_one_line(tmp_path, scene, capsys, monkeypatch):
    # CLBLUR_DEVICE naming no device falls back to numpy with a warning: one line, named
    # as the command's, not Python's two (file:line, then the source line)
    import importlib

    blur_module = importlib.import_module("clblur.blur")  # clblur.blur is the function
    monkeypatch.setenv("CLBLUR_DEVICE", "9:9")
    monkeypatch.delenv("CLBLUR_QUIET", raising=False)
    monkeypatch.setattr(blur_module, "_warned_fallback", False)  # once per process
    src, _ = scene
    assert run("blur", src, tmp_path / "o.png", "--motion=2,0") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("clblur blur: warning: no usable OpenCL"), err


def test_a_kernel_image_s_alpha_is_its_weight_and_a_floor_is_named(tmp_path, rng):
    # white on transparent (an editor's drawing) was read as a 27 x 27 box; a background
    # floor under the kernel blurs as light and was taken without a word
    import warnings

    from clblur.io import read_psf

    line = np.zeros((27, 27), np.uint8)
    line[13, 5:22] = 250
    write_image(tmp_path / "line.png", line)
    drawn = np.zeros((27, 27, 4), np.uint8)
    drawn[..., :3] = 255
    drawn[..., 3] = line
    write_image(tmp_path / "drawn.png", drawn)
    want = read_psf(tmp_path / "line.png")
    np.testing.assert_allclose(read_psf(tmp_path / "drawn.png"), want)
    write_image(tmp_path / "floor.png", line + 3)
    with pytest.warns(UserWarning, match="no pixel is black"):
        read_psf(tmp_path / "floor.png")
    box = np.full((1, 7), 255, np.uint8)  # all light, all peak: a box, no floor
    write_image(tmp_path / "box.png", box)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_psf(tmp_path / "box.png")
