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
