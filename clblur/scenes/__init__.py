"""Sub-frame ground truth: layered scenes rendered at many shutter instants with exact occlusion.

A camera integrates light over the exposure.  ``render`` evaluates a scene of textured,
depth-ordered objects (translating, accelerating and rotating over a textured, possibly
panning background) at ``samples`` instants of the shutter, resolves occlusion exactly at
every instant and sub-pixel (nearest object wins), averages the radiance in the *linear*
domain, and only then applies the camera response and quantises, with
``clblur.responses`` and ``clblur.pixels`` (the same curves and rounding the blur uses).  That
average is the exposure a camera records, the truth every vector blur is scored against.

Alongside it, ``render`` returns what a renderer hands a compositor at the shutter's centre
time: the sharp frame, per-pixel motion vectors in clblur's convention, depth, coverage (alpha)
and object IDs, plus the *swept region* (pixels any moving layer covers during the shutter).

Conventions
-----------
* Pixel ``(row, col)`` has its centre at ``x = col``, ``y = row`` (x right, y down, pixels),
  as in ``clblur.motion``.
* Time ``t`` is in units of the exposure, ``t = 0`` at the shutter's centre: the shutter is
  open over ``[-1/2, 1/2]``.  Instants are the midpoints ``t_k = (k + 1/2)/K - 1/2``
  (midpoint rule, ``K = samples``).  A frame interval is ``1/shutter`` exposures, so the
  previous and next frames are at ``t = -1/s`` and ``t = +1/s`` for a shutter fraction ``s``.
* An object's centre follows ``c(t) = c0 + v t + a t^2 / 2`` and its angle
  ``theta(t) = theta0 + w t`` (radians, positive turns +x towards +y, i.e. clockwise on
  screen).  A material point with local coordinates ``q`` (pixels, in the object's frame) is
  at ``c(t) + R(theta(t)) q``.  ``v`` is the centre's displacement over the exposure.
* Motion vectors (``Render.flow``): content displacement over the exposure, clblur's
  convention: the chord ``P(+1/2) - P(-1/2)`` of the material point ``P`` seen at the pixel
  centre at ``t = 0`` (the background's velocity where no object is).  ``flow_first`` /
  ``flow_second`` are the halves ``P(0) - P(-1/2)`` and ``P(1/2) - P(0)`` (a bent path, as
  ``clblur.video.half_paths`` gives).  Vectors, depth and IDs are point samples at the pixel
  centre, not anti-aliased (as renderers write Z, index and vector passes).
* Depth: smaller is nearer.  Each object has one constant depth; the background has
  ``Background.depth`` (default 1000).  Ties: the later object in ``Scene.objects`` is in front.
* Radiance is linear (exposure units of ``clblur.responses``: the response maps it to a
  normalised value).  Keep it inside the response's unclipped range (below 1 for ``srgb``) to
  score blur models rather than the saturation policy.
* Sub-pixel sampling: ``spp x spp`` stratified points per pixel (box filter), the same for the
  sharp frame and every instant.  ``alpha`` is the fraction of them covered by an object at
  ``t = 0``; ``exposure_alpha`` the same averaged over the shutter (the truth of a blurred
  matte).
* Swept region: pixels that any object covers (any sub-pixel point) at any instant or at
  ``t = 0``; every pixel when the background moves (then every pixel changes).
* Hidden light (``Render.hidden``): the fraction of a pixel's exposure that comes from surface
  points the sharp frame does not show (background disoccluded by a moving object, the part of
  a far object behind a near one, anything outside the frame at ``t = 0``), looked up on the
  sub-pixel grid.  No method that sees only the sharp frame can know that light; it bounds
  what any single-frame vector blur can score there.
* Clean plate (``Render.plate``): the background layer alone at ``t = 0`` through the same
  response and rounding, as a multi-layer render delivers it.
"""

from clblur.scenes.description import (
    Background,
    Disc,
    MaskShape,
    Rect,
    Scene,
    SceneObject,
    Texture,
    example_scenes,
    flat_texture,
    frame_displacements,
    star_mask,
    wave_texture,
)
from clblur.scenes.renderer import Render, object_layers, psnr, render

__all__ = ["Texture", "wave_texture", "flat_texture", "Disc", "Rect", "MaskShape", "star_mask",
           "SceneObject", "Background", "Scene", "Render", "render", "object_layers", "psnr",
           "frame_displacements", "example_scenes"]
