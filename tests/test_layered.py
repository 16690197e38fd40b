"""Layered exposure (``clblur.layered_exposure``), the pipeline entry and alpha.

Scenes with an exact sub-frame exposure come from ``tests/layered_scenes.py``; the bench
(``bench/bench_occlusion.py``) scores every scene at K = 64, these tests at K = 32.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import clblur
from clblur import layered_exposure as layered
from clblur import pipeline, reference
from clblur.request import make_plan
from clblur.responses import response

sys.path.insert(0, str(Path(__file__).parent))
from layered_scenes import Disc, Scene, psnr, scenes  # noqa: E402

SRGB = response("srgb")


def scored(name: str, k: int = 32):
    sc = scenes()[name]
    frame = SRGB.forward(sc.render(sc.anchor))
    truth = SRGB.forward(sc.truth(k))
    flow, depth = sc.maps()
    return sc, frame, truth, flow, depth, sc.swept()


@pytest.fixture(scope="module")
def disc():
    return scored("disc")


@pytest.fixture(scope="module")
def crossing():
    return scored("crossing-faster-behind")


# --------------------------------------------------------------------- accuracy vs truth

def test_disc_smears_over_the_background(disc):
    sc, frame, truth, flow, depth, swept = disc
    gather = clblur.blur(frame, flow, "srgb", backend="numpy")
    layers = clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth)
    plate = clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth,
                        background=SRGB.forward(sc.background()))
    # measured (K = 32): gather 30.9, depth 42.9, depth + clean plate 51.2 dB
    assert psnr(gather, truth, swept) < 32
    assert psnr(layers, truth, swept) > 41.5
    assert psnr(plate, truth, swept) > 50


def test_crossing_with_the_faster_object_behind(crossing):
    """Depth decides who is in front; speed ordering gets this scene wrong."""
    sc, frame, truth, flow, depth, swept = crossing
    by_depth = clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth)
    by_speed = clblur.blur(frame, flow, "srgb", backend="numpy", depth="speed")
    plate = clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth,
                        background=SRGB.forward(sc.background()))
    gather = clblur.blur(frame, flow, "srgb", backend="numpy")
    # measured (K = 32): gather 29.7, speed 32.6, depth 37.6, depth + plate 46.0 dB
    assert psnr(by_depth, truth, swept) > psnr(by_speed, truth, swept) + 3
    assert psnr(by_depth, truth, swept) > psnr(gather, truth, swept) + 6
    assert psnr(plate, truth, swept) > 45.5


@pytest.mark.parametrize("view", ["flip x", "flip y", "transpose"])
def test_layered_exposure_commutes_with_flips_and_transposition(crossing, view):
    """Mirroring or transposing the scene (image, depth and the vectors with it) mirrors or
    transposes the result.  Not bit for bit: the culling's tiles start at the top left and
    the nearest-pixel transforms break ties in row-major order, so a handful of pixels on
    the layers' seams take another equidistant neighbour.  Measured on this scene: under
    0.4 % of the pixels move by more than 1e-3, none by more than 0.008, swept PSNR within
    0.03 dB."""
    sc, frame, truth, flow, depth, swept = crossing
    mirror = {"flip x": (lambda a: a[:, ::-1], np.float32([-1, 1])),
              "flip y": (lambda a: a[::-1], np.float32([1, -1])),
              "transpose": (lambda a: a.swapaxes(0, 1), None)}
    view_of, sign = mirror[view]
    moved = view_of(flow)[..., ::-1] if sign is None else view_of(flow) * sign
    img, v, d = (np.ascontiguousarray(x) for x in (view_of(frame), moved, view_of(depth)))
    got = view_of(clblur.blur(img, v, "srgb", backend="numpy", depth=d))
    want = clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth)
    diff = np.abs(got - want)
    assert (diff > 1e-3).mean() < 0.01 and diff.max() < 0.02 and diff.mean() < 1e-4
    assert abs(psnr(got, truth, swept) - psnr(want, truth, swept)) < 0.1


def test_a_far_object_continues_under_a_near_one_as_far_as_its_convex_hull():
    """The amodal completion of an intermediate layer: the convex hull of what shows of it,
    where a nearer layer covers it; never outside the object for a convex one."""
    from clblur.layer_planes import hidden_hull

    yy, xx = np.mgrid[:60, :80]
    near = (yy - 30) ** 2 + (xx - 30) ** 2 < 15 ** 2
    far = (yy - 30) ** 2 + (xx - 50) ** 2 < 12 ** 2  # 80 px of it behind the near disc
    labels = np.where(near, 0, np.where(far, 1, 2))
    hull = hidden_hull(labels, 1)
    assert hull.sum() > 20 and not (hull & ~(far & near)).any()  # 26: the chord's side
    assert not hidden_hull(labels, 0).any()  # nothing is nearer than the nearest layer


def _two_shapes(near: np.ndarray, far: np.ndarray) -> np.ndarray:
    return np.where(near, 0, np.where(far, 1, 2))


def test_a_round_far_object_stays_round_under_a_near_one():
    """A far disc whose visible silhouette lies on one circle continues as that disc under
    the near one (the hull stops at the chord between the silhouettes' crossings), even when
    most of it is hidden; never a pixel outside it."""
    from clblur.layer_planes import hidden_completion, hidden_hull

    yy, xx = np.mgrid[:80, :100]

    def disc(cx, cy, r):
        return (yy - cy) ** 2 + (xx - cx) ** 2 < r ** 2

    for near, far, least in ((disc(30, 40, 15), disc(50, 40, 12), 1.0),   # 80 hidden px
                             (disc(40, 40, 20), disc(52, 46, 13), 0.98),  # 386, a crescent shows
                             (disc(30, 40, 12), disc(55, 40, 22), 1.0)):  # 126
        labels = _two_shapes(near, far)
        hidden = far & near
        got = hidden_completion(labels, 1)
        assert not (got & ~hidden).any()
        assert got.sum() >= least * hidden.sum() > hidden_hull(labels, 1).sum()
        for view in (np.fliplr, np.flipud, np.transpose):  # the same pixels, seen flipped
            assert np.array_equal(hidden_completion(view(labels), 1), view(got))
    assert not hidden_completion(_two_shapes(disc(30, 40, 15), disc(50, 40, 12)), 0).any()


def test_a_far_object_that_is_not_round_keeps_the_hull():
    """Squares, a bar, ellipses and a straight edge partly hidden by a near disc: their
    visible silhouettes lie on no circle, so the completion is the convex hull alone (no arc
    invents a round side for them)."""
    from clblur.layer_planes import hidden_completion, hidden_hull

    yy, xx = np.mgrid[:80, :100]

    def disc(cx, cy, r):
        return (yy - cy) ** 2 + (xx - cx) ** 2 < r ** 2

    square = (abs(xx - 55) < 12) & (abs(yy - 40) < 12)
    bar = (abs(xx - 50) < 40) & (abs(yy - 40) < 6)
    wide = ((xx - 55) / 22.0) ** 2 + ((yy - 40) / 10.0) ** 2 < 1
    tall = ((xx - 55) / 10.0) ** 2 + ((yy - 40) / 22.0) ** 2 < 1
    for near, far in ((disc(38, 24, 12), square), (disc(40, 40, 10), square),
                      (disc(50, 40, 10), bar), (disc(30, 40, 12), wide),
                      (disc(38, 40, 10), tall), (disc(60, 40, 10), xx > 60)):
        labels = _two_shapes(near, far)
        assert np.array_equal(hidden_completion(labels, 1), hidden_hull(labels, 1))


def test_a_disc_hidden_at_the_frame_time_streaks_whole():
    """clblur.scenes' crossing_hidden_behind: at the frame time the fast far disc shows only
    a crescent beside the slow near one, and its streak in the truth is the whole disc.
    Measured (K = 64, swept region): 29.2 dB with the hull alone, 42.0 with the disc
    completed round (42.0 with the true hidden shape put in by hand)."""
    from clblur import scenes as rendered

    r = rendered.render(rendered.example_scenes()["crossing_hidden_behind"], "srgb",
                        np.uint8, samples=64, spp=2)
    got = clblur.blur(r.sharp, r.flow, "srgb", anchor="center", backend="numpy",
                      depth=r.depth)
    assert rendered.psnr(got, r.image, r.swept) > 40.0


def test_the_slow_disc_behind_a_fast_one_is_completed_under_it():
    """clblur.scenes' crossing_fast_front: the slow far disc is partly hidden by the fast
    near one, which uncovers it during the shutter.  Measured (K = 64, swept region): with
    2 px under the fast disc 37.7 dB, with the hull 41.7 dB, completed round 42.3 dB."""
    from clblur import scenes as rendered

    r = rendered.render(rendered.example_scenes()["crossing_fast_front"], "srgb", np.uint8,
                        samples=64, spp=2)
    got = clblur.blur(r.sharp, r.flow, "srgb", anchor="center", backend="numpy",
                      depth=r.depth)
    assert rendered.psnr(got, r.image, r.swept) > 41.9


@pytest.fixture(scope="module")
def spinning():
    """clblur.scenes' spinning_rect (turns 26 degrees while it moves) at K = 64."""
    from clblur import scenes as rendered

    scene = rendered.example_scenes()["spinning_rect"]
    return rendered.render(scene, "srgb", np.uint8, samples=64, spp=2)


def test_a_turning_layer_is_read_along_its_inverse_motion(spinning, monkeypatch):
    """A turning object's points do not pass a pixel along that pixel's own vector: the layer
    is read where its point was at the frame time (INVERSE_STEPS fixed-point steps)."""
    from clblur import scenes as rendered

    r = spinning

    def score() -> float:
        out = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth=r.depth)
        return rendered.psnr(out, r.image, r.swept)

    turned = score()
    monkeypatch.setattr(layered, "INVERSE_STEPS", 0)
    own_vector = score()
    # measured (K = 64): 42.4 dB with the inverse motion, 32.6 dB along each pixel's own vector
    assert turned > 41.0
    assert turned > own_vector + 8.0


