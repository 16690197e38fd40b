"""A validated blur request: what both backends receive.

Validation lives here, once, so the numpy reference and the OpenCL backend see the same checked
inputs and raise the same clear errors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.motion import (
    FLOW_LIMIT,
    PSF,
    Field,
    Motion,
    Uniform,
    anchor_value,
    check_exposure,
    parse_motion,
    sample_counts,
    time_weights,
    trapezoid_weights,
)
from clblur.pixels import SUPPORTED_DTYPES, validate_saturation
from clblur.responses import Linear, Response, per_channel

__all__ = ["BlurPlan", "bound_far_flow", "check_depth", "check_image", "make_plan", "retime"]


@dataclass(frozen=True)
class BlurPlan:
    """Everything a backend needs.  ``image`` is always H x W x C (a view of the input)."""

    image: np.ndarray
    squeeze: bool  # the input was H x W; drop the channel axis on output
    motion: Motion
    responses: tuple[Response, ...]  # one per channel
    anchor: float
    samples: int | None  # None: the per-pixel default ceil(|v|) + 1
    weights: np.ndarray | None  # normalised time weights, length == samples
    saturation: float
    # Tiling: ``image`` is the window starting at ``origin`` (row, col) of a full image of
    # ``extent`` (H, W).  Sample positions are computed and clamped in full-image coordinates,
    # so a tile with a large enough halo reproduces the untiled result bit for bit.
    origin: tuple[int, int] = (0, 0)
    extent: tuple[int, int] | None = None
    # The last channel is coverage (alpha), not light: see ``clblur.reference`` Conventions.
    alpha: bool = False
    # Occlusion ordering (``clblur.layered_exposure``): None (plain gather), an H x W float64
    # depth (smaller = nearer), or H x W int64 layer IDs (smaller = nearer).
    depth: np.ndarray | None = None
    # ``depth`` is the speed ordering ``-|v|`` (cut by gaps in its range, not at surfaces).
    speed_order: bool = False
    # What lies behind every layer (a clean plate), the input's dtype and layout, or None.
    background: np.ndarray | None = None
    # How samples are weighted without time weights (``clblur.motion`` Conventions, exposure).
    # ``make_plan`` turns a ``continuous`` exposure with a fixed sample count (and uniform
    # motion) into explicit ``weights``; only a per-pixel count keeps it here (``ends``).
    exposure: str = "frames"

    @property
    def ends(self) -> bool:
        """Per-pixel sample counts with the ``continuous`` exposure: each pixel's first and
        last samples take half weight (``clblur.motion.sample_weight``)."""
        return self.exposure == "continuous" and self.weights is None

    @property
    def colour_channels(self) -> int:
        """Channels that carry light (all but the alpha channel)."""
        return self.image.shape[2] - (1 if self.alpha else 0)

    @property
    def full_shape(self) -> tuple[int, int]:
        return self.extent if self.extent is not None else self.image.shape[:2]

    @property
    def dtype(self) -> np.dtype:
        return self.image.dtype

    def finish(self, out: np.ndarray) -> np.ndarray:
        """Give the output the input's layout."""
        return out[..., 0] if self.squeeze else out


def check_image(image) -> np.ndarray:
    """Return ``image`` as an H x W x C array, or raise a clear error."""
    if not isinstance(image, np.ndarray):
        raise InputTypeError(f"image must be a numpy array, got {type(image).__name__}")
    if not image.dtype.isnative and image.dtype.newbyteorder("=") in [
            np.dtype(d) for d in SUPPORTED_DTYPES]:
        image = image.astype(image.dtype.newbyteorder("="))  # big-endian data: same values
    if image.dtype not in [np.dtype(d) for d in SUPPORTED_DTYPES]:
        raise InputTypeError(f"unsupported image dtype {image.dtype}; use uint8, uint16, float32 "
                             "or float64")
    if image.ndim not in (2, 3):
        raise InputError(f"image must be H x W or H x W x C, got shape {image.shape}")
    if image.size == 0:
        raise InputError(f"image is empty (shape {image.shape})")
    if image.dtype.kind == "f" and not np.isfinite(image).all():
        raise InputError("image contains NaN or infinite values")
    return image if image.ndim == 3 else image[..., None]


