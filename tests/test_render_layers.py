"""Multi-layer renders (``clblur.blur_layers``): each object its own layer, nothing hidden."""

from __future__ import annotations

import re

import numpy as np
import pytest

import clblur
from clblur.errors import InputError
from clblur.scenes import example_scenes, object_layers, psnr, render


@pytest.fixture(scope="module")
def crossing():
    """The study's crossing with the fast disc behind, smaller: truth and its layers."""
    scene = example_scenes(160, 112)["crossing_fast_behind"]
    return scene, render(scene, "srgb", np.uint8, samples=48), object_layers(scene, "srgb")


def straight(layers):
    return [(image, flow) for image, flow, _, _ in layers]


def bent(layers):
    return [(image, (first, second)) for image, _, first, second in layers]


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_one_layer_is_the_gather_with_alpha(dtype, rng):
    """One layer, translating: the composite of one plane along its vector is the gather of
    the premultiplied image, which is what ``blur(..., alpha=True)`` does (any coverage)."""
    image = rng.random((30, 40, 4))
    image = (image * 255).astype(np.uint8) if dtype == np.uint8 else image.astype(dtype)
    flow = np.empty((30, 40, 2), np.float32)
    flow[...] = (5.5, -2.0)
    for motion in (flow, (5.5, -2.0)):
        for anchor in ("center", "start"):
            want = clblur.blur(image, motion, "srgb", alpha=True, anchor=anchor,
                               backend="numpy")
            got = clblur.blur_layers([(image, motion)], "srgb", anchor=anchor, backend="numpy")
            np.testing.assert_array_equal(got, want)


def test_still_layers_are_composited_over(rng):
    """No motion: the front layer over the back one, in linear light (premultiplied float)."""
    front = rng.random((20, 24, 4)).astype(np.float32)
    front[..., :3] *= front[..., 3:]  # premultiplied
    back = rng.random((20, 24, 4)).astype(np.float32)
    back[..., 3] = 1.0
    zero = np.zeros((20, 24, 2), np.float32)
    got = clblur.blur_layers([(front, zero), (back, zero)], "linear", backend="numpy")
    want = front + (1.0 - front[..., 3:]) * back
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_a_crossing_behind_is_right_from_its_layers(crossing):
    """The far, fast disc passes behind the near one; part of it is hidden at the frame time.
    From one frame and its depth that part is a guess; from the layers it is known."""
    scene, truth, layers = crossing
    swept = truth.swept
    from_layers = psnr(clblur.blur_layers(bent(layers), "srgb", backend="numpy")[..., :3],
                       truth.image, swept)
    from_frame = psnr(clblur.blur(truth.sharp, truth.flow, "srgb", depth=truth.depth,
                                  backend="numpy"), truth.image, swept)
    assert from_layers >= 44.0
    assert from_layers > from_frame + 3.0
    # the order is what makes it right: the far disc listed first paints over the near one
    swapped = [layers[1], layers[0], layers[2]]
    wrong = psnr(clblur.blur_layers(bent(swapped), "srgb", backend="numpy")[..., :3],
                 truth.image, swept)
    assert wrong < from_layers - 10.0


def test_overscan_brings_in_what_enters_the_frame():
    """A star leaving the frame: its parts outside the frame at the frame time were inside
    earlier in the shutter.  Layers with overscan hold them; the output keeps the frame's size."""
    scene = example_scenes(160, 112)["star_leaving"]
    truth = render(scene, "srgb", np.uint8, samples=48)
    edge = np.zeros(truth.swept.shape, bool)
    edge[:, -12:] = True
    edge &= truth.swept
    scores = {}
    for m in (0, 24):
        out = clblur.blur_layers(bent(object_layers(scene, "srgb", overscan=m)), "srgb",
                                 overscan=m, backend="numpy")
        assert out.shape == truth.image.shape[:2] + (4,)
        scores[m] = psnr(out[..., :3], truth.image, edge)
    assert scores[24] > scores[0] + 3.0


def test_transparent_layers_leave_coverage(crossing):
    """Without the background layer the result is the objects' premultiplied exposure: its
    coverage is the shutter-averaged coverage of the objects (the renderer's, within the
    rounding of the coverage and the sampling of the rims)."""
    scene, truth, layers = crossing
    floats = object_layers(scene, "srgb", np.float32)[:-1]
    out = clblur.blur_layers(bent(floats), "srgb", backend="numpy")
    err = np.abs(out[..., 3] - truth.exposure_alpha)
    assert err.mean() < 2e-3 and np.percentile(err, 99) < 0.05
    assert out[..., 3].max() <= 1.0 + 1e-6


