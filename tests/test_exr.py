"""OpenEXR input/output (clblur.io.exr) and renderer vector passes through the command line."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("OpenEXR", reason="OpenEXR bindings not installed (pip install clblur[exr])")

import clblur  # noqa: E402
from clblur import scenes, vectors  # noqa: E402
from clblur.cli import main  # noqa: E402
from clblur.io import (  # noqa: E402
    exr,  # noqa: E402
    read_flow,
    read_image,
    write_flow,
    write_image,
)


@pytest.fixture(scope="module")
def rendered():
    sc = scenes.example_scenes(96, 64)["crossing_fast_behind"]
    return sc, scenes.render(sc, "linear", np.float32, samples=64)


def test_round_trip_rgba_depth_vectors_ids(tmp_path, rendered):
    """Premultiplied RGBA, depth, clblur flow, a Blender vector pass and object IDs survive a
    write and a read bit for bit (float32) or to float16 precision (half colour)."""
    sc, r = rendered
    rgba = np.concatenate([r.sharp * r.alpha[..., None], r.alpha[..., None]], axis=-1)
    prev, nxt = scenes.frame_displacements(sc, 0.5)
    vp = vectors.to_blender(prev, nxt)
    extra = {"Z": r.depth, "flow.x": r.flow[..., 0], "flow.y": r.flow[..., 1],
             "ViewLayer.Vector.X": vp[..., 0], "ViewLayer.Vector.Y": vp[..., 1],
             "ViewLayer.Vector.Z": vp[..., 2], "ViewLayer.Vector.W": vp[..., 3],
             "id": r.ids}
    for half in (False, True):
        path = tmp_path / f"frame_{half}.exr"
        exr.write_image(path, rgba, half=half, extra=extra)
        back = exr.read_image(path)
        assert back.shape == rgba.shape and back.dtype == np.float32
        if half:
            np.testing.assert_allclose(back, rgba, rtol=1e-3, atol=1e-4)
        else:
            np.testing.assert_array_equal(back, rgba.astype(np.float32))
        np.testing.assert_array_equal(exr.read_depth(path), r.depth)
        np.testing.assert_array_equal(exr.read_flow(path), r.flow)
        np.testing.assert_array_equal(vectors.read_vectors(path, "blender")["pass"], vp)
        chans = exr.read_channels(path)
        np.testing.assert_array_equal(chans["id"], r.ids)
        assert chans["Z"].dtype == np.float32  # depth keeps float32 even with half colour
    assert not list(tmp_path.glob(".*part*")), "temp files left behind"


def test_io_dispatch_by_extension(tmp_path, rendered):
    _, r = rendered
    write_image(tmp_path / "a.exr", r.sharp)
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), r.sharp)
    write_flow(tmp_path / "f.exr", r.flow)
    np.testing.assert_array_equal(read_flow(tmp_path / "f.exr"), r.flow)
    grey = r.sharp[..., 0]
    write_image(tmp_path / "g.exr", grey)
    np.testing.assert_array_equal(read_image(tmp_path / "g.exr"), grey)


def test_layers_and_errors(tmp_path):
    a = np.ones((4, 5), np.float32)
    p = tmp_path / "ml.exr"
    exr.write_channels(p, {"RenderLayer.Combined.R": a, "RenderLayer.Combined.G": 2 * a,
                           "RenderLayer.Combined.B": 3 * a, "RenderLayer.Depth.Z": 4 * a})
    img = exr.read_image(p)
    assert img.shape == (4, 5, 3) and img[0, 0, 2] == 3
    assert exr.read_depth(p)[0, 0] == 4
    with pytest.raises(ValueError, match="no flow"):
        exr.read_flow(p)
    with pytest.raises(ValueError, match="no Blender vector pass"):
        vectors.read_vectors(p, "blender")
    with pytest.raises(ValueError, match="shape"):
        exr.write_channels(tmp_path / "bad.exr", {"R": a, "G": np.ones((3, 3))})
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="cannot read EXR"):
        exr.read_channels(tmp_path / "junk.exr")


def test_a_blender_file_with_vector_and_normal_passes_reads_its_combined_layer(tmp_path):
    # ViewLayer.Vector.Y (and Normal.Y) were taken for luminance layers: "several colour
    # layers", so a standard Blender multilayer file could not be read or blurred
    rng = np.random.default_rng(0)
    rgba = rng.uniform(0, 1, (6, 7, 4)).astype(np.float32)
    vp = rng.normal(0, 2, (6, 7, 4)).astype(np.float32)
    chans = {f"ViewLayer.Combined.{c}": rgba[..., i] for i, c in enumerate("RGBA")}
    chans |= {f"ViewLayer.Vector.{c}": vp[..., i] for i, c in enumerate("XYZW")}
    chans |= {f"ViewLayer.Normal.{c}": vp[..., i] for i, c in enumerate("XYZ")}
    chans["ViewLayer.Depth.Z"] = np.ones((6, 7), np.float32)
    exr.write_channels(tmp_path / "bl.exr", chans)
    np.testing.assert_array_equal(exr.read_image(tmp_path / "bl.exr"), rgba)
    assert main(["blur", str(tmp_path / "bl.exr"), str(tmp_path / "o.exr"), "--flow",
                 str(tmp_path / "bl.exr"), "--vectors", "blender", "--response", "linear",
                 "--backend", "numpy"]) == 0
    assert read_image(tmp_path / "o.exr").shape == (6, 7, 4)


def test_grey_and_alpha_round_trip_and_blur(tmp_path):
    # read_image returned H x W x 2 for a Y, A file that write_image then refused, so a
    # blur of one ran and failed at the write
    ya = np.random.default_rng(1).uniform(0, 1, (6, 7, 2)).astype(np.float32)
    ya[..., 0] *= ya[..., 1]  # premultiplied
    exr.write_image(tmp_path / "ya.exr", ya)
    np.testing.assert_array_equal(exr.read_image(tmp_path / "ya.exr"), ya)
    assert main(["blur", str(tmp_path / "ya.exr"), str(tmp_path / "o.exr"), "--motion=3,0",
                 "--response", "linear", "--backend", "numpy"]) == 0
    np.testing.assert_allclose(read_image(tmp_path / "o.exr"),
                               clblur.blur(ya, (3, 0), "linear", alpha=True, backend="numpy"))


def test_cli_blender_vector_pass_gives_the_clblur_flow_blur(tmp_path, rendered, capsys):
    """`clblur blur IN.exr OUT.exr --flow vectors.exr --vectors blender` equals blurring with
    the renderer's own clblur flow; a file without a vector pass is a one-line error, exit 2."""
    sc, r = rendered
    shutter = 0.5
    prev, nxt = scenes.frame_displacements(sc, shutter)
    src = tmp_path / "beauty.exr"
    exr.write_image(src, r.sharp)
    vec = tmp_path / "vectors.exr"
    vp = vectors.to_blender(prev, nxt)
    exr.write_channels(vec, {f"ViewLayer.Vector.{c}": vp[..., i] for i, c in enumerate("XYZW")})
    out = tmp_path / "out.exr"
    assert main(["blur", str(src), str(out), "--flow", str(vec), "--vectors", "blender",
                 "--vector-shutter", str(shutter), "--response", "linear",
                 "--backend", "numpy"]) == 0
    # the renderer's exposure is s * per-frame displacement: frame_displacements used 1 / s
    expected = clblur.blur(r.sharp, r.flow, "linear", backend="numpy")
    np.testing.assert_allclose(read_image(out), expected, atol=1e-5)
    nuke = tmp_path / "nuke.exr"
    fwd, bwd = vectors.to_nuke(prev, nxt)
    exr.write_channels(nuke, {"forward.u": fwd[..., 0], "forward.v": fwd[..., 1],
                              "backward.u": bwd[..., 0], "backward.v": bwd[..., 1]})
    out2 = tmp_path / "out_nuke.exr"
    assert main(["blur", str(src), str(out2), "--flow", str(nuke), "--vectors", "nuke",
                 "--response", "linear", "--backend", "numpy"]) == 0
    np.testing.assert_allclose(read_image(out2), expected, atol=1e-5)
    capsys.readouterr()  # drop the progress bars of the runs above
    assert main(["blur", str(src), str(tmp_path / "x.exr"), "--flow", str(src), "--vectors",
                 "blender", "--response", "linear", "--backend", "numpy"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no Blender vector pass" in err[0]
    assert not (tmp_path / "x.exr").exists()


@pytest.mark.skipif("depth" not in __import__("inspect").signature(clblur.blur).parameters,
                    reason="clblur.blur does not take depth= yet")
def test_cli_depth_from_an_exr_channel(tmp_path, rendered):
    """`--depth FILE.exr` reads the Z channel, `FILE.exr:CHANNEL` a named one; with a Blender
    vector pass the result is clblur.blur with the renderer's flow and depth."""
    sc, r = rendered
    prev, nxt = scenes.frame_displacements(sc, 0.5)
    vp = vectors.to_blender(prev, nxt)
    src = tmp_path / "frame.exr"
    exr.write_image(src, r.sharp, extra={"Z": r.depth, "ids": r.ids, **{
        f"ViewLayer.Vector.{c}": vp[..., i] for i, c in enumerate("XYZW")}})
    expected = clblur.blur(r.sharp, r.flow, "linear", backend="numpy", depth=r.depth)
    for depth_arg in (str(src), f"{src}:Z"):
        out = tmp_path / "out.exr"
        assert main(["blur", str(src), str(out), "--flow", str(src), "--vectors", "blender",
                     "--depth", depth_arg, "--response", "linear", "--backend", "numpy"]) == 0
        np.testing.assert_allclose(read_image(out), expected, atol=1e-5)
        out.unlink()
    assert main(["blur", str(src), str(tmp_path / "o.exr"), "--flow", str(src), "--vectors",
                 "blender", "--depth", f"{src}:nope", "--response", "linear"]) == 2


# ------------------------------------------------- what a compositor's EXR files carry

def _windowed(tmp_path, name, channels, data, display, **attrs):
    """Write ``channels`` with the data window ``data`` in the display window ``display``
    (and header ``attrs``: pixel aspect ratio, line order, compression)."""
    h, w = next(iter(channels.values())).shape
    x0, y0 = data
    layout = exr.Layout((x0, y0, x0 + w - 1, y0 + h - 1), display, **attrs)
    path = tmp_path / name
    exr.write_channels(path, channels, layout=layout)
    return path


def test_an_exr_output_keeps_its_inputs_windows_and_header(tmp_path, rng):
    """A bounding-box data window, an overscan window, a pixel aspect ratio, a line order,
    a compression and float16 colour come back as they went in, on the tiled path and on the
    whole-image one (alpha, depth); the pixels are the data window's, blurred in place."""
    import OpenEXR

    rgb = rng.uniform(0, 1, (40, 56, 3)).astype(np.float32)
    planes = {c: rgb[..., i] for i, c in enumerate("RGB")}
    display = (0, 0, 63, 47)
    cases = {"bbox": ((5, 3), {}), "overscan": ((-8, -6), {}),
             "aspect": ((0, 0), {"pixel_aspect": 2.0, "compression": OpenEXR.PIZ_COMPRESSION,
                                 "line_order": OpenEXR.DECREASING_Y})}
    for name, (corner, attrs) in cases.items():
        src = _windowed(tmp_path, f"{name}.exr", planes, corner, display, **attrs)
        want = exr.layout(src)
        # a depth takes the whole-image path; it needs a per-pixel flow (here uniform)
        np.save(tmp_path / "flow.npy", np.broadcast_to(np.float32([4, 1]), (40, 56, 2)))
        for extra in (["--motion=4,1"], ["--flow", str(tmp_path / "flow.npy"),
                                         "--depth", "speed"]):
            out = tmp_path / f"{name}_out{len(extra)}.exr"
            assert main(["blur", str(src), str(out), "--backend", "numpy", *extra]) == 0
            got = exr.layout(out)
            assert got == want, (name, extra)
            np.testing.assert_allclose(exr.read_image(out),
                                       clblur.blur(rgb, (4, 1), "linear", backend="numpy"),
                                       atol=1e-6)
    half = tmp_path / "half.exr"
    exr.write_channels(half, planes, half=True)
    assert exr.layout(half).half
    assert main(["blur", str(half), str(tmp_path / "half_out.exr"), "--motion=3,0"]) == 0
    assert exr.layout(tmp_path / "half_out.exr").half  # float16 in, float16 out


def test_exr_depth_and_vectors_are_matched_by_window_not_index(tmp_path, rng, capsys):
    """A flow or depth file whose data window covers the image's is cropped to it; one that
    does not cover it is refused (it had been read by array index, misplaced by the windows'
    offset, without a word)."""
    rgb = rng.uniform(0, 1, (30, 40, 3)).astype(np.float32)
    flow = np.zeros((30, 40, 2), np.float32)
    flow[8:20, 10:24] = (7, 2)
    src = _windowed(tmp_path, "img.exr", {c: rgb[..., i] for i, c in enumerate("RGB")},
                    (4, 2), (0, 0, 47, 35))
    big = np.zeros((40, 52, 2), np.float32)  # covers the image's window from (-2, -3)
    big[5:35, 6:46] = flow
    flows = _windowed(tmp_path, "flow.exr", {"flow.x": big[..., 0], "flow.y": big[..., 1]},
                      (-2, -3), (0, 0, 47, 35))
    depth = np.where(flow[..., 0] > 0, 1.0, 5.0).astype(np.float32)
    deep = np.full((40, 52), 9.0, np.float32)
    deep[5:35, 6:46] = depth
    depths = _windowed(tmp_path, "depth.exr", {"Z": deep}, (-2, -3), (0, 0, 47, 35))
    for extra, kw in (([], {}), (["--depth", str(depths)], {"depth": depth})):
        out = tmp_path / f"o{len(extra)}.exr"
        assert main(["blur", str(src), str(out), "--flow", str(flows), "--backend", "numpy",
                     *extra]) == 0
        np.testing.assert_allclose(exr.read_image(out),
                                   clblur.blur(rgb, flow, "linear", backend="numpy", **kw),
                                   atol=1e-6)
    short = _windowed(tmp_path, "short.exr", {"flow.x": flow[..., 0], "flow.y": flow[..., 1]},
                      (0, 0), (0, 0, 47, 35))  # same size, another place
    capsys.readouterr()
    assert main(["blur", str(src), str(tmp_path / "x.exr"), "--flow", str(short)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not cover the image's (4, 2) - (43, 31)" in err[0]


def test_exr_layers_are_named_never_guessed(tmp_path, rng, capsys):
    """A Blender multilayer render with several colour passes blurs from FILE.exr:LAYER; two
    view layers' vector passes or depth channels are refused until one is named (the first
    had been taken silently); plain X, Y, Z, W is a vector pass too."""
    rgba = rng.uniform(0, 1, (20, 24, 4)).astype(np.float32)
    chans = {f"View.{p}.{c}": rgba[..., i] * k for p, k in (("Combined", 1), ("AO", 0.5))
             for i, c in enumerate("RGBA")}
    moving = np.zeros((20, 24, 4), np.float32)
    moving[..., 0] = moving[..., 2] = -6  # Blender: previous and next, x right
    chans |= {f"Main.Vector.{c}": moving[..., i] for i, c in enumerate("XYZW")}
    chans |= {f"AOVs.Vector.{c}": np.zeros((20, 24), np.float32) for c in "XYZW"}
    chans |= {"Main.Depth.Z": np.ones((20, 24), np.float32),
              "AOVs.Depth.Z": np.ones((20, 24), np.float32)}
    src = tmp_path / "render.exr"
    exr.write_channels(src, chans)
    capsys.readouterr()
    for args, why in (([str(src), "--flow", f"{src}:Main"], "several colour layers"),
                      ([f"{src}:View.Combined", "--flow", str(src)],
                       "several Blender vector passes (view layers AOVs, Main)"),
                      ([f"{src}:View.Combined", "--flow", f"{src}:Main", "--depth", str(src)],
                       "several depth channels")):
        assert main(["blur", args[0], str(tmp_path / "x.exr"), *args[1:], "--vectors",
                     "blender"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and why in err[0], err
    out = tmp_path / "o.exr"
    assert main(["blur", f"{src}:View.Combined", str(out), "--flow", f"{src}:Main",
                 "--depth", f"{src}:Main.Depth.Z", "--vectors", "blender",
                 "--backend", "numpy"]) == 0
    flow = vectors.load_flow(src, "blender", layer="Main")
    np.testing.assert_allclose(exr.read_image(out), clblur.blur(
        rgba, flow, "linear", alpha=True, depth=np.ones((20, 24)), backend="numpy"), atol=1e-6)
    plain = tmp_path / "xyzw.exr"
    exr.write_channels(plain, {c: moving[..., i] for i, c in enumerate("XYZW")})
    np.testing.assert_array_equal(vectors.read_vectors(plain, "blender")["pass"], moving)


def test_inverse_depth_and_the_exr_default_response(tmp_path, rng):
    """`--inverse-depth` reads 1 / distance (Nuke's depth.Z): the same blur as the distance;
    an EXR's default response is linear, so a highlight of 8 and a negative stay (exp had
    clipped them at full scale and 0)."""
    rgb = rng.uniform(-0.1, 1, (20, 30, 3)).astype(np.float32)
    rgb[5, 5] = 8.0
    src = tmp_path / "hdr.exr"
    exr.write_image(src, rgb)
    flow = np.zeros((20, 30, 2), np.float32)
    flow[4:12, 4:14] = (6, 0)
    np.save(tmp_path / "flow.npy", flow)
    distance = np.where(flow[..., 0] > 0, 2.0, 10.0).astype(np.float32)
    exr.write_channels(tmp_path / "inv.exr", {"depth.Z": 1 / distance})
    out = tmp_path / "o.exr"
    assert main(["blur", str(src), str(out), "--flow", str(tmp_path / "flow.npy"), "--depth",
                 str(tmp_path / "inv.exr"), "--inverse-depth", "--backend", "numpy"]) == 0
    np.testing.assert_allclose(exr.read_image(out), clblur.blur(
        rgb, flow, "linear", depth=distance, backend="numpy"), atol=1e-6)
    assert exr.read_image(out).max() > 1 and exr.read_image(out).min() < 0


def test_batch_and_blur_file_take_an_exr_as_linear_light(tmp_path, rng):
    """`clblur batch` chooses the response per image as `clblur blur` does: an EXR in the
    folder goes through `linear` (a highlight of 8 and a negative stay), a PNG beside it
    through `exp`; a manifest cell still decides its image.  `blur_file` takes the same
    default."""
    from clblur.tiling import blur_file

    rgb = rng.uniform(-0.1, 1, (16, 24, 3)).astype(np.float32)
    rgb[5, 5] = 8.0
    src = tmp_path / "in"
    src.mkdir()
    for name in ("hdr.exr", "cell.exr"):
        exr.write_image(src / name, rgb)
    png = (rng.uniform(0, 1, (16, 24, 3)) * 255).astype(np.uint8)
    write_image(src / "ldr.png", png)
    (tmp_path / "m.csv").write_text("image,response\ncell.exr,srgb\n")
    out = tmp_path / "out"
    assert main(["batch", str(src), str(out), "--motion", "5,1", "--manifest",
                 str(tmp_path / "m.csv"), "--backend", "numpy", "--quiet"]) == 0
    for name, spec in (("hdr.exr", "linear"), ("cell.exr", "srgb")):
        np.testing.assert_allclose(exr.read_image(out / name),
                                   clblur.blur(rgb, (5, 1), spec, backend="numpy"), atol=1e-6)
    assert exr.read_image(out / "hdr.exr").max() > 1
    np.testing.assert_array_equal(read_image(out / "ldr.png"),
                                  clblur.blur(png, (5, 1), "exp", backend="numpy"))
    blur_file(src / "hdr.exr", tmp_path / "one.exr", (5, 1), backend="numpy")
    np.testing.assert_array_equal(exr.read_image(tmp_path / "one.exr"),
                                  exr.read_image(out / "hdr.exr"))


def test_bad_exr_colour_is_one_line(tmp_path, capfd):
    """A truncated file, UINT colour (IDs) and NaN colour: one line naming the file, exit 2
    (the library had printed its own two lines before ours)."""
    rgb = np.random.default_rng(2).uniform(0, 1, (32, 40, 3)).astype(np.float32)
    good = tmp_path / "good.exr"
    exr.write_image(good, rgb)
    data = good.read_bytes()
    (tmp_path / "trunc.exr").write_bytes(data[:len(data) // 2])
    exr.write_channels(tmp_path / "ids.exr", {c: np.arange(12, dtype=np.uint32).reshape(3, 4)
                                              for c in "RGB"})
    nan = rgb.copy()
    nan[3, 4, 1] = np.nan
    exr.write_image(tmp_path / "nan.exr", nan)
    capfd.readouterr()
    for name, why in (("trunc", "cannot read EXR"), ("ids", "unsigned integers"),
                      ("nan", "1 value(s) of the colour channels are NaN")):
        src = tmp_path / f"{name}.exr"
        assert main(["blur", str(src), str(tmp_path / "o.exr"), "--motion=3,0"]) == 2
        captured = capfd.readouterr()
        lines = (captured.out + captured.err).strip().splitlines()
        assert len(lines) == 1 and why in lines[0] and str(src) in lines[0], lines


def test_blur_layers_takes_the_overscan_its_windows_state(tmp_path, capsys):
    """Layers rendered with 2 px of overscan (a data window beyond the display window): the
    output is the display window, with the EXR windows; a different --overscan is refused
    (5 had cut 3 px of picture off, 0 had written the overscan as picture)."""
    h, w = 24, 32
    fg = np.zeros((h + 4, w + 4, 4), np.float32)
    fg[10:18, 8:16] = (1.0, 0.2, 0.1, 1.0)
    bg = np.full((h + 4, w + 4, 3), 0.3, np.float32)
    display = (0, 0, w - 1, h - 1)
    paths = []
    for name, img in (("fg", fg), ("bg", bg)):
        chans = {c: img[..., i] for i, c in enumerate("RGBA"[:img.shape[2]])}
        paths.append(str(_windowed(tmp_path, f"{name}.exr", chans, (-2, -2), display)))
    flow = np.zeros((h + 4, w + 4, 2), np.float32)
    flow[fg[..., 3] > 0] = (6, 0)
    np.save(tmp_path / "fg.npy", flow)
    np.save(tmp_path / "bg.npy", np.zeros_like(flow))
    layers = ["--layer", paths[0], str(tmp_path / "fg.npy"), "--layer", paths[1],
              str(tmp_path / "bg.npy")]
    out = tmp_path / "o.exr"
    assert main(["blur-layers", str(out), *layers, "--backend", "numpy"]) == 0
    got = exr.layout(out)
    assert got.data_window == got.display_window == display
    want = clblur.blur_layers([(fg, flow), (bg, np.zeros_like(flow))], "linear", overscan=2,
                              backend="numpy")
    np.testing.assert_allclose(exr.read_image(out), want, atol=1e-6)
    capsys.readouterr()
    assert main(["blur-layers", str(tmp_path / "x.exr"), *layers, "--overscan", "5"]) == 2
    assert "reaches 2 px beyond their display window" in capsys.readouterr().err