def make_plan(image, motion, response="exp", *, anchor: str = "center",
              samples: int | None = None, weights=None, saturation: float = 1.0,
              region: tuple[int, int, int, int] | None = None, depth=None,
              alpha: bool = False, background=None, check_flow: bool = True,
              exposure: str = "frames") -> BlurPlan:
    """Validate a request.  ``region = (row0, col0, full_h, full_w)`` marks ``image`` as a
    window of a larger image (used by tiling); the flow, if any, covers the window.
    ``depth``: occlusion ordering, H x W (see ``check_depth``); ``alpha``: the last channel is
    coverage; ``background``: a clean plate (what lies behind every layer), same shape and
    dtype as ``image``, used with ``depth``.  ``check_flow=False``: the OpenCL backend
    validates the flow's values on the device.  ``exposure``: ``clblur.motion.EXPOSURES``."""
    img = check_image(image)
    h, w, c = img.shape
    exposure = check_exposure(exposure, weights)
    n, wts = time_weights(samples, weights)
    a = anchor_value(anchor)
    where = _region(region, (h, w))
    if n is not None and isinstance(motion, np.ndarray) and motion.ndim == 3:
        motion = bound_far_flow(motion, n, a, where.get("extent", (h, w)))
    parsed = parse_motion(motion, (h, w), check=check_flow)
    if isinstance(parsed, PSF) and (samples is not None or weights is not None):
        # a PSF's taps are its samples and their weights: the options would be dropped
        raise InputError("samples and weights apply to motion vectors; a PSF carries its own "
                         "taps and weights")
    if isinstance(parsed, Uniform) and n is None and \
            math.hypot(parsed.dx, parsed.dy) > FLOW_LIMIT:
        # the default ceil(|v|) + 1 samples: 1e9 px had allocated 7.5 GiB of positions (or
        # drawn the OOM killer), 1e6 px ran for minutes; the flows' limit, as the CLI's
        raise InputError(f"motion ({parsed.dx:g}, {parsed.dy:g}) is longer than "
                         f"{FLOW_LIMIT:g} px and would take that many samples per pixel by "
                         "default; give a sample count (samples=N, --samples N)")
    if exposure == "continuous":
        if isinstance(parsed, PSF):
            raise InputError("exposure='continuous' applies to motion vectors; a PSF carries "
                             "its own weights")
        if isinstance(parsed, Uniform) and n is None:  # one count for every pixel
            n = int(sample_counts(np.float32(parsed.dx), np.float32(parsed.dy)))
        if n is not None:  # one count: the weights say it all (ends stays False)
            wts = trapezoid_weights(n)
    if not isinstance(alpha, (bool, np.bool_)):
        raise InputTypeError(f"alpha must be True or False, got {alpha!r}")
    if alpha and c < 2:
        raise InputError("alpha=True needs an image with at least 2 channels (colour + alpha), "
                         f"got {c}")
    # coverage never passes through a response: one per colour channel (a calibrated RGB
    # set fits an RGBA image), and the identity stands in the coverage channel's place
    responses = (per_channel(response, c - 1, "colour channel(s) and alpha, which takes none")
                 + [Linear()] if alpha else per_channel(response, c))
    return BlurPlan(image=img, squeeze=np.ndim(image) == 2, motion=parsed,
                    responses=tuple(responses), anchor=a,
                    samples=n, weights=wts, saturation=validate_saturation(saturation),
                    alpha=bool(alpha), speed_order=_is_speed(depth),
                    depth=check_depth(_named(depth, parsed), (h, w), speed=_is_speed(depth)),
                    background=_check_background(background, image, depth),
                    exposure=exposure, **where)


def retime(plan: BlurPlan, **changes) -> BlurPlan:
    """``plan`` with ``changes`` (motion, anchor, samples, weights, exposure), its weights
    derived as :func:`make_plan` derives them for a ``continuous`` exposure: explicit
    trapezoid weights for a fixed count, none for per-pixel counts (``BlurPlan.ends``).  For
    plans built once and run with other sample counts or anchors (a bent path's halves, the
    layers of a render)."""
    from dataclasses import replace

    plan = replace(plan, **changes)
    if plan.exposure == "continuous":
        plan = replace(plan, weights=None if plan.samples is None
                       else trapezoid_weights(plan.samples))
    return plan


