"""Optical flow between neighbouring video frames (OpenCV) or read from a folder.

Conventions
-----------
* ``flow(src, dst)`` is defined on ``src``'s pixel grid, float32 H x W x 2 (dx, dy), x right,
  y down: the content at pixel ``p`` of ``src`` is at ``p + flow(p)`` in ``dst`` (OpenCV's
  convention: ``src(p) ~ dst(p + flow(p))``).
* For frame ``i``: the *forward* flow is ``flow(frame i, frame i+1)`` and the *backward* flow is
  ``flow(frame i, frame i-1)``; both live on frame ``i``'s grid.
* A flow folder holds ``forward_NNNNNN.{flo,npy}`` and ``backward_NNNNNN.{flo,npy}`` with ``N``
  the 0-based frame index (6 digits).  Missing files are allowed: the caller extrapolates from
  the other direction (constant velocity).
* Flow is estimated on 8-bit grey versions of the frames (the estimators expect display-like
  values; the linear domain only matters for the blur itself).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.io import read_flow, resolve_inside, write_flow
from clblur.pixels import quantise

__all__ = ["DIS_MIN_SIDE", "METHODS", "FlowEstimator", "FlowFolder", "flow_path", "grey8",
           "save_flows"]

METHODS = ("dis", "farneback")
# OpenCV's DIS picks its pyramid from the frame size and reads past its levels when the
# frame is too small for it: with the medium preset, frames 8 - 15 px high and 48 px or more
# wide crash the process (OpenCV 5.0: 12 x 64, 15 x 256; opencv/opencv#14554) and smaller
# ones raise.  Every shape with both sides >= 16 ran (16 - 3000 px, scanned); a smaller frame
# is padded to that by repeating its edge pixels, and its flow cropped back.
DIS_MIN_SIDE = 16


def grey8(image: np.ndarray) -> np.ndarray:
    """RGB or grey frame of any supported dtype -> uint8 grey."""
    import cv2

    img = image
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype.kind == "f":
        img = quantise(img, np.uint8)
    elif img.dtype != np.uint8:
        raise InputTypeError(f"unsupported frame dtype {img.dtype}")
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img)  # DIS rejects strided views (crops)


class FlowEstimator:
    """Dense optical flow with OpenCV: ``dis`` (DIS, medium preset) or ``farneback``."""

    def __init__(self, method: str = "dis"):
        import cv2

        if method not in METHODS:
            raise InputError(f"unknown flow method {method!r}; use {', '.join(METHODS)} or a "
                             "folder of precomputed flows")
        self.method = method
        self._dis = (cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
                     if method == "dis" else None)

    def __call__(self, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        import cv2

        a, b = grey8(src), grey8(dst)
        if a.shape != b.shape:
            raise InputError(f"frames differ in size: {a.shape} and {b.shape}")
        if self._dis is not None:
            h, w = a.shape
            grow = (max(DIS_MIN_SIDE - h, 0), max(DIS_MIN_SIDE - w, 0))
            if any(grow):  # too small for DIS (DIS_MIN_SIDE): pad with the edge pixels
                a, b = (cv2.copyMakeBorder(x, 0, grow[0], 0, grow[1], cv2.BORDER_REPLICATE)
                        for x in (a, b))
            flow = self._dis.calc(a, b, None)[:h, :w]
        else:
            flow = cv2.calcOpticalFlowFarneback(a, b, None, pyr_scale=0.5, levels=5,
                                                winsize=15, iterations=3, poly_n=5,
                                                poly_sigma=1.2, flags=0)
        return np.ascontiguousarray(flow, dtype=np.float32)


def flow_path(folder: str | os.PathLike, direction: str, index: int) -> Path | None:
    """The stored ``forward``/``backward`` flow of frame ``index``, or None if absent."""
    for suffix in (".flo", ".npy"):
        p = Path(folder) / f"{direction}_{index:06d}{suffix}"
        if p.is_file():
            return p
    return None


class FlowFolder:
    """Precomputed flows (layout in the module docstring)."""

    def __init__(self, folder: str | os.PathLike):
        self.path = Path(folder)
        if not self.path.is_dir():
            raise InputError(f"flow folder not found: {folder}")
        if not any(self.path.glob("forward_*")) and not any(self.path.glob("backward_*")):
            raise InputError(f"{folder} holds no forward_NNNNNN/backward_NNNNNN .flo or .npy "
                             "flow files")

    def get(self, direction: str, index: int, shape: tuple[int, int]) -> np.ndarray | None:
        p = flow_path(self.path, direction, index)
        if p is None:
            return None
        # a flow in the folder must be a file in the folder, not a symlink leading out of it
        flow = read_flow(resolve_inside(self.path, p.name, f"flow folder {self.path}: file"))
        if flow.shape[:2] != tuple(shape):
            raise InputError(f"{p.name} has size {flow.shape[:2]}, the frame {tuple(shape)}")
        return flow


def save_flows(folder: str | os.PathLike, index: int, backward: np.ndarray | None,
               forward: np.ndarray | None) -> None:
    """Write a frame's flows in the folder layout (``.npy``), e.g. to reuse them later; the
    folder is created if missing."""
    Path(folder).mkdir(parents=True, exist_ok=True)
    for direction, flow in (("backward", backward), ("forward", forward)):
        if flow is not None:
            write_flow(Path(folder) / f"{direction}_{index:06d}.npy", flow)