def test_inverse_motion_is_safeguarded_where_the_map_does_not_contract():
    """q <- p - D(q) t with D_x = g (x - 32): the steps contract for |g t| < 1 and are taken;
    for |g t| > 1 each step moves further from the solution, and the first guess (the
    iterate of least residual) is read instead."""
    h, w = 4, 64
    xx = np.broadcast_to(np.arange(w, dtype=np.float64), (h, w))
    yy = np.broadcast_to(np.arange(h, dtype=np.float64)[:, None], (h, w))
    num, den, tt = np.full((h, w), 1.0), np.full((h, w), 2.0), np.zeros((h, w))  # t = 1/2
    for g, expected in ((0.5, 38.375), (3.0, 28.0)):
        d = np.zeros((h, w, 2))
        d[..., 0] = g * (xx - 32.0)
        x0 = xx - d[..., 0] * 0.5  # the rigid guess
        x, y = layered._inverse_motion(d, None, x0, yy, xx, yy, num, den, tt, (0, 0), (h, w))
        # p = 40: g = 0.5 steps 38 -> 38.5 -> 38.375 (residuals 0.5, 0.125: contracting);
        # g = 3 steps 28 -> 46 -> 19 (residuals 18, 27): 28 is kept
        assert x[1, 40] == pytest.approx(expected)
        np.testing.assert_array_equal(y, yy)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_opencl_safeguarded_inverse_motion_matches_the_reference(opencl, dtype):
    """A layer whose vectors change faster than the steps contract (|t| |grad D| > 1, as
    estimated flow can): the device picks the reference's iterates."""
    rng = np.random.default_rng(5)
    h, w = 48, 96
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    lin = rng.uniform(0.05, 0.9, (h, w, 3))
    inside = np.hypot(xx - 48, yy - 24) < 14
    flow = np.zeros((h, w, 2), np.float32)
    flow[..., 0] = np.where(inside, 12.0 + 3.0 * (xx - 48), 0.0)  # grad 3: expands
    flow[..., 1] = np.where(inside, 2.0 * np.sin(xx / 2.0), 0.0)
    depth = np.where(inside, 1.0, 10.0)
    img = SRGB.forward(lin)
    img = np.rint(img * 255).astype(np.uint8) if dtype == np.uint8 else img.astype(dtype)
    ref = clblur.blur(img, flow, "srgb", backend="numpy", depth=depth)
    got = clblur.blur(img, flow, "srgb", backend="opencl", depth=depth)
    agree(ref, got)
    # and the CPU layout (eight lanes as vectors) is the one-pixel kernel, bit for bit
    from clblur.layer_planes import prepare
    from clblur.opencl.layered import composite

    layers = prepare(lin, flow, depth, 0.5, layered.region_mask(flow, 0.5))
    assert layers.warped.any()
    np.testing.assert_array_equal(composite(layers, 0.5, None, None, (h, w), lanes=True),
                                  composite(layers, 0.5, None, None, (h, w), lanes=False))


def test_departure_orders_a_tracked_subject_in_front():
    """A camera tracks a subject (2 px) across a background that pans 24 px: speed puts the
    background in front and does worse than the gather; departure from the dominant motion
    (the background's) orders it as the renderer's depth does."""
    from clblur import scenes as rendered
    from clblur.layering import departure_order
    from clblur.scenes import Background, Scene, SceneObject, wave_texture
    from clblur.scenes import Disc as RoundShape

    w, h = 160, 112
    bg = Background(wave_texture(1, (0.16, 0.14, 0.10), 0.6), velocity=(-24.0, 0.0))
    ball = wave_texture(2, (0.62, 0.35, 0.18), 0.5, periods=(5.0, 16.0))
    scene = Scene(w, h, bg, (SceneObject(RoundShape(18), ball, (w / 2, h / 2), (2.0, 0.0),
                                         1.0),), "tracked", "a tracked subject")
    r = rendered.render(scene, "srgb", np.uint8, samples=32, spp=2)

    def score(depth) -> float:
        out = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth=depth)
        return rendered.psnr(out, r.image, r.swept)

    departure, speed, gather = score("departure"), score("speed"), score(None)
    # measured (K = 64): departure 48.7 (the true depth's score), speed 33.2, gather 34.7
    assert departure > gather + 10.0 and departure > speed + 10.0
    assert departure == pytest.approx(score(r.depth), abs=0.05)
    np.testing.assert_array_equal(
        clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth="departure"),
        clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth=departure_order(r.flow)))
    with pytest.raises(TypeError, match="depth must be .* 'speed' or 'departure'"):
        clblur.blur(r.sharp, r.flow, "srgb", backend="numpy", depth="nearest")


def test_region_takes_the_inside_of_a_turning_object(rng):
    """Far from any motion edge, a body that turns while it moves still departs from the
    gather: those pixels take the layered path (else a seam where the region ends).  Flow
    noise does not, nor does a translation."""
    h, w = 160, 160
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    turn = 0.4  # radians over the exposure, about the centre, while moving 20 px right
    flow = np.stack([20 - (yy - 80) * turn, (xx - 80) * turn], -1).astype(np.float32)
    outside = np.hypot(xx - 80, yy - 80) > 70
    flow[outside] = 0.0
    inside = np.hypot(xx - 80, yy - 80) < 20  # more than 50 px from the motion edge
    # the inverse motion departs by about t^2 turn |v| = 2 px at the shutter's ends
    assert layered.region_mask(flow, 0.5)[inside].all()
    # noise of 0.1 px: its 3 x 3 spread (~0.4 px) times the reach (15 px) would pass a
    # gradient test, but it moves no reading position by anything like a pixel
    for moving in ((30.0, 0.0), (30.0, 0.0) + rng.normal(0.0, 0.1, flow.shape)):
        flow[~outside] = moving[~outside] if np.ndim(moving) == 3 else moving
        assert not layered.region_mask(flow.astype(np.float32), 0.5)[inside].any()


def test_inverse_departure_of_many_pixels():
    """layered_exposure._inverse_departure against a direct evaluation, for more pixels than
    one cv2.remap row may hold (2^15)."""
    from scipy.ndimage import map_coordinates

    h, w = 200, 220
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    v = np.stack([12 - (yy - 100) * 0.3, (xx - 110) * 0.3 + 0.01 * xx], -1).astype(np.float32)
    at = np.nonzero(np.ones((h, w), bool))
    got = layered._inverse_departure(v, 0.5, at)
    want = np.zeros(h * w)
    for t in (-0.5, 0.5):
        pos = [yy - v[..., 1] * t, xx - v[..., 0] * t]
        there = np.stack([map_coordinates(v[..., c], pos, order=1, mode="nearest")
                          for c in range(2)], -1)
        want = np.maximum(want, abs(t) * np.abs(there - v).max(axis=2).ravel())
    assert got.shape == (h * w,)
    np.testing.assert_allclose(got, want, atol=0.02)  # OpenCV's 1/32 px bilinear weights