def test_bad_layers_are_one_line_errors(rng):
    image = rng.random((10, 12, 4)).astype(np.float32)
    flow = np.zeros((10, 12, 2), np.float32)
    cases = {
        "non-empty list": [],
        "(image, motion) pair": [(image,)],
        "mix straight and bent": [(image, flow), (image, (flow, flow))],
        "layers must match": [(image, flow), (image[:9], flow[:9])],
        "pair (first, second)": [(image, (flow, flow, flow))],
    }
    for words, layers in cases.items():
        with pytest.raises(InputError, match=re.escape(words)):
            clblur.blur_layers(layers, "srgb", backend="numpy")
    with pytest.raises(InputError, match="overscan"):
        clblur.blur_layers([(image, flow)], "srgb", overscan=5, backend="numpy")
    with pytest.raises(InputError, match="overscan"):
        clblur.blur_layers([(image, flow)], "srgb", overscan=-1, backend="numpy")
    with pytest.raises(InputError, match="bent"):
        clblur.blur_layers([(image, (flow, flow))], "srgb", weights=[1, 2, 1], backend="numpy")
    with pytest.raises(InputError, match="anchored at its bend"):
        clblur.blur_layers([(image, (flow, flow))], "srgb", anchor="start", backend="numpy")
    over = image.copy()
    over[0, 0, 3] = 1.5
    with pytest.raises(InputError, match=re.escape("in [0, 1]")):
        clblur.blur_layers([(over, flow)], "srgb", backend="numpy")
    with pytest.raises(ValueError, match="NaN"):
        clblur.blur_layers([(image, np.full_like(flow, np.nan))], "srgb", backend="numpy")


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_opencl_render_layers_match_the_reference(opencl, dtype):
    """The device composite of multi-layer renders within docs/tolerances.md ("Layered
    exposure"): straight and bent, overscan, a turning object."""
    for name in ("crossing_fast_behind", "spinning_rect"):
        scene = example_scenes(160, 112)[name]
        layers = object_layers(scene, "srgb", dtype, overscan=6)
        for form in (straight, bent):
            ref = clblur.blur_layers(form(layers), "srgb", overscan=6, backend="numpy")
            got = clblur.blur_layers(form(layers), "srgb", overscan=6, backend="opencl")
            if dtype == np.uint8:
                d = np.abs(ref.astype(np.int64) - got)
                assert d.max() <= 1 and (d > 0).mean() <= 0.02
            else:
                np.testing.assert_allclose(got, ref, atol=2e-5, rtol=1e-5)


def test_command_line_blurs_layer_files(tmp_path, crossing, capsys):
    """``clblur blur-layers``: PNG layers with .npy vectors give the library's result; bad
    layers are one line and exit code 2."""
    from clblur.cli import main
    from clblur.io import read_image, write_image

    _, _, layers = crossing
    argv = ["blur-layers", str(tmp_path / "out.png"), "--response", "srgb",
            "--backend", "numpy"]
    for i, (image, flow, _, _) in enumerate(layers):
        write_image(tmp_path / f"layer{i}.png", image)
        np.save(tmp_path / f"layer{i}.npy", flow)
        argv += ["--layer", str(tmp_path / f"layer{i}.png"), str(tmp_path / f"layer{i}.npy")]
    assert main(argv) == 0
    want = clblur.blur_layers(straight(layers), "srgb", backend="numpy")
    np.testing.assert_array_equal(read_image(tmp_path / "out.png"), want)
    # an RGB layer is opaque: the background without its alpha channel gives the same
    write_image(tmp_path / "rgb.png", layers[-1][0][..., :3])
    rgb = argv[:-2] + [str(tmp_path / "rgb.png"), argv[-1]]
    rgb[1] = str(tmp_path / "out_rgb.png")
    assert main(rgb) == 0
    np.testing.assert_array_equal(read_image(tmp_path / "out_rgb.png"), want)
    write_image(tmp_path / "small.png", layers[0][0][1:])
    capsys.readouterr()
    bad = ["blur-layers", str(tmp_path / "bad.png"), "--backend", "numpy",
           "--layer", str(tmp_path / "small.png"), str(tmp_path / "layer0.npy")]
    assert main(bad) == 2
    err = capsys.readouterr().err.strip()
    assert "shape" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "bad.png").exists()
    # a bent path needs a renderer's pass (a clblur flow is one straight vector per pixel)
    bad = [*argv[:1], str(tmp_path / "bad.png"), *argv[2:], "--path", "bent"]
    assert main(bad) == 2
    assert "--vectors blender or nuke" in capsys.readouterr().err


