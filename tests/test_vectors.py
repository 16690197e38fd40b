"""Renderer vector conventions (clblur.vectors): Blender and Nuke passes -> clblur's flow."""

from __future__ import annotations

import numpy as np
import pytest

import clblur
from clblur import scenes, vectors
from clblur.scenes import Background, Disc, Scene, SceneObject, wave_texture

H, W = 48, 80
PREV = (10.0, -4.0)  # content displacement previous -> current frame, x right, y down
NEXT = (14.0, 2.0)   # current -> next frame


def _disc_mask() -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return np.hypot(xx - 40.0, yy - 24.0) <= 12


def _blender_pass_by_hand() -> np.ndarray:
    """A Blender Vector pass written from its definition (Cycles primitive_motion_vector):
    (X, Y) = P_prev - P_cur, (Z, W) = P_cur - P_next in raster axes with y UP.  The disc's
    centre is at y_down = 24 now; in y-up raster coordinates y_up = H - 1 - y_down."""
    def up(p):
        return np.array([p[0], H - 1 - p[1]])

    cur = np.array([40.0, 24.0])
    prev = cur - PREV
    nxt = cur + NEXT
    xy = up(prev) - up(cur)
    zw = up(cur) - up(nxt)
    out = np.zeros((H, W, 4), np.float32)
    out[_disc_mask()] = [xy[0], xy[1], zw[0], zw[1]]
    return out


def test_blender_signs_from_the_definition():
    d_prev, d_next = vectors.blender_displacements(_blender_pass_by_hand())
    m = _disc_mask()
    np.testing.assert_allclose(d_prev[m], np.broadcast_to(PREV, d_prev[m].shape))
    np.testing.assert_allclose(d_next[m], np.broadcast_to(NEXT, d_next[m].shape))
    assert not d_prev[~m].any()
    # moving right and up between the previous frame and now: X < 0 (right), Y < 0 (up)
    v = _blender_pass_by_hand()[24, 40]
    assert v[0] < 0 and v[1] < 0
    np.testing.assert_allclose(vectors.to_blender(d_prev, d_next), _blender_pass_by_hand())


def test_nuke_signs_from_the_definition():
    """Nuke: forward(p) = where p's content will be next frame minus p, backward(p) = where it
    was, in y-up axes."""
    m = _disc_mask()
    fwd = np.zeros((H, W, 2), np.float32)
    bwd = np.zeros((H, W, 2), np.float32)
    fwd[m] = [NEXT[0], -NEXT[1]]
    bwd[m] = [-PREV[0], PREV[1]]
    d_prev, d_next = vectors.nuke_displacements(fwd, bwd)
    np.testing.assert_allclose(d_prev[m][0], PREV)
    np.testing.assert_allclose(d_next[m][0], NEXT)
    # one missing layer mirrors the other (constant velocity)
    p2, n2 = vectors.nuke_displacements(forward=fwd)
    np.testing.assert_allclose(p2, n2)
    f3, b3 = vectors.to_nuke(d_prev, d_next)
    np.testing.assert_allclose(f3, fwd)
    np.testing.assert_allclose(b3, bwd)
    np.testing.assert_allclose(vectors.from_nuke(fwd, bwd, 0.5),
                               vectors.from_blender(_blender_pass_by_hand(), 0.5))


@pytest.mark.parametrize("shutter", [0.5, 1.0])
def test_blender_pass_blurs_like_the_renderers_clblur_flow(shutter):
    """A rendered disc moving at a constant per-frame velocity: its Blender vector pass,
    built from the renderer's per-frame positions, gives exactly the renderer's exposure flow
    and therefore the same blur; swapping the y convention does not.  (A centred straight
    blur is the same for v and -v, so the overall sign is pinned by the flow values and by
    test_blender_signs_from_the_definition, not by the picture.)"""
    vel = np.array([18.0, -6.0])  # per frame
    bg = Background(wave_texture(1, (0.2, 0.15, 0.1), 0.6))
    sc = Scene(W, H, bg, (SceneObject(Disc(10), wave_texture(2, (0.6, 0.4, 0.2)), (40.0, 24.0),
                                      tuple(vel * shutter)),))
    r = scenes.render(sc, samples=64)
    prev, nxt = scenes.frame_displacements(sc, shutter)
    vp = vectors.to_blender(prev, nxt)
    flow = vectors.from_blender(vp, shutter)
    np.testing.assert_allclose(flow, r.flow, atol=1e-4)
    a = clblur.blur(r.sharp, flow, "srgb", backend="numpy")
    b = clblur.blur(r.sharp, r.flow, "srgb", backend="numpy")
    assert np.abs(a.astype(int) - b).max() <= 1
    yflip = vp * np.float32([1, -1, 1, -1])
    wrong_y = clblur.blur(r.sharp, vectors.from_blender(yflip, shutter), "srgb", backend="numpy")
    inner = r.alpha == 1  # on the disc, where the gather follows the disc's own vectors
    good = scenes.psnr(a, r.image, inner)
    assert good > scenes.psnr(wrong_y, r.image, inner) + 3.0


def test_bent_halves_and_blur_bent():
    """Halves are s/2 of each per-frame displacement; blur_bent with equal halves is the
    straight centred blur (within one code: the frame-time sample counts twice)."""
    d_prev = np.broadcast_to(np.float32(PREV), (H, W, 2))
    d_next = np.broadcast_to(np.float32(NEXT), (H, W, 2))
    first, second = vectors.half_vectors(d_prev, d_next, 0.5)
    np.testing.assert_allclose(first[0, 0], np.float32(PREV) / 4)
    np.testing.assert_allclose(second[0, 0], np.float32(NEXT) / 4)
    rng = np.random.default_rng(3)
    img = (rng.random((H, W, 3)) * 255).astype(np.uint8)
    flow = np.broadcast_to(np.float32([12.0, 4.0]), (H, W, 2))
    bent = vectors.blur_bent(img, flow / 2, flow / 2, "srgb", backend="numpy", samples=129)
    straight = clblur.blur(img, flow, "srgb", backend="numpy", samples=257)
    assert np.abs(bent.astype(int) - straight).max() <= 1
    with pytest.raises(ValueError):
        vectors.from_blender(np.zeros((H, W, 2)))
    with pytest.raises(ValueError):
        vectors.exposure_flow(d_prev, d_next, 0)
    with pytest.raises(ValueError):
        vectors.nuke_displacements()