def test_layer_ids_order_like_depth(crossing):
    sc, frame, truth, flow, depth, swept = crossing
    ids = np.where(depth < 10, 0, np.where(depth < 50, 1, 2)).astype(np.int32)
    np.testing.assert_array_equal(
        clblur.blur(frame, flow, "srgb", backend="numpy", depth=ids),
        clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth))


# ------------------------------------------------------- the gather where nothing occludes

def test_no_relative_motion_is_the_gather_bit_for_bit(rng):
    img = rng.integers(0, 256, (40, 52, 3), dtype=np.uint8)
    depth = rng.random((40, 52))
    flow = np.zeros((40, 52, 2), np.float32) + (6.5, -2.0)
    for motion in ((6.5, -2.0), flow):
        np.testing.assert_array_equal(
            clblur.blur(img, motion, "exp", backend="numpy", depth=depth),
            clblur.blur(img, motion, "exp", backend="numpy"))


def test_far_from_motion_boundaries_is_the_gather_bit_for_bit(disc):
    sc, frame, truth, flow, depth, swept = disc
    big = np.zeros((96, 160, 2), np.float32)
    big[:64, :96] = flow
    img = np.pad(frame, ((0, 32), (0, 64), (0, 0)), mode="reflect")
    dep = np.pad(depth, ((0, 32), (0, 64)), mode="edge")
    region = layered.boundary_mask(big, 0.5)
    assert region.any() and not region[:, -48:].any()
    got = clblur.blur(img, big, "srgb", backend="numpy", depth=dep)
    plain = clblur.blur(img, big, "srgb", backend="numpy")
    np.testing.assert_array_equal(got[~region], plain[~region])
    assert np.abs(got[region] - plain[region]).max() > 0.1


def test_boundary_mask_flags_only_tiles_near_relative_motion():
    v = np.zeros((80, 128, 2), np.float32) + (3.0, 1.0)
    assert not layered.boundary_mask(v, 0.5).any()
    v[30:40, 50:60] = (12.0, 1.0)  # reach 6 px: neighbour radius ceil(8 / 16) = 1 tile
    mask = layered.boundary_mask(v, 0.5)
    rows, cols = np.nonzero(mask)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (0, 63, 32, 79)


def test_split_coverage_fits_the_mixed_light(rng):
    front, behind = rng.uniform(0.05, 0.9, (2, 50, 3))
    a = rng.uniform(0, 1, 50)
    mixed = a[:, None] * front + (1 - a[:, None]) * behind
    got = layered.split_coverage(mixed, front, behind)
    contrast = np.sum((front - behind) ** 2, axis=1)
    # exact up to the pull of the prior towards 1/2, which fades with the contrast
    bound = layered.SPLIT_PRIOR * np.abs(0.5 - a) / (contrast + layered.SPLIT_PRIOR)
    assert np.all(np.abs(got - a) <= bound + 1e-12)
    # no contrast, or no unmixed pixel to compare with: half and half
    assert layered.split_coverage(mixed, behind, behind).tolist() == [0.5] * 50
    front[:3] = np.nan
    assert layered.split_coverage(mixed, front, behind)[:3].tolist() == [0.5] * 3
    # light outside the segment from B to F clips to a coverage in [0, 1]
    assert layered.split_coverage(2 * front - behind, front, behind)[3:].min() == 1.0


def test_layer_labels():
    assert layered.layer_labels(np.array([[3, 1], [1, 7]])).tolist() == [[1, 0], [0, 2]]
    d = np.array([1.0, 1.01, 1.02, 5.0, 5.02, 9.0])
    assert layered.layer_labels(d).tolist() == [0, 0, 0, 1, 1, 2]
    smooth = np.linspace(1.0, 2.0, 100)  # steps of 1 %: one surface
    assert layered.layer_labels(smooth).max() == 0
    strips = np.repeat(np.arange(1.0, 11.0), 3)[None].repeat(3, axis=0)  # 3 px wide each
    assert layered.layer_labels(strips).max() == layered.MAX_LAYERS - 1
    # a one-pixel strip between two surfaces is taken for their mixed pixels: it joins the
    # surface in front of it
    assert layered.layer_labels(np.array([[1.0, 1.0, 1.0, 5.0, 9.0, 9.0, 9.0]])).tolist() == \
        [[0, 0, 0, 0, 1, 1, 1]]
    assert layered.layer_labels(np.arange(10)).max() == layered.MAX_LAYERS - 1
    # the speed ordering keeps its own rule: gaps wider than GAP_FRACTION of the range
    speed = -np.array([0.0, 0.01, 0.02, 5.0, 5.02, 9.0])
    assert layered.layer_labels(speed, rule="speed").tolist() == [2, 2, 2, 1, 1, 0]