def test_curved_path_without_a_bend_is_the_straight_path(crossing):
    """Equal halves have no curvature: the curved path is the straight one, bit for bit."""
    _, _, layers = crossing
    halves = [(image, (flow / 2, flow / 2)) for image, flow, _, _ in layers]
    np.testing.assert_array_equal(
        clblur.blur_layers(halves, "srgb", curved=True, backend="numpy"),
        clblur.blur_layers(straight(layers), "srgb", backend="numpy"))
    with pytest.raises(InputError, match="bent path"):
        clblur.blur_layers(straight(layers), "srgb", curved=True, backend="numpy")


def test_curved_path_follows_a_spinning_accelerating_star():
    """The star turns by 34 degrees and accelerates: its points move along arcs and a
    parabola, which the parabola through the halves' three points follows far better than
    two straight halves."""
    scene = example_scenes(160, 112)["star_leaving"]
    truth = render(scene, "srgb", np.uint8, samples=48)
    layers = bent(object_layers(scene, "srgb", overscan=24))
    two = psnr(clblur.blur_layers(layers, "srgb", overscan=24, backend="numpy")[..., :3],
               truth.image, truth.swept)
    curved = psnr(clblur.blur_layers(layers, "srgb", overscan=24, curved=True,
                                     backend="numpy")[..., :3], truth.image, truth.swept)
    assert curved > two + 3.0


def test_opencl_curved_layouts_agree_bit_for_bit(opencl):
    """The CPU layout (eight pixels per work-item) and the one-pixel kernel on curved paths of
    turning layers: the same float operations, the same bits; and the reference within the
    layered tolerance."""
    from clblur import layered_exposure
    from clblur.opencl.layered import composite
    from clblur.reference import linearise
    from clblur.render_layers import layers_for
    from clblur.request import make_plan

    scene = example_scenes(160, 112)["star_leaving"]
    layers = object_layers(scene, "srgb", np.float32, overscan=8)
    linear = [linearise(make_plan(image, flow, "srgb", alpha=True))
              for image, flow, _, _ in layers]
    chord = [first + second for _, _, first, second in layers]
    bend = [2 * (second - first) for _, _, first, second in layers]
    region = np.ones(linear[0].shape[:2], bool)
    stack = layers_for(linear, chord, 0.5, region, curvature=bend)
    assert stack.warped[0] and stack.curvature is not None
    # RGB light and coverage only (the CPU layout takes three light channels)
    stack.planes = np.ascontiguousarray(stack.planes[..., [0, 1, 2, 4]])
    stack.linear = np.ascontiguousarray(stack.linear[..., :3])
    shape = region.shape
    lanes = composite(stack, 0.5, None, None, shape, lanes=True)
    one = composite(stack, 0.5, None, None, shape, lanes=False)
    np.testing.assert_array_equal(lanes, one)
    ref = layered_exposure.composite(stack, 0.5, None, None, shape)[region]
    np.testing.assert_allclose(one, ref, atol=2e-5, rtol=1e-5)