def bound_far_flow(flow: np.ndarray, samples: int, anchor: float,
                   full_shape: tuple[int, int]) -> np.ndarray:
    """A flow whose components beyond ``FLOW_LIMIT`` are clipped to it, where that is exact.

    With a fixed sample count ``N``, every sample but the anchor's lies at least
    ``|v| * d_min`` px from its pixel (``d_min``: the smallest non-zero ``|s_j - a|``).  When
    ``FLOW_LIMIT * d_min`` already exceeds the image, such a sample reads the clamped edge
    whether the component is ``FLOW_LIMIT`` or ``1e9``, so clipping changes no output value
    and keeps the kernels' float32 positions in range.  Otherwise (or with the per-pixel
    default ``N = ceil(|v|) + 1``) the flow is returned as it is and the limit is enforced.
    NaN and infinite values are left for the flow check to refuse.
    """
    if flow.dtype.kind != "f" or flow.dtype == np.float16:  # finite halves stay below 65504
        return flow
    beyond = np.abs(flow) > FLOW_LIMIT  # NaN compares False; inf counts and is refused later
    if not beyond.any():
        return flow
    j = np.arange(samples, dtype=np.float64)
    offsets = np.abs(j - anchor * (samples - 1)) / max(samples - 1, 1)
    moving = offsets[offsets > 0]
    if moving.size and FLOW_LIMIT * moving.min() < max(full_shape):
        return flow
    finite = np.isfinite(flow)
    return np.where(beyond & finite, np.sign(flow) * FLOW_LIMIT, flow).astype(flow.dtype)


def _check_background(background, image: np.ndarray, depth) -> np.ndarray | None:
    if background is None:
        return None
    if depth is None:
        raise InputError("a background plate is only used with a depth ordering (depth=...)")
    if not isinstance(background, np.ndarray) or background.shape != image.shape \
            or background.dtype != image.dtype:
        raise InputError("background must be an array with the image's shape and dtype "
                         f"({image.shape}, {image.dtype})")
    return check_image(background)


def _is_speed(depth) -> bool:
    return isinstance(depth, str) and depth == "speed"


def _named(depth, motion):
    """An ordering named by a string (``clblur.layering.named_order``), computed from the
    motion; no order for uniform motion or a PSF, where nothing moves relative to anything
    else.  Anything else is returned as it is (``check_depth`` refuses other strings)."""
    from clblur.layering import NAMED_ORDERS, named_order

    if not isinstance(depth, str) or depth not in NAMED_ORDERS:
        return depth

    return named_order(depth, motion.flow if isinstance(motion, Field) else None)


def check_depth(depth, shape: tuple[int, int], speed: bool = False) -> np.ndarray | None:
    """An occlusion ordering for an image of ``shape``: None, an H x W float depth (smaller is
    nearer, > 0, +inf for the sky; returned as float64) or H x W integer layer IDs (smaller
    is nearer; int64).  ``speed``: ``depth`` is the speed ordering ``-|v|`` (any finite
    value)."""
    if depth is None:
        return None
    d = np.asarray(depth)
    if d.dtype == object or not np.issubdtype(d.dtype, np.number):
        raise InputTypeError("depth must be a numeric H x W array, 'speed' or 'departure', got "
                             f"{depth!r:.40}")
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.shape != tuple(shape):
        raise InputError(f"depth has shape {d.shape}, expected {tuple(shape)} to match the "
                         "image")
    if np.issubdtype(d.dtype, np.integer):
        return d.astype(np.int64)
    d = d.astype(np.float64, copy=False)
    if speed:
        return d
    # one pass when the depth is valid (every value > 0 and not NaN; +inf passes), which is
    # every call but a refused one: the checks below name the problem
    if (d > 0).all():
        return d
    # +inf is the sky (farther than anything, a layer of its own); NaN has no order and a
    # distance is positive: both are refused in one line rather than guessed at
    bad = np.isnan(d) | (d == -np.inf)
    if bad.any():
        raise InputError(f"depth contains {int(bad.sum())} NaN or -inf value(s); use +inf for "
                         "the sky")
    if (d <= 0).any():
        raise InputError(f"depth contains {int((d <= 0).sum())} value(s) <= 0; a float depth "
                         "is a distance (> 0, smaller = nearer); pass integer layer IDs for a "
                         "rank order")
    return d


def _region(region, shape) -> dict:
    if region is None:
        return {}
    r0, c0, fh, fw = (int(v) for v in region)
    if r0 < 0 or c0 < 0 or r0 + shape[0] > fh or c0 + shape[1] > fw:
        raise InputError(f"window {shape} at ({r0}, {c0}) does not fit a {fh} x {fw} image")
    return {"origin": (r0, c0), "extent": (fh, fw)}
