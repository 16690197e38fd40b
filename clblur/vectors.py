"""Renderers' motion-vector conventions (Blender, Nuke) converted to clblur's flow.

clblur's flow is the displacement of scene content over the *exposure*: x right, y down,
pixels (``clblur.motion``).  Renderers store per-*frame* displacements, with their own axes and
signs; the shutter (a fraction ``s`` of the frame interval, centred on the frame time) turns
them into an exposure.  Full statement with sources: ``docs/model.md``, "Renderer vector
passes".

Conventions
-----------
* Intermediate form: ``(d_prev, d_next)``, H x W x 2 float32 each, in clblur's axes, pixels
  per frame: ``d_prev`` is how far the content at a pixel travelled from the previous frame
  to this one, ``d_next`` how far it travels from this frame to the next.
* Blender ``Vector`` pass (Cycles; EEVEE writes the same layout): 4 channels ``X, Y, Z, W``
  in pixels, in Blender's raster axes (x right, **y up**).  Cycles computes them as
  ``(X, Y) = P_prev - P_cur`` and ``(Z, W) = P_cur - P_next`` (``primitive_motion_vector``
  in ``intern/cycles/kernel/geom/primitive.h``), so in clblur's axes
  ``d_prev = (-X, +Y)`` and ``d_next = (-Z, +W)``: content moving right has *negative* X and
  Z; content moving down has positive Y and W.
* Nuke ``forward`` / ``backward`` layers (``u``, ``v``), as VectorGenerator writes them:
  ``forward(p)`` is the offset from ``p`` to where its content is in the next frame,
  ``backward(p)`` to where it was in the previous frame, in pixels, in Nuke's axes (x right,
  **y up**, origin bottom left).  So ``d_next = (u_f, -v_f)`` and ``d_prev = (-u_b, +v_b)``.
  ``y_up=False`` reads vectors already flipped to y down.
* Exposure (shutter fraction ``s``, centred): first half ``s/2 d_prev`` (ends at the frame
  time, anchor ``end``), second half ``s/2 d_next`` (starts at it, anchor ``start``); the
  straight chord is ``s/2 (d_prev + d_next)`` with anchor ``center``.  Blender's shutter is
  in frames (default 0.5); a shutter angle ``theta`` is ``s = theta / 360``.
* A missing half (the first or last frame) mirrors the other (constant velocity), as
  ``clblur.video.half_paths`` does.
"""

from __future__ import annotations

import os

import numpy as np

from clblur.errors import InputError

__all__ = ["CONVENTIONS", "blender_displacements", "to_blender", "nuke_displacements",
           "to_nuke", "exposure_flow", "half_vectors", "from_blender", "from_nuke",
           "blur_bent", "read_vectors", "load_flow"]

CONVENTIONS = ("clblur", "blender", "nuke")


def _field(a, what: str, channels: int) -> np.ndarray:
    f = np.asarray(a, np.float32)
    if f.ndim != 3 or f.shape[2] != channels:
        raise InputError(f"{what} has shape {f.shape}, expected H x W x {channels}")
    if not np.isfinite(f).all():
        raise InputError(f"{what} contains NaN or infinite values")
    return f


def _shutter(shutter: float) -> float:
    s = float(shutter)
    if not np.isfinite(s) or s <= 0:
        raise InputError(f"shutter must be a positive fraction of the frame interval, got "
                         f"{shutter}")
    return s