def test_command_line_reads_view_layers_of_a_multilayer_exr(tmp_path, capsys):
    """Blender's multilayer EXR: each view layer's RGBA (``<layer>.Combined.R/G/B/A``) and
    Vector pass (``<layer>.Vector.X/Y/Z/W``) named by ``FILE.exr:PREFIX``."""
    pytest.importorskip("OpenEXR")
    from clblur.cli import main
    from clblur.io import exr
    from clblur.vectors import from_blender, to_blender

    scene = example_scenes(96, 64)["crossing_fast_behind"]
    layers = object_layers(scene, "linear", np.float32)
    names = ["Slow", "Fast", "Background"]
    channels = {}
    for name, (image, _, first, second) in zip(names, layers, strict=True):
        for c, plane in zip("RGBA", np.moveaxis(image, 2, 0), strict=True):
            channels[f"{name}.Combined.{c}"] = plane
        # a 360-degree shutter (one frame): the halves are the per-frame displacements
        vector_pass = to_blender(2 * first, 2 * second)
        for c, plane in zip("XYZW", np.moveaxis(vector_pass, 2, 0), strict=True):
            channels[f"{name}.Vector.{c}"] = plane
    exr.write_channels(tmp_path / "render.exr", channels)
    argv = ["blur-layers", str(tmp_path / "out.exr"), "--response", "linear", "--backend",
            "numpy", "--vectors", "blender", "--vector-shutter", "1", "--path", "curved"]
    for name in names:
        argv += ["--layer", f"{tmp_path / 'render.exr'}:{name}.Combined",
                 f"{tmp_path / 'render.exr'}:{name}"]
    assert main(argv) == 0
    for _, _, first, second in layers:  # the pass holds the renderer's halves
        got = from_blender(to_blender(2 * first, 2 * second), 1.0, bent=True)
        np.testing.assert_allclose(got[0], first, atol=1e-5)
        np.testing.assert_allclose(got[1], second, atol=1e-5)
    want = clblur.blur_layers([(image, (first, second)) for image, _, first, second in layers],
                              "linear", curved=True, backend="numpy")
    np.testing.assert_allclose(exr.read_image(tmp_path / "out.exr"), want, atol=1e-6)
    capsys.readouterr()
    argv[-1] = f"{tmp_path / 'render.exr'}:Nowhere"
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Nowhere.Vector" in err and len(err.strip().splitlines()) == 1


def test_render_layers_solve_the_inverse_motion_to_convergence(monkeypatch):
    """A renderer's vectors are exact: RENDER_INVERSE_STEPS steps score as many more do, and
    above the count kept for estimated flow (INVERSE_STEPS) on the turning star."""
    from clblur import layered_exposure, render_layers

    scene = example_scenes(160, 112)["star_leaving"]
    truth = render(scene, "srgb", np.uint8, samples=48)
    layers = bent(object_layers(scene, "srgb", overscan=24))

    def score(steps: int) -> float:
        monkeypatch.setattr(render_layers, "RENDER_INVERSE_STEPS", steps)
        out = clblur.blur_layers(layers, "srgb", overscan=24, curved=True, backend="numpy")
        return psnr(out[..., :3], truth.image, truth.swept)

    kept = score(render_layers.RENDER_INVERSE_STEPS)
    assert abs(kept - score(8)) < 0.1
    assert kept > score(layered_exposure.INVERSE_STEPS) + 0.2


