"""A validated blur request: what both backends receive.

Validation lives here, once, so the numpy reference and the OpenCL backend see the same checked
inputs and raise the same clear errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clblur.motion import Motion, anchor_value, parse_motion, time_weights
from clblur.pixels import SUPPORTED_DTYPES, validate_saturation
from clblur.responses import Response, per_channel


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
        raise TypeError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype not in [np.dtype(d) for d in SUPPORTED_DTYPES]:
        raise TypeError(f"unsupported image dtype {image.dtype}; use uint8, uint16, float32 "
                        "or float64")
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be H x W or H x W x C, got shape {image.shape}")
    if image.size == 0:
        raise ValueError(f"image is empty (shape {image.shape})")
    if image.dtype.kind == "f" and not np.isfinite(image).all():
        raise ValueError("image contains NaN or infinite values")
    return image if image.ndim == 3 else image[..., None]


def make_plan(image, motion, response="exp", *, anchor: str = "center",
              samples: int | None = None, weights=None, saturation: float = 1.0,
              region: tuple[int, int, int, int] | None = None,
              check_flow: bool = True) -> BlurPlan:
    """Validate a request.  ``region = (row0, col0, full_h, full_w)`` marks ``image`` as a
    window of a larger image (used by tiling); the flow, if any, covers the window.
    ``check_flow=False``: the OpenCL backend validates the flow's values on the device."""
    img = check_image(image)
    h, w, c = img.shape
    parsed = parse_motion(motion, (h, w), check=check_flow)
    n, wts = time_weights(samples, weights)
    return BlurPlan(image=img, squeeze=np.ndim(image) == 2, motion=parsed,
                    responses=tuple(per_channel(response, c)), anchor=anchor_value(anchor),
                    samples=n, weights=wts, saturation=validate_saturation(saturation),
                    **_region(region, (h, w)))


def _region(region, shape) -> dict:
    if region is None:
        return {}
    r0, c0, fh, fw = (int(v) for v in region)
    if r0 < 0 or c0 < 0 or r0 + shape[0] > fh or c0 + shape[1] > fw:
        raise ValueError(f"window {shape} at ({r0}, {c0}) does not fit a {fh} x {fw} image")
    return {"origin": (r0, c0), "extent": (fh, fw)}