def blender_displacements(vector_pass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blender ``Vector`` pass (H x W x 4: X, Y, Z, W) -> ``(d_prev, d_next)``."""
    v = _field(vector_pass, "Blender vector pass", 4)
    d_prev = np.stack([-v[..., 0], v[..., 1]], axis=-1)
    d_next = np.stack([-v[..., 2], v[..., 3]], axis=-1)
    return d_prev, d_next


def to_blender(d_prev: np.ndarray, d_next: np.ndarray) -> np.ndarray:
    """``(d_prev, d_next)`` -> a Blender ``Vector`` pass (H x W x 4), the inverse of
    ``blender_displacements``."""
    p = _field(d_prev, "d_prev", 2)
    n = _field(d_next, "d_next", 2)
    return np.stack([-p[..., 0], p[..., 1], -n[..., 0], n[..., 1]], axis=-1)


def nuke_displacements(forward: np.ndarray | None = None, backward: np.ndarray | None = None,
                       *, y_up: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Nuke ``forward`` / ``backward`` (u, v) layers -> ``(d_prev, d_next)``; a missing one
    mirrors the other."""
    if forward is None and backward is None:
        raise InputError("need the forward or the backward vectors (or both)")
    flip = np.float32(-1.0 if y_up else 1.0)
    d_next = d_prev = None
    if forward is not None:
        f = _field(forward, "Nuke forward vectors", 2)
        d_next = np.stack([f[..., 0], flip * f[..., 1]], axis=-1)
    if backward is not None:
        b = _field(backward, "Nuke backward vectors", 2)
        d_prev = np.stack([-b[..., 0], -flip * b[..., 1]], axis=-1)
    if d_prev is None:
        d_prev = d_next.copy()
    if d_next is None:
        d_next = d_prev.copy()
    if d_prev.shape != d_next.shape:
        raise InputError(f"forward and backward vectors differ in shape: {d_next.shape} and "
                         f"{d_prev.shape}")
    return d_prev, d_next


def to_nuke(d_prev: np.ndarray, d_next: np.ndarray, *,
            y_up: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(d_prev, d_next)`` -> Nuke ``(forward, backward)`` (u, v) layers."""
    p = _field(d_prev, "d_prev", 2)
    n = _field(d_next, "d_next", 2)
    flip = np.float32(-1.0 if y_up else 1.0)
    forward = np.stack([n[..., 0], flip * n[..., 1]], axis=-1)
    backward = np.stack([-p[..., 0], -flip * p[..., 1]], axis=-1)
    return forward, backward


def exposure_flow(d_prev: np.ndarray, d_next: np.ndarray, shutter: float = 0.5) -> np.ndarray:
    """The straight chord over a centred exposure of ``shutter`` frames: clblur's flow for
    ``clblur.blur(..., anchor="center")``."""
    s = _shutter(shutter)
    return (np.float32(s / 2) * (d_prev + d_next)).astype(np.float32)


def half_vectors(d_prev: np.ndarray, d_next: np.ndarray,
                 shutter: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The two halves of a centred exposure: ``(first, second)``, for anchors ``end`` and
    ``start`` (a bent path; see ``blur_bent``)."""
    s = _shutter(shutter)
    return (np.float32(s / 2) * d_prev).astype(np.float32), \
        (np.float32(s / 2) * d_next).astype(np.float32)


def from_blender(vector_pass: np.ndarray, shutter: float = 0.5, *, bent: bool = False):
    """clblur's flow from a Blender ``Vector`` pass for a centred shutter of ``shutter`` frames.

    Returns the straight flow (H x W x 2, anchor ``center``), or with ``bent=True`` the two
    halves ``(first, second)`` for ``blur_bent``."""
    d_prev, d_next = blender_displacements(vector_pass)
    return half_vectors(d_prev, d_next, shutter) if bent else \
        exposure_flow(d_prev, d_next, shutter)


def from_nuke(forward: np.ndarray | None = None, backward: np.ndarray | None = None,
              shutter: float = 0.5, *, bent: bool = False, y_up: bool = True):
    """clblur's flow from Nuke ``forward``/``backward`` vectors (as ``from_blender``)."""
    d_prev, d_next = nuke_displacements(forward, backward, y_up=y_up)
    return half_vectors(d_prev, d_next, shutter) if bent else \
        exposure_flow(d_prev, d_next, shutter)


def blur_bent(image: np.ndarray, first: np.ndarray, second: np.ndarray, response="srgb",
              *, curved: bool = False, **options) -> np.ndarray:
    """Blur along a bent path: ``first`` ends at the frame time, ``second`` starts there.

    Both halves are integrated in the linear domain and the response is applied once
    (``clblur.video.blur_frame``, which takes per-frame flows; with a 360-degree shutter its
    halves are minus half the backward flow and half the forward flow).  ``curved``: the
    parabola through the path's three points instead of two straight halves
    (``clblur.video.blur_curved``; Blender's Vector Blur ``use_curved`` follows a Bezier
    through the same three points)."""
    from clblur.video import blur_frame

    f = _field(first, "first half", 2)
    s = _field(second, "second half", 2)
    return blur_frame(image, -2 * f, 2 * s, response, shutter=360, curved=curved, **options)


def read_vectors(path: str | os.PathLike, convention: str,
                 layer: str | None = None) -> dict[str, np.ndarray]:
    """A renderer's vector pass from a file: ``.npy`` (H x W x 4 for Blender, H x W x 2 or
    H x W x 4 = forward u, v, backward u, v for Nuke) or ``.exr`` (Blender
    ``[<layer>.]Vector.X/Y/Z/W``; Nuke ``forward.u/v``, ``backward.u/v``; or RGBA holding the
    vector pass, as a Blender File Output node saves it).  Returns ``{"pass": ...}`` (Blender)
    or ``{"forward": ..., "backward": ...}`` (Nuke, either may be absent).  ``layer``: a
    Blender view layer of a multilayer EXR, ``<layer>.Vector.X/Y/Z/W``."""
    from clblur.io.paths import require_file

    if convention not in ("blender", "nuke"):
        raise InputError(f"unknown vector convention {convention!r}; use blender or nuke")
    path = require_file(path, "vector")
    if path.suffix.lower() == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except Exception as e:
            raise InputError(f"cannot read vectors {path}: {e}") from None
        if convention == "blender":
            return {"pass": _field(a, f"Blender vector pass {path}", 4)}
        if a.ndim == 3 and a.shape[2] == 4:
            return {"forward": a[..., :2], "backward": a[..., 2:]}
        return {"forward": _field(a, f"Nuke forward vectors {path}", 2)}
    from clblur.io import exr

    chans = exr.read_channels(path)
    if layer is not None:  # one view layer of a multilayer file: <layer>.Vector.X/Y/Z/W
        names = [f"{layer}.Vector.{c}" for c in "XYZW"]
        if convention != "blender" or not all(n in chans for n in names):
            raise InputError(f"{path} has no Blender vector pass {layer}.Vector.X/Y/Z/W "
                             f"(a named layer is a Blender view layer); channels: "
                             f"{', '.join(chans)}")
        return {"pass": np.stack([chans[n] for n in names], axis=-1)}
    if convention == "blender":
        # "Vector.", "<layer>.Vector.", then plain X, Y, Z, W, then RGBA (a File Output node)
        groups = sorted(n[:-1] for n in chans if n.endswith("Vector.X")
                        and all(n[:-1] + c in chans for c in "XYZW"))
        if len(groups) > 1:  # one per view layer: which one is the user's to say
            layers = ", ".join(g[:-len(".Vector.")] or "(none)" for g in groups)
            raise InputError(f"{path} has several Blender vector passes (view layers {layers}); "
                             f"name one: {path}:LAYER")
        for pre in [*groups, "", None]:
            names = [pre + c for c in "XYZW"] if pre is not None else list("RGBA")
            if all(n in chans for n in names):
                return {"pass": np.stack([chans[n] for n in names], axis=-1)}
        raise InputError(f"{path} has no Blender vector pass (Vector.X/Y/Z/W, X/Y/Z/W or "
                         f"RGBA); channels: {', '.join(chans)}")
    out = {}
    for layer in ("forward", "backward"):
        if f"{layer}.u" in chans and f"{layer}.v" in chans:
            out[layer] = np.stack([chans[f"{layer}.u"], chans[f"{layer}.v"]], axis=-1)
    if not out:
        raise InputError(f"{path} has no Nuke forward.u/v or backward.u/v channels; channels: "
                         f"{', '.join(chans)}")
    return out


def load_flow(path: str | os.PathLike, convention: str = "clblur",
              shutter: float = 0.5, *, bent: bool = False, layer: str | None = None):
    """clblur's straight flow (anchor ``center``) from a file in ``convention``
    (``clblur``: ``.npy``/``.flo``/``.exr`` flow as is; ``blender``/``nuke``: a vector pass
    and a centred shutter of ``shutter`` frames).  ``bent=True`` (a renderer's pass only):
    the two halves ``(first, second)`` of the bent path instead.  ``layer``: a Blender view
    layer of a multilayer EXR (:func:`read_vectors`)."""
    if convention not in CONVENTIONS:
        raise InputError(f"unknown vector convention {convention!r}; use one of "
                         f"{', '.join(CONVENTIONS)}")
    if convention == "clblur":
        if layer is not None:
            raise InputError(f"{path}:{layer}: a layer names a renderer's vector pass; give "
                             "--vectors blender (clblur flows are flow.x / flow.y)")
        if bent:
            raise InputError("a bent path needs a renderer's vector pass (blender or nuke): "
                             "a clblur flow is one straight vector per pixel")
        from clblur.io import read_flow

        return read_flow(path)
    v = read_vectors(path, convention, layer)
    if convention == "blender":
        return from_blender(v["pass"], shutter, bent=bent)
    return from_nuke(v.get("forward"), v.get("backward"), shutter, bent=bent)