def _brute_swept(covered, d, anchor, c=None, steps=4001):
    """Pixels whose samples at ``steps`` instants of the path read a covered bilinear corner
    (positions clamped to the image, as the sampler does): the definition of ``swept``."""
    h, w = covered.shape
    c = np.zeros(2) if c is None else np.asarray(c, np.float64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.zeros((h, w), bool)
    for t in np.linspace(-anchor, 1.0 - anchor, steps):
        x = np.clip(xx - d[0] * t - c[0] * t * t, 0, w - 1)
        y = np.clip(yy - d[1] * t - c[1] * t * t, 0, h - 1)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
        out |= covered[y0, x0] | covered[y0, x1] | covered[y1, x0] | covered[y1, x1]
    return out


def test_swept_holds_every_pixel_a_rigid_layer_can_reach(rng):
    """``render_layers.swept`` against a brute-force sampling of the path: never short
    (a missed pixel would lose the layer's light), and within two pixels of it (the
    3 x 3 margin and the whole-pixel offsets), with paths that leave the image."""
    from scipy.ndimage import binary_dilation

    from clblur.render_layers import swept

    for trial in range(12):
        h, w = 40, 56
        covered = np.zeros((h, w), bool)
        r0, c0 = rng.integers(0, h - 6), rng.integers(0, w - 6)
        covered[r0:r0 + rng.integers(1, 7), c0:c0 + rng.integers(1, 7)] = True
        if trial % 4 == 0:
            covered[:, 0] |= rng.random(h) < 0.2  # touching the image's edge
        d = rng.uniform(-30, 30, 2)
        c = rng.uniform(-12, 12, 2) if trial % 3 == 0 else None
        anchor = (0.5, 0.0, 1.0)[trial % 3]
        got = swept(covered, d, anchor, c)
        want = _brute_swept(covered, d, anchor, c)
        assert not (want & ~got).any(), trial
        assert not (got & ~binary_dilation(want, np.ones((5, 5), bool))).any(), trial
        assert got.sum() < want.sum() + 4 * (h + w) + 200


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_culling_changes_no_pixel(dtype, monkeypatch):
    """The culled composite (a still layer alone at a pixel is its plane, looked up per code
    for integer images; a rigid layer visited only where its path reaches) gives what
    compositing every pixel with every layer in reach gives: the same codes for integer
    images, float rounding for float ones; straight, bent and curved paths."""
    from clblur import render_layers

    scene = example_scenes(160, 112)["pan_and_object"]
    layers = object_layers(scene, "srgb", dtype, overscan=6)
    still_scene = example_scenes(160, 112)["crossing_fast_behind"]
    still_layers = object_layers(still_scene, "srgb", dtype)

    def run(form, lay, **kw):
        return clblur.blur_layers(form(lay), "srgb", backend="numpy", **kw)

    cases = [(straight, layers, dict(overscan=6)), (bent, layers, dict(overscan=6)),
             (bent, layers, dict(overscan=6, curved=True)), (straight, still_layers, {}),
             (bent, still_layers, {})]
    culled = [run(form, lay, **kw) for form, lay, kw in cases]
    alone = render_layers.still_alone
    monkeypatch.setattr(render_layers, "still_alone",
                        lambda stack: (np.zeros_like(stack.region), alone(stack)[1]))
    monkeypatch.setattr(render_layers, "swept", lambda covered, *a: np.ones_like(covered))
    for got, (form, lay, kw) in zip(culled, cases, strict=True):
        want = run(form, lay, **kw)
        if np.dtype(dtype).kind == "u":
            np.testing.assert_array_equal(got, want)
        else:
            np.testing.assert_allclose(got, want, atol=1e-6, rtol=0)
    monkeypatch.undo()
    # the background is still in crossing_fast_behind: most of its pixels skip the composite
    from clblur.reference import linearise
    from clblur.request import make_plan

    linear = [linearise(make_plan(image, flow, "srgb", alpha=True))
              for image, flow, _, _ in still_layers]
    region = np.ones(linear[0].shape[:2], bool)
    stack = render_layers.layers_for(linear, [f for _, f, _, _ in still_layers], 0.5, region)
    assert render_layers.still_alone(stack)[0].mean() > 0.5


def test_continuous_exposure_of_a_render(opencl):
    """A renderer's vectors are exposure chords: exposure="continuous" (the trapezoid rule)
    scores closer to the sub-frame truth than equal weights, and the device is within the
    layered tolerance of the reference (its half-weight ends, culled composite)."""
    scene = example_scenes(160, 112)["disc"]
    truth = render(scene, "srgb", np.uint8, samples=64)
    layers = straight(object_layers(scene, "srgb"))
    ref = clblur.blur_layers(layers, "srgb", backend="numpy", exposure="continuous")
    got = clblur.blur_layers(layers, "srgb", backend="opencl", exposure="continuous")
    d = np.abs(ref.astype(np.int64) - got)
    assert d.max() <= 1 and (d > 0).mean() <= 0.02
    frames = clblur.blur_layers(layers, "srgb", backend="numpy")
    gain = (psnr(ref[..., :3], truth.image, truth.swept)
            - psnr(frames[..., :3], truth.image, truth.swept))
    assert gain > 1.0, gain
    with pytest.raises(InputError, match="not both"):
        clblur.blur_layers(layers, "srgb", backend="numpy", exposure="continuous",
                           weights=[1, 1])


def test_a_layer_without_alpha_is_opaque_in_python_as_on_the_command_line(rng):
    # an RGB layer had its blue read as coverage (README: a layer without alpha is opaque)
    rgb = rng.integers(0, 256, (20, 24, 3)).astype(np.uint8)
    flow = np.zeros((20, 24, 2), np.float32)
    flow[..., 0] = 3.0
    rgba = np.dstack([rgb, np.full((20, 24), 255, np.uint8)])
    for image, full in ((rgb, rgba), (rgb[..., 0], rgba[..., [0, 3]])):
        np.testing.assert_array_equal(
            clblur.blur_layers([(image, flow)], "srgb", backend="numpy"),
            clblur.blur(full, flow, "srgb", alpha=True, backend="numpy"))