def _ground(scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A 64 x 80 Z pass: sky (+inf) above row 10, a ground plane below it (z = 100 / (y - 10):
    steps of up to 100 % between rows near the horizon, 2 % at the bottom) and a card in front
    of it (rows 20-40, columns 30-49, 0.7 times the depth of the ground just below it)."""
    y = np.arange(64, dtype=np.float64)[:, None] + np.zeros((1, 80))
    with np.errstate(divide="ignore"):
        z = np.where(y > 10, 100.0 / (y - 10), np.inf)
    card = np.zeros(z.shape, bool)
    card[20:41, 30:50] = True
    z[card] = 0.7 * 100.0 / 31
    return z * scale, card


def test_float_depth_separates_an_object_but_not_a_slanted_ground_plane():
    z, card = _ground()
    labels = layered.layer_labels(z)
    sky = ~np.isfinite(z)
    ground = ~sky & ~card
    assert np.unique(labels[card]).tolist() == [0]      # the card is nearest
    assert np.unique(labels[ground]).tolist() == [1]    # the whole plane is one surface
    assert np.unique(labels[sky]).tolist() == [2]       # the sky is farthest
    # a global gap rule would have cut the plane: its rows near the horizon differ by 100 %
    assert z[11, 0] / z[12, 0] == 2.0


def test_float_depth_layering_is_scale_invariant(rng):
    z, card = _ground()
    base = layered.layer_labels(z)
    for scale in (1e-3, 1000.0):
        np.testing.assert_array_equal(layered.layer_labels(z * scale), base)
    # objects at 1 and 2 in front of a background at 1000 (a renderer's Z pass) are three
    # layers whatever the units, and ordered as their depths are
    d = np.full((40, 60), 1000.0)
    d[5:20, 5:25], d[20:35, 30:55] = 2.0, 1.0
    for scale in (1.0, 1e-3, 1e3):
        lab = layered.layer_labels(d * scale)
        assert (lab[25, 40], lab[10, 10], lab[0, 0]) == (0, 1, 2)
    # mixed pixels between a disc and the background (an antialiased Z) join the disc
    yy, xx = np.mgrid[:40, :60]
    cover = np.clip(9.5 - np.hypot(yy - 20, xx - 30), 0, 1)
    soft = 1.0 / (cover / 2.0 + (1 - cover) / 10.0)  # inverse depths mix linearly
    lab = layered.layer_labels(soft)
    assert lab.max() == 1 and (lab[cover > 0] == 0).all()


def test_float_depth_keeps_at_most_max_layers():
    d = np.ones((30, 90))
    for i in range(9):  # nine cards at 1.5^i in front of one another's neighbours
        d[5:25, 10 * i:10 * i + 8] = 1.5 ** -i
    lab = layered.layer_labels(d)
    assert lab.max() == layered.MAX_LAYERS - 1
    from clblur.opencl.constants import LAYERED_MAXK  # what the kernels hold

    assert layered.MAX_LAYERS <= LAYERED_MAXK
    # order is kept: a nearer card never lands on a farther layer than a farther card
    cards = [int(lab[10, 10 * i]) for i in range(9)]
    assert cards == sorted(cards, reverse=True)


def test_bad_depth_is_refused():
    img = np.zeros((8, 9, 3), np.uint8)
    flow = np.zeros((8, 9, 2), np.float32)
    with pytest.raises(ValueError, match="depth has shape"):
        clblur.blur(img, flow, depth=np.zeros((9, 8)))
    with pytest.raises(ValueError, match="NaN"):
        clblur.blur(img, flow, depth=np.full((8, 9), np.nan))
    with pytest.raises(ValueError, match="<= 0"):
        clblur.blur(img, flow, depth=np.zeros((8, 9)))
    with pytest.raises(ValueError, match="-inf"):
        clblur.blur(img, flow, depth=np.full((8, 9), -np.inf))
    with pytest.raises(ValueError, match="<= 0"):
        layered.layer_labels(-np.ones((3, 3)))
    sky = np.full((8, 9), np.inf)  # +inf is the sky: accepted
    assert clblur.blur(img, flow, depth=sky).shape == img.shape
    with pytest.raises(TypeError, match="depth must be"):
        clblur.blur(img, flow, depth="far")
    with pytest.raises(ValueError, match="background"):
        clblur.blur(img, flow, background=img)
    with pytest.raises(ValueError, match="whole image"):
        plan = make_plan(img, flow, depth=np.ones((8, 9)), region=(0, 0, 10, 10))
        pipeline.run_numpy(plan, layered.integrate)


def test_video_layers_use_the_layered_integrator():
    from clblur.video import blur_frame

    sc = Scene((40, 64), (Disc((30.0, 20.0), 8.0, (12.0, 0.0), 5.0, 1),))
    frame = np.rint(SRGB.forward(sc.render(0.5)) * 255).astype(np.uint8)
    flow, _ = sc.maps()
    half = flow / 2
    got = blur_frame(frame, -flow, flow, "srgb", shutter=360, layers=True, backend="numpy")
    lin = reference.linearise(make_plan(frame, (0, 0), "srgb")).astype(np.float32)
    e = 0.5 * (layered.layered_half(lin, half, "end", backend="numpy").astype(np.float64)
               + layered.layered_half(lin, half, "start", backend="numpy"))
    expected = np.rint(np.clip(SRGB.forward(e), 0, 1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(got, expected)


# ------------------------------------------------------- parts of the region, built apart

def _two_corners(h: int = 160, w: int = 288, keep: tuple[int, ...] = (0, 1)):
    """Two textured discs in opposite corners over a static textured background."""
    yy, xx = np.mgrid[:h, :w]
    img = np.stack([np.sin(xx / 5.0 + c) * np.cos(yy / 7.0 - c) for c in range(3)], -1)
    img = ((img * 0.4 + 0.5) * 255).astype(np.uint8)
    flow, depth = np.zeros((h, w, 2), np.float32), np.full((h, w), 50.0)
    for i, (cx, cy, v, z) in enumerate(((30, 28, (12.0, 0.0), 5.0),
                                         (w - 34, h - 30, (-8.0, 6.0), 9.0))):
        if i in keep:
            inside = np.hypot(xx - cx, yy - cy) < 14
            img[inside] = 255 - img[inside]
            flow[inside], depth[inside] = v, z
    return img, flow, depth


def test_region_parts_split_far_pieces_and_keep_near_ones():
    img, flow, depth = _two_corners()
    region, r = layered.region_and_reach(flow, 0.5)
    parts = layered.region_parts(region, r)
    assert len(parts) == 2
    np.testing.assert_array_equal(parts[0] | parts[1], region)
    assert not (parts[0] & parts[1]).any() and parts[0][:40, :60].any()
    # pieces whose crops would overlap stay one part: the region itself
    near = np.zeros_like(region)
    near[20:30, 20:30] = near[20:30, 20 + 2 * layered.crop_margin(r):][:, :10] = True
    assert len(layered.region_parts(near, r)) == 1
    assert layered.region_parts(near, r)[0] is near


def test_layers_are_built_on_each_part_alone(monkeypatch):
    """Two objects in opposite corners: the layers are built on two small windows, not on
    the frame between them, and each object's blur is what the frame with it alone gives,
    bit for bit."""
    from clblur import layer_planes

    img, flow, depth = _two_corners()
    windows = []

    def spy(*args, **kwargs):
        layers = layer_planes.prepare(*args, **kwargs)
        windows.append(layers.region.size)
        return layers
    monkeypatch.setattr(layered, "prepare", spy)
    both = clblur.blur(img, flow, "srgb", backend="numpy", depth=depth)
    assert len(windows) == 2 and sum(windows) < 0.3 * flow.shape[0] * flow.shape[1]
    monkeypatch.undo()
    for keep, near in (((0,), np.s_[:80, :144]), ((1,), np.s_[80:, 144:])):
        one_img, one_flow, one_depth = _two_corners(keep=keep)
        alone = clblur.blur(one_img, one_flow, "srgb", backend="numpy", depth=one_depth)
        np.testing.assert_array_equal(both[near], alone[near])


# ----------------------------------------------------------------------------- pipeline

def test_reference_blur_is_the_pipeline(rng):
    img = rng.integers(0, 65536, (20, 30, 2), dtype=np.uint16)
    flow = (rng.normal(size=(20, 30, 2)) * 4).astype(np.float32)
    plan = make_plan(img, flow, "gamma:2.2", anchor="start")
    by_hand = reference.finish(reference.integrate(reference.linearise(plan), plan), plan)
    np.testing.assert_array_equal(reference.blur(plan), by_hand)
    np.testing.assert_array_equal(pipeline.run(plan), by_hand)


# -------------------------------------------------------------------------------- alpha

def opaque_square(dtype):
    img = np.zeros((24, 40, 4), np.float64)
    img[8:16, 10:18, :3] = (0.8, 0.45, 0.15)
    img[8:16, 10:18, 3] = 1.0
    if dtype == np.uint8:
        return np.rint(img * 255).astype(np.uint8)
    return img.astype(dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_alpha_is_coverage_blurred_linearly(dtype):
    img = opaque_square(dtype)
    full = 255.0 if dtype == np.uint8 else 1.0
    out = clblur.blur(img, (8, 0), "srgb", alpha=True, backend="numpy")
    a = img[..., 3] / full
    a_blur = clblur.blur(a, (8, 0), "linear", backend="numpy")
    lin = SRGB.inverse(img[..., :3] / full)
    if dtype == np.uint8:  # straight alpha: premultiply in linear light, un-premultiply after
        c_blur = clblur.blur(lin * a[..., None], (8, 0), "linear", backend="numpy")
        colour = np.where(a_blur[..., None] > 0,
                          SRGB.forward(c_blur / np.maximum(a_blur, 1e-300)[..., None]), 0)
        np.testing.assert_array_equal(out[..., 3], np.rint(a_blur * 255))
        np.testing.assert_array_equal(out[..., :3], np.rint(colour * 255))
        assert (out[12, 6:22, 0] == img[12, 12, 0]).all()  # the colour keeps its value
    else:  # premultiplied in, premultiplied out: the response of the light per coverage
        c_blur = clblur.blur(lin * a[..., None], (8, 0), "linear", backend="numpy")
        seen = a_blur[..., None] > 0
        colour = np.where(seen, SRGB.forward(c_blur / np.where(seen, a_blur[..., None], 1))
                          * a_blur[..., None], 0)
        np.testing.assert_allclose(out[..., 3], a_blur, atol=1e-6)
        np.testing.assert_allclose(out[..., :3], colour, atol=1e-6)
        # the colour keeps its value per unit coverage: never above the coverage
        covered = out[..., 3] > 1e-3
        np.testing.assert_allclose(out[..., 0][covered] / out[..., 3][covered], img[12, 12, 0],
                                   rtol=1e-5)
    assert 0 < out[12, 6, 3] < out[12, 12, 3]  # a linear ramp, no response applied


@pytest.mark.parametrize("spec", ["srgb", "gamma:2.2", "exp", "linear"])
def test_premultiplied_float_alpha_blurs_as_straight_integer_alpha(spec, rng):
    """A float RGBA image premultiplied in the response's domain (the EXR convention) and the
    same picture as straight-alpha uint16 are one scene: the gather and the layered path give
    the same premultiplied colour, within the uint16 output's rounding."""
    h, w = 24, 40
    straight = rng.integers(0, 65536, (h, w, 4)).astype(np.uint16)
    straight[..., 3] = 0
    straight[6:18, 8:22, 3] = rng.integers(20000, 65536, (12, 14))
    straight[8:16, 10:20, 3] = 65535
    a = straight[..., 3] / 65535.0
    premultiplied = np.concatenate([straight[..., :3] / 65535.0 * a[..., None], a[..., None]],
                                   axis=2).astype(np.float64)
    flow = np.zeros((h, w, 2), np.float32)
    flow[6:18, 8:22] = (9, 2)
    depth = np.where(flow[..., 0] > 0, 1.0, 2.0)
    for kw in ({}, {"depth": depth}):
        got = clblur.blur(premultiplied, flow, spec, alpha=True, backend="numpy", **kw)
        want = clblur.blur(straight, flow, spec, alpha=True, backend="numpy", **kw) / 65535.0
        want[..., :3] *= want[..., 3:]
        np.testing.assert_allclose(got, want, atol=3e-5, err_msg=f"{spec} {kw}")
        assert np.all(got[..., :3] <= got[..., 3:] + 1e-12) or spec == "linear"


# ------------------------------------------------------------------ OpenCL cross-checks

def agree(a: np.ndarray, b: np.ndarray) -> None:
    """The layered-path tolerance of docs/tolerances.md."""
    if a.dtype.kind == "u":
        d = np.abs(a.astype(np.int64) - b)
        assert d.max() <= 1 and (d > 0).mean() <= 0.02
    else:
        np.testing.assert_allclose(b, a, atol=2e-5, rtol=1e-5)


# where the layers' distance transforms and membrane fill run on the OpenCL path (both are
# held to the reference: clblur.opencl.layered.integrator, docs/tolerances.md)
BUILDS = pytest.mark.parametrize("build", ["host", "device"])


@BUILDS
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_opencl_layered_matches_the_reference(opencl, crossing, dtype, build, monkeypatch):
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", build)
    sc, frame, truth, flow, depth, swept = crossing
    img = frame.astype(dtype) if dtype == np.float32 else \
        np.rint(frame * np.iinfo(dtype).max).astype(dtype)
    for opts in (dict(), dict(anchor="start", samples=9),
                 dict(background=img[::-1].copy(), weights=[1, 2, 3, 2, 1])):
        ref = clblur.blur(img, flow, "srgb", backend="numpy", depth=depth, **opts)
        got = clblur.blur(img, flow, "srgb", backend="opencl", depth=depth, **opts)
        agree(ref, got)
        plain = clblur.blur(img, flow, "srgb", backend="opencl",
                            **{k: v for k, v in opts.items() if k != "background"})
        region = layered.boundary_mask(flow, 0.0 if opts.get("anchor") == "start" else 0.5)
        np.testing.assert_array_equal(got[~region], plain[~region])


@BUILDS
def test_opencl_builds_the_parts_apart_as_the_reference(opencl, build, monkeypatch):
    """The device integrator cuts the region into the same parts and returns every part's
    pixels (two objects in opposite corners)."""
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", build)
    img, flow, depth = _two_corners()
    ref = clblur.blur(img, flow, "srgb", backend="numpy", depth=depth)
    got = clblur.blur(img, flow, "srgb", backend="opencl", depth=depth)
    agree(ref, got)
    plain = clblur.blur(img, flow, "srgb", backend="opencl")
    region = layered.boundary_mask(flow, 0.5)
    for corner in (np.s_[:80, :144], np.s_[80:, 144:]):  # both parts were layered
        assert (got[corner] != plain[corner]).any()
    np.testing.assert_array_equal(got[~region], plain[~region])


@BUILDS
@pytest.mark.parametrize("plate", [False, True])
def test_a_rearmost_surface_of_mixed_pixels_only_is_no_layer(opencl, build, plate,
                                                             monkeypatch):
    """A far surface at most 2 px wide (a wire, a pole) has only mixed pixels: they all join
    the layers in front, and nothing is left at or behind it.  Both builds skip it as the
    reference does (the device's nearest transform used to be asked for a transform with no
    pixel to be nearest to and refused the blur)."""
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", build)
    rng = np.random.default_rng(3)
    h, w = 48, 64
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    flow = np.zeros((h, w, 2), np.float32)
    depth = np.full((h, w), 5.0)
    depth[:, 30:32] = 50.0  # the rearmost surface: a 2 px line
    depth[20:32, 33:35] = 80.0  # and a second one behind it, as thin
    depth[10:30, 10:25] = 1.0  # a moving object in front
    flow[10:30, 10:25] = (6.0, 0.0)
    labels = layered.layer_labels(depth)
    assert labels.max() == 3  # four surfaces before the mixed pixels are split
    opts = dict(background=img[::-1].copy()) if plate else {}
    ref = clblur.blur(img, flow, "srgb", backend="numpy", depth=depth, **opts)
    got = clblur.blur(img, flow, "srgb", backend="opencl", depth=depth, **opts)
    agree(ref, got)
    # the layered path ran: the object's light lands on the background beyond its silhouette
    plain = clblur.blur(img, flow, "srgb", backend="numpy")
    assert not np.array_equal(ref[10:30, 25:31], plain[10:30, 25:31])


def _random_scene(rng: np.random.Generator) -> tuple:
    """A small random layered scene: sides from 1 px, 1, 3 or 4 channels, surfaces of every
    width down to one pixel (some turning), sky, float depth, layer IDs, speed or departure
    order, and the call's options.  Returns (image, flow, order, response, options)."""
    h, w = int(rng.choice([1, 2, 3, 5, 8, 17, 33, 48])), int(rng.choice([1, 2, 5, 17, 64]))
    c = int(rng.choice([1, 3, 4]))
    dtype = rng.choice([np.uint8, np.uint16, np.float32])
    img = rng.random((h, w, c)).astype(np.float32) if dtype == np.float32 else \
        rng.integers(0, np.iinfo(dtype).max + 1, (h, w, c)).astype(dtype)
    flow = np.zeros((h, w, 2), np.float32)
    depth = np.full((h, w), rng.uniform(1, 100))
    if rng.random() < 0.2:
        depth[:, :max(1, w // 3)] = np.inf  # sky
    for _ in range(rng.integers(0, 5)):
        (r0, r1), (c0, c1) = sorted(rng.integers(0, h + 1, 2)), sorted(rng.integers(0, w + 1, 2))
        if rng.random() < 0.3:  # a line 1 or 2 px wide
            c1 = min(c0 + int(rng.integers(1, 3)), w)
        depth[r0:r1, c0:c1] = rng.uniform(0.5, 200)
        flow[r0:r1, c0:c1] = rng.normal(0, 8, 2)
        if rng.random() < 0.3:  # turning
            yy, xx = np.mgrid[r0:r1, c0:c1]
            flow[r0:r1, c0:c1, 0] += 0.2 * (yy - (r0 + r1) / 2)
            flow[r0:r1, c0:c1, 1] -= 0.2 * (xx - (c0 + c1) / 2)
    flow += rng.normal(0, rng.choice([0.0, 0.7]), flow.shape).astype(np.float32)
    opts = {}
    if rng.random() < 0.3:
        opts["anchor"] = str(rng.choice(["start", "center", "end"]))
    if rng.random() < 0.2:
        opts["samples"] = int(rng.integers(1, 12))
    elif rng.random() < 0.15:
        opts["exposure"] = "continuous"
    if rng.random() < 0.15:
        opts["background"] = img[::-1].copy()
    order = [depth, "speed", "departure", np.where(np.isinf(depth), 9, depth).astype(np.int64) % 4][
        int(rng.choice(4, p=[0.6, 0.15, 0.15, 0.1]))]
    return img, flow, order, str(rng.choice(["srgb", "linear", "exp"])), opts


@BUILDS
def test_random_small_scenes_build_and_match_the_reference(opencl, build, monkeypatch):
    """Small random scenes (``_random_scene``): every one blurs on both backends, within the
    tolerance (at most 1 code; the share of such codes is no test on images of a few
    pixels).  Before the empty-layer fix 14 of these 60 refused the blur on the device."""
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", build)
    for seed in range(60):
        img, flow, order, resp, opts = _random_scene(np.random.default_rng(seed))
        ref = clblur.blur(img, flow, resp, backend="numpy", depth=order, **opts)
        got = clblur.blur(img, flow, resp, backend="opencl", depth=order, **opts)
        if img.dtype.kind == "u":
            assert np.abs(ref.astype(np.int64) - got).max() <= 1, seed
        else:
            np.testing.assert_allclose(got, ref, atol=2e-5, rtol=1e-5, err_msg=str(seed))


def agree_straight(a: np.ndarray, b: np.ndarray) -> None:
    """The straight-alpha tolerance of docs/tolerances.md: coverage within 1 code, colour
    times coverage (what composites over anything) within 2 codes; the colour alone is the
    premultiplied light divided by the coverage, which scales its float32 rounding by
    1 / coverage (21 codes of a uint16 pixel at coverage 1 / 65535)."""
    m = np.iinfo(a.dtype).max
    a, b = a.astype(np.int64), b.astype(np.int64)
    assert np.abs(a[..., -1] - b[..., -1]).max() <= 1
    assert np.abs(a[..., :-1] * (a[..., -1:] / m) - b[..., :-1] * (b[..., -1:] / m)).max() <= 2


@BUILDS
def test_random_small_scenes_with_alpha_match_the_reference(opencl, build, monkeypatch):
    """``_random_scene`` with a coverage channel (0, 1 and anything between), as straight
    alpha (integer images) or premultiplied (float images), on both backends."""
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", build)
    for seed in range(60):
        rng = np.random.default_rng(seed)
        img, flow, order, resp, opts = _random_scene(rng)
        opts.pop("background", None)
        cover = rng.random(img.shape[:2])
        cover[rng.random(cover.shape) < 0.3] = 0.0
        cover[rng.random(cover.shape) < 0.3] = 1.0
        colour = (img if img.ndim == 3 else img[..., None])[..., :3]
        if img.dtype == np.float32:
            img = np.concatenate([colour * cover[..., None], cover[..., None]], axis=2)
            img = img.astype(np.float32)
        else:
            code = np.rint(cover * np.iinfo(img.dtype).max).astype(img.dtype)
            img = np.concatenate([colour, code[..., None]], axis=2)
        ref = clblur.blur(img, flow, resp, backend="numpy", depth=order, alpha=True, **opts)
        got = clblur.blur(img, flow, resp, backend="opencl", depth=order, alpha=True, **opts)
        if img.dtype.kind == "u":
            agree_straight(ref, got)
        else:
            np.testing.assert_allclose(got, ref, atol=2e-5, rtol=1e-5, err_msg=str(seed))


def test_a_transparent_pixel_has_no_colour():
    """Straight alpha: where the blurred coverage rounds to code 0 the colour is 0, whatever
    residue the sums left in the coverage (the backends' residues differ)."""
    from clblur.reference import finish
    from clblur.request import make_plan

    img = np.zeros((1, 3, 4), np.uint8)
    plan = make_plan(img, (0.0, 0.0), "srgb", alpha=True)
    acc = np.zeros((1, 3, 4))
    acc[0, :, 3] = [1e-9, 0.49 / 255, 0.51 / 255]  # a residue, under and over half a code
    acc[0, :, :3] = 0.5 * acc[0, :, 3:]  # premultiplied light: mid-grey where it is seen
    out = finish(acc, plan)
    assert out[0, :2].tolist() == [[0, 0, 0, 0], [0, 0, 0, 0]]
    assert out[0, 2, 3] == 1 and out[0, 2, :3].max() > 0


@BUILDS
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_opencl_turning_layers_match_the_reference(opencl, spinning, dtype, build, monkeypatch):
    """The inverse motion of warped layers (layered.cl inverse_motion) on the device."""
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", build)
    r = spinning
    img = r.sharp if dtype == np.uint8 else (r.sharp / 255.0).astype(np.float32)
    for opts in (dict(), dict(anchor="end", samples=11)):
        ref = clblur.blur(img, r.flow, "srgb", backend="numpy", depth=r.depth, **opts)
        got = clblur.blur(img, r.flow, "srgb", backend="opencl", depth=r.depth, **opts)
        agree(ref, got)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_opencl_alpha_matches_the_reference(opencl, dtype):
    img = opaque_square(dtype)
    ref = clblur.blur(img, (8, 3), "srgb", alpha=True, backend="numpy")
    got = clblur.blur(img, (8, 3), "srgb", alpha=True, backend="opencl")
    agree(ref, got)
    flow = np.zeros((24, 40, 2), np.float32)
    flow[6:18, 8:20] = (9, 0)
    depth = np.where(flow[..., 0] > 0, 1.0, 2.0)
    agree(clblur.blur(img, flow, "srgb", alpha=True, depth=depth, backend="numpy"),
          clblur.blur(img, flow, "srgb", alpha=True, depth=depth, backend="opencl"))


# --------------------------------------------------------------------------- command line

def test_command_line_depth_and_alpha(tmp_path, capsys):
    from clblur.cli import main
    from clblur.io import read_image, write_image

    sc = scenes()["disc"]
    img = np.rint(SRGB.forward(sc.render(0.5)) * 255).astype(np.uint8)
    flow, depth = sc.maps()
    write_image(tmp_path / "in.png", img)
    np.save(tmp_path / "flow.npy", flow)
    np.save(tmp_path / "depth.npy", depth)
    common = ["--flow", str(tmp_path / "flow.npy"), "--response", "srgb", "--backend", "numpy"]
    assert main(["blur", str(tmp_path / "in.png"), str(tmp_path / "out.png"), *common,
                 "--depth", str(tmp_path / "depth.npy")]) == 0
    np.testing.assert_array_equal(
        read_image(tmp_path / "out.png"),
        clblur.blur(img, flow, "srgb", backend="numpy", depth=depth))
    for name in ("speed", "departure"):  # orderings computed from the flow, not files
        assert main(["blur", str(tmp_path / "in.png"), str(tmp_path / f"{name}.png"), *common,
                     "--depth", name]) == 0
        np.testing.assert_array_equal(
            read_image(tmp_path / f"{name}.png"),
            clblur.blur(img, flow, "srgb", backend="numpy", depth=name))
    rgba = np.dstack([img, np.full(img.shape[:2], 255, np.uint8)])
    rgba[:20, :, 3] = 0
    write_image(tmp_path / "rgba.png", rgba)
    assert main(["blur", str(tmp_path / "rgba.png"), str(tmp_path / "o.png"), *common]) == 0
    np.testing.assert_array_equal(
        read_image(tmp_path / "o.png"),
        clblur.blur(rgba, flow, "srgb", backend="numpy", alpha=True))
    assert main(["blur", str(tmp_path / "in.png"), str(tmp_path / "x.png"), *common,
                 "--depth", str(tmp_path / "flow.npy")]) == 2
    assert "depth has shape" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
    # one displacement for every pixel occludes nothing: a depth with it is refused, not
    # ignored without a word (the library computes the gather, which is then exact)
    np.save(tmp_path / "kernel.npy", np.full((1, 5), 0.2))
    for motion in (["--motion=4,1"], ["--psf", str(tmp_path / "kernel.npy")]):
        for order in (str(tmp_path / "depth.npy"), "speed"):
            assert main(["blur", str(tmp_path / "in.png"), str(tmp_path / "x.png"), *motion,
                         "--backend", "numpy", "--depth", order]) == 2
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and motion[0][:6] in err and "--flow" in err, err
            assert not (tmp_path / "x.png").exists()
    np.testing.assert_array_equal(clblur.blur(img, (4.0, 1.0), "srgb", backend="numpy",
                                              depth=depth),
                                  clblur.blur(img, (4.0, 1.0), "srgb", backend="numpy"))


def test_opencl_cpu_layout_is_the_one_pixel_kernel_bit_for_bit(opencl, crossing):
    """composite_lanes (8 pixels of a row per work-item) against composite_layers, on
    non-rigid layers (varying vectors), a clean plate, time weights, a start anchor and the
    continuous exposure; and both against the reference."""
    from clblur.layer_planes import prepare
    from clblur.opencl.layered import composite

    sc, frame, truth, flow, depth, swept = crossing
    h, w = depth.shape
    yy, xx = np.mgrid[0:h, 0:w]
    bend = np.stack([np.sin(yy / 9.0), np.cos(xx / 7.0)], -1).astype(np.float32)
    flow = flow + bend * (depth < np.max(depth))[..., None]
    lin = SRGB.inverse(frame)
    for anchor, samples, weights, plate, ends in (
            (0.5, None, None, None, False),
            (0.0, 5, np.array([1, 2, 3, 2, 1]) / 9.0, lin[::-1].copy(), False),
            (0.5, None, None, None, True)):  # the continuous exposure's half-weight ends
        region = layered.region_mask(flow, anchor)
        layers = prepare(lin, flow, depth, anchor, region, plate)
        one = composite(layers, anchor, samples, weights, (h, w), lanes=False, ends=ends)
        eight = composite(layers, anchor, samples, weights, (h, w), lanes=True, ends=ends)
        assert one.shape == (region.sum(), 3)
        np.testing.assert_array_equal(eight, one)
        ref = layered.composite(layers, anchor, samples, weights, (h, w), ends)[layers.region]
        np.testing.assert_allclose(one, ref, atol=2e-5, rtol=1e-5)


def test_opencl_own_counts_are_the_hosts(opencl, crossing, spinning, monkeypatch):
    """Both compositing kernels counting samples themselves (counts.cl) give the bits of the
    host's counts (clblur.layered_exposure.counts), on rigid and turning layers, lengths just
    off integers included; the counts matter (one sample fewer changes the result)."""
    from clblur.layer_planes import prepare
    from clblur.opencl import runtime
    from clblur.opencl.layered import composite

    if not runtime().fp64:
        pytest.skip("the device has no fp64: the host counts")
    sc, frame, truth, flow, depth, swept = crossing
    r = spinning
    near_integer = flow * np.float32(1 + 3e-7)  # |v| a hair beyond an integer length
    cases = [(SRGB.inverse(frame), flow, depth), (SRGB.inverse(frame), near_integer, depth),
             (SRGB.inverse(r.sharp / 255.0), r.flow, r.depth)]
    for lin, v, d in cases:
        region = layered.region_mask(v, 0.5)
        layers = prepare(lin, v, d, 0.5, region)
        for lanes in (False, True):
            kw = dict(lanes=lanes)
            own = composite(layers, 0.5, None, None, d.shape, own_counts=True, **kw)
            host = composite(layers, 0.5, None, None, d.shape, own_counts=False, **kw)
            np.testing.assert_array_equal(own, host)
    fewer = layered.counts(layers, None, np.nonzero(layers.region)) - 1
    monkeypatch.setattr(layered, "counts", lambda *a, **k: fewer)
    for lanes in (False, True):
        short = composite(layers, 0.5, None, None, d.shape, own_counts=False, lanes=lanes)
        assert not np.array_equal(short, own)


def test_distance_to_is_scipys_transform_bit_for_bit():
    from scipy.ndimage import distance_transform_edt

    from clblur.layer_planes import distance_to

    rng = np.random.default_rng(7)
    for density in (0.0005, 0.02, 0.4):
        inside = rng.random((97, 131)) < density
        inside[50, 60] = True
        want = distance_transform_edt(~inside)
        np.testing.assert_array_equal(distance_to(inside), want)
        at = np.nonzero(rng.random(inside.shape) < 0.3)
        np.testing.assert_array_equal(distance_to(inside, at), want[at])


def test_nearest_pixel_is_a_nearest_pixel(monkeypatch):
    """layer_planes._nearest_pixel gives a nearest ``inside`` pixel, as far as a whole-array
    distance transform's, by each of its routes: the lookup under 4 px, distances to every
    pixel of a sparse ``inside``, and the transform of a box around the pixels left (ties
    picked as the whole transform picks them)."""
    from scipy.ndimage import distance_transform_edt

    from clblur import layer_planes

    rng = np.random.default_rng(5)
    for brute in (1 << 21, 0):  # the pairs route where it fits, then never
        monkeypatch.setattr(layer_planes, "_BRUTE_PAIRS", brute)
        far_seen = 0
        for case in range(60):
            h, w = rng.integers(5, 90, 2)
            if case % 2:  # a sparse grid: many pixels with several nearest ones, far apart
                inside = np.zeros((h, w), bool)
                inside[rng.integers(0, 4)::rng.integers(5, 25),
                       rng.integers(0, 4)::rng.integers(5, 25)] = True
            else:
                inside = rng.random((h, w)) < rng.choice([0.003, 0.03, 0.3])
            inside[rng.integers(h), rng.integers(w)] = True
            at = (rng.random((h, w)) < 0.2) & ~inside
            dist, idx = distance_transform_edt(~inside, return_indices=True)
            ys, xs = np.nonzero(at)
            ry, rx = layer_planes._nearest_pixel(inside, at)
            assert inside[ry, rx].all()
            np.testing.assert_allclose(np.hypot(ry - ys, rx - xs), dist[at], rtol=1e-12)
            far = dist[at] >= 4.0
            far_seen += int(far.sum())
            # under 4 px: the first offset of the lookup's order that lands inside, a pixel
            # at a time (the lookup visits only the pixels that have one, a few at a time)
            for i in np.flatnonzero(~far)[:200]:
                first = next((ys[i] + dy, xs[i] + dx) for dy, dx in layer_planes._NEAR
                             if 0 <= ys[i] + dy < h and 0 <= xs[i] + dx < w
                             and inside[ys[i] + dy, xs[i] + dx])
                assert (ry[i], rx[i]) == first
            if not brute:
                np.testing.assert_array_equal(ry[far], idx[0][at][far])
                np.testing.assert_array_equal(rx[far], idx[1][at][far])
        assert far_seen > 100


def test_sliver_merge_numbers_the_surfaces_as_unique_does(monkeypatch):
    """depth_components renumbers the components left after slivers merge 0..n-1 in the
    order of the components they merged into (np.unique's inverse), without sorting every
    pixel."""
    from clblur import layering

    targets = []

    def recorded(*args):
        targets.append(real(*args))
        return targets[-1]
    real = layering.sliver_targets
    monkeypatch.setattr(layering, "sliver_targets", recorded)
    rng = np.random.default_rng(9)
    merged = 0
    for _ in range(40):
        h, w = rng.integers(4, 40, 2)
        blocks = rng.choice([1.0, 3.0, 9.0, np.inf], size=(h // 3 + 1, w // 3 + 1))
        depth = np.kron(blocks, np.ones((3, 3)))[:h, :w]
        depth = np.where(rng.random((h, w)) < 0.15, rng.choice([1.5, 4.0, 20.0], (h, w)), depth)
        targets.clear()
        comp, n = layering.depth_components(depth)
        if not targets:
            continue  # no sliver
        wi = layering._inverse_depth(depth)
        _, raw = layering._components(layering._continuous(wi, 1), layering._continuous(wi, 0))
        uniq, want = np.unique(targets[0][raw], return_inverse=True)
        assert comp.dtype == np.int32 and n == uniq.size
        np.testing.assert_array_equal(comp, want.reshape(h, w))
        merged += int(uniq.size < targets[0].size)
    assert merged > 5


def test_grid_components_number_as_scipy_does():
    """layering._components (OpenCV on a twice-as-fine grid) against the sparse graph."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from clblur.layering import _components

    rng = np.random.default_rng(11)
    for h, w, p in ((1, 1, 0.5), (1, 9, 0.5), (7, 1, 0.5), (40, 57, 0.6), (63, 35, 0.95)):
        right, down = rng.random((h, w - 1)) < p, rng.random((h - 1, w)) < p
        idx = np.arange(h * w).reshape(h, w)
        rows = np.concatenate([idx[:, :-1][right], idx[:-1, :][down]])
        cols = np.concatenate([idx[:, 1:][right], idx[1:, :][down]])
        graph = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(h * w,) * 2)
        n, comp = connected_components(graph, directed=False)
        got_n, got = _components(right, down)
        assert got_n == n
        np.testing.assert_array_equal(got, comp.reshape(h, w))


def test_harmonic_fill_fills_holes_within_the_known_range(rng):
    """The hidden-light fill: known pixels untouched, a constant stays constant, a ramp is
    followed across a hole, and every filled value is a convex combination of known ones
    (every step averages with non-negative weights)."""
    from clblur.layer_planes import harmonic_fill

    h, w = 61, 90
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    known = np.ones((h, w), bool)
    known[20:45, 30:70] = False  # a hole
    known[0:3, 0:5] = False  # and one at a corner
    ramp = np.stack([xx / w, 0.25 + yy / (2 * h), np.full((h, w), 0.4, np.float32)], axis=2)
    noisy = ramp + rng.normal(0, 0.01, ramp.shape).astype(np.float32)
    filled = harmonic_fill(noisy, known)
    assert filled.dtype == np.float32 and filled.shape == noisy.shape
    np.testing.assert_array_equal(filled[known], noisy[known])
    for c in range(3):
        lo, hi = noisy[..., c][known].min(), noisy[..., c][known].max()
        assert lo <= filled[..., c][~known].min() and filled[..., c][~known].max() <= hi
    np.testing.assert_allclose(harmonic_fill(ramp[..., 2:], known), 0.4, rtol=1e-6)
    # across the 40 x 25 px hole the fill follows the ramp (measured: off by at most 0.023,
    # the corner hole included; the pull-push estimate alone bends towards the hole's mean,
    # 0.06), far closer than the nearest known pixel does (0.14)
    from scipy.ndimage import distance_transform_edt

    rows, cols = distance_transform_edt(~known, return_indices=True)[1]
    nearest = noisy[rows, cols]
    off = np.abs(filled - ramp)[~known].max()
    assert off < 0.03 and off < 0.25 * np.abs(nearest - ramp)[~known].max()
    one = harmonic_fill(noisy[..., :1], known)  # a single channel keeps its axis
    np.testing.assert_allclose(one, filled[..., :1], rtol=1e-6, atol=1e-7)


def test_layer_build_is_checked(opencl, monkeypatch):
    """A layer build other than auto, device or host is a one-line error, not a silent host."""
    from clblur.opencl.layered import integrator

    monkeypatch.setenv("CLBLUR_LAYER_BUILD", "gpu")
    with pytest.raises(ValueError, match="CLBLUR_LAYER_BUILD"):
        integrator()
    assert integrator(build="host") is not None


def test_device_layer_build_runs_the_device_transforms(opencl, crossing, monkeypatch):
    """With build="device", and by default on any device, the region, the labels and the
    layers' transforms run on the device (not silently on the host), and the result is the
    host build's within the layered tolerance."""
    from clblur.opencl import fill, labels, nearest, region

    sc, frame, truth, flow, depth, swept = crossing
    calls = []
    for module, name in ((nearest, "nearest_transform"), (nearest, "distance"),
                         (fill, "harmonic_fill"), (region, "region_and_reach"),
                         (labels, "layer_labels")):
        real = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _r=real, _n=name, **k: (calls.append(_n),
                                                                           _r(*a, **k))[1])
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", "host")
    host = clblur.blur(frame, flow, "srgb", backend="opencl", depth=depth)
    assert not calls
    monkeypatch.setenv("CLBLUR_LAYER_BUILD", "device")
    dev = clblur.blur(frame, flow, "srgb", backend="opencl", depth=depth)
    on_device = {"nearest_transform", "distance", "harmonic_fill", "region_and_reach",
                 "layer_labels"}
    assert on_device <= set(calls)
    agree(host, dev)
    calls.clear()
    monkeypatch.delenv("CLBLUR_LAYER_BUILD")
    default = clblur.blur(frame, flow, "srgb", backend="opencl", depth=depth)
    assert on_device <= set(calls)
    np.testing.assert_array_equal(default, dev)


# ------------------------------------------------------------- curved paths of one frame

@pytest.fixture(scope="module")
def star():
    """clblur.scenes' star_leaving (turns 34 degrees and accelerates) at K = 48."""
    from clblur import scenes as rendered

    scene = rendered.example_scenes(160, 112)["star_leaving"]
    return rendered.render(scene, "srgb", np.uint8, samples=48)


def test_a_curved_path_without_a_bend_is_the_straight_chord(crossing):
    """Equal halves have no quadratic term: the curved path is the layered blur along the
    chord, bit for bit."""
    from clblur.vectors import blur_bent

    sc, frame, truth, flow, depth, swept = crossing
    half = flow / 2
    np.testing.assert_array_equal(
        blur_bent(frame, half, half, "srgb", backend="numpy", layers=True, depth=depth,
                  curved=True),
        clblur.blur(frame, flow, "srgb", backend="numpy", depth=depth))


def test_a_curved_gather_is_the_mean_along_the_parabola(rng):
    """One surface that accelerates (no ordering): every sample along ``p - D t - C t^2``,
    averaged in linear light, against a direct evaluation of that sum."""
    from clblur.reference import bilinear_at
    from clblur.vectors import blur_bent

    h, w = 40, 56
    img = rng.random((h, w, 3)).astype(np.float32)
    first = np.broadcast_to(np.float32([2.0, 1.0]), (h, w, 2))  # slow, then fast
    second = np.broadcast_to(np.float32([7.0, -2.0]), (h, w, 2))
    got = blur_bent(img, first, second, "linear", backend="numpy", curved=True)
    d = first[0, 0].astype(np.float64) + second[0, 0]
    c = 2.0 * (second[0, 0].astype(np.float64) - first[0, 0])
    n = int(np.ceil(np.hypot(*d) + np.hypot(*c) / 2)) + 1
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    want = np.zeros((h, w, 3))
    for j in range(n):
        t = j / (n - 1) - 0.5
        want += bilinear_at(img.astype(np.float64), xx - d[0] * t - c[0] * t * t,
                            yy - d[1] * t - c[1] * t * t, (0, 0), (h, w)) / n
    np.testing.assert_allclose(got, want, atol=2e-6)
    # the path passes the halves' ends: two straight halves end where the curve does
    straight = blur_bent(img, first, second, "linear", backend="numpy")
    assert np.abs(got - straight).max() > 0.05  # ... but not along the same points


def test_a_curved_path_follows_a_turning_accelerating_star(star):
    """From one frame and its depth, the parabola through the halves' points follows the
    star's arcs better than two straight halves (the full-size scene of
    docs/studies/occlusion.md: 37.4 -> 40.4 dB over the swept region)."""
    from clblur.vectors import blur_bent

    r = star
    opts = dict(backend="numpy", layers=True, depth=r.depth)
    two = psnr(blur_bent(r.sharp, r.flow_first, r.flow_second, "srgb", **opts) / 255.0,
               r.image / 255.0, r.swept)
    curved = psnr(blur_bent(r.sharp, r.flow_first, r.flow_second, "srgb", curved=True,
                            **opts) / 255.0, r.image / 255.0, r.swept)
    assert curved > two + 1.5


@BUILDS
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_opencl_curved_path_matches_the_reference(opencl, star, dtype, build, monkeypatch):
    from clblur.vectors import blur_bent

    monkeypatch.setenv("CLBLUR_LAYER_BUILD", build)
    r = star
    img = r.sharp if dtype == np.uint8 else (r.sharp / 255.0).astype(np.float32)
    for opts in (dict(layers=True, depth=r.depth), dict(), dict(layers=True, samples=9)):
        ref = blur_bent(img, r.flow_first, r.flow_second, "srgb", curved=True,
                        backend="numpy", **opts)
        got = blur_bent(img, r.flow_first, r.flow_second, "srgb", curved=True,
                        backend="opencl", **opts)
        agree(ref, got)


def test_command_line_curved_path_of_a_vector_pass(tmp_path, star, capsys):
    from clblur.cli import main
    from clblur.io import read_image, write_image
    from clblur.vectors import blur_bent, from_blender, to_blender

    r = star
    write_image(tmp_path / "in.png", r.sharp)
    np.save(tmp_path / "vec.npy", to_blender(2 * r.flow_first, 2 * r.flow_second))
    np.save(tmp_path / "depth.npy", r.depth)
    common = ["--flow", str(tmp_path / "vec.npy"), "--vectors", "blender",
              "--vector-shutter", "1", "--response", "srgb", "--backend", "numpy"]
    first, second = from_blender(to_blender(2 * r.flow_first, 2 * r.flow_second), 1.0,
                                 bent=True)
    for path in ("bent", "curved"):
        assert main(["blur", str(tmp_path / "in.png"), str(tmp_path / f"{path}.png"), *common,
                     "--path", path, "--depth", str(tmp_path / "depth.npy")]) == 0
        np.testing.assert_array_equal(
            read_image(tmp_path / f"{path}.png"),
            blur_bent(r.sharp, first, second, "srgb", backend="numpy", layers=True,
                      depth=r.depth, curved=path == "curved"))
    capsys.readouterr()
    np.save(tmp_path / "flow.npy", r.flow)
    for extra, message in ((["--flow", str(tmp_path / "flow.npy")], "--vectors blender or nuke"),
                           (common[:6] + ["--anchor", "end"], "anchored at its bend")):
        assert main(["blur", str(tmp_path / "in.png"), str(tmp_path / "x.png"), *extra,
                     "--path", "curved"]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.png").exists()


def test_a_curved_path_checks_its_halves():
    from clblur.video import blur_curved

    img = np.zeros((10, 12, 3), np.uint8)
    ok = np.zeros((10, 12, 2), np.float32)
    with pytest.raises(ValueError, match=r"second half flow has shape \(10, 11, 2\)"):
        blur_curved(img, ok, np.zeros((10, 11, 2)), backend="numpy")
    with pytest.raises(ValueError, match="first half flow contains NaN"):
        blur_curved(img, np.full_like(ok, np.nan), ok, backend="numpy")
