"""Exact Euclidean distance transforms with nearest-pixel indices on the OpenCL device.

Device versions of ``clblur.layer_planes._nearest_transform`` (scipy's
``distance_transform_edt(outside, return_indices=True)``, indices flat) and
``clblur.layer_planes.distance_to`` (the distance alone), with the same results bit for bit.

Conventions
-----------
* The kernels (``nearest.cl``) compute the exact integer squared distance (Felzenszwalb and
  Huttenlocher's two passes, in integers); the host takes its float64 square root, which is
  what scipy returns (it sums the squared integer offsets in float64 exactly, then takes the
  correctly rounded ``sqrt``).
* A *feature* pixel is one that is not ``outside`` (``nearest_transform``) or one that is
  ``inside`` (``distance``); at least one is required (else ``ValueError``).
* Ties between equally near feature pixels may pick another pixel than scipy; the distance is
  the same.  Images up to 32767 px a side (int32 squared distances and flat indices).
"""

from __future__ import annotations

import numpy as np

from clblur.opencl.device import pyopencl_module
from clblur.opencl.program import Program

__all__ = ["MAX_SIDE", "distance", "nearest_transform"]

MAX_SIDE = 32767  # 2 * (MAX_SIDE - 1)^2 and MAX_SIDE^2 - 1 fit int32
GROUP = 64  # work-items per group: global sizes are padded to it (the kernels guard)


def _program(rt) -> Program:
    """The distance-transform program, built once per runtime (kept in the runtime's program
    cache, keyed by its build options)."""
    return rt.built(("nearest.cl",))


def _padded(n: int) -> int:
    return -(-n // GROUP) * GROUP


def _mask(mask: np.ndarray, name: str) -> np.ndarray:
    """``mask`` as a contiguous 2-D bool array, checked."""
    mask = np.ascontiguousarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array, got shape {mask.shape}")
    if max(mask.shape) > MAX_SIDE:
        raise ValueError(f"{name} is larger than {MAX_SIDE} px a side: {mask.shape}")
    return mask


def _transform(mask: np.ndarray, feature_on: bool, want_index: bool,
               device: str | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The squared distances (int32, H x W) from every pixel to the nearest feature pixel
    (where ``mask == feature_on``) and, with ``want_index``, the flat index (int32) of one."""
    from clblur.opencl import runtime

    cl = pyopencl_module()
    h, w = mask.shape
    n = h * w
    d2 = np.empty((h, w), np.int32)
    index = np.empty((h, w), np.int32) if want_index else None
    rt = runtime(device)
    mf = cl.mem_flags
    with rt.lock:
        program = _program(rt)
        mask_buf = cl.Buffer(rt.context, mf.READ_ONLY | mf.COPY_HOST_PTR,
                             hostbuf=mask.view(np.uint8))
        frow = rt.buffer("nearest.frow", 4 * n)
        d2_buf = rt.buffer("nearest.d2", 4 * n)
        index_buf = rt.buffer("nearest.index", 4 * n if want_index else 4)
        program.run("nearest_columns", rt.queue, (_padded(w),), (GROUP,), mask=mask_buf,
                    feature_on=int(feature_on), h=h, w=w, frow=frow)
        program.run("nearest_rows", rt.queue, (_padded(h),), (GROUP,), frow=frow, h=h, w=w,
                    site=rt.buffer("nearest.site", 4 * n),
                    start=rt.buffer("nearest.start", 4 * n),
                    d2=d2_buf, index=index_buf, want_index=int(want_index))
        cl.enqueue_copy(rt.queue, d2, d2_buf, is_blocking=index is None)
        if index is not None:
            cl.enqueue_copy(rt.queue, index, index_buf, is_blocking=True)
    return d2, index


def nearest_transform(outside: np.ndarray,
                      device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The distance from every pixel to the nearest pixel that is not ``outside``, and that
    pixel's flat (row-major) index: ``clblur.layer_planes._nearest_transform`` on the device.

    Parameters
    ----------
    outside : numpy.ndarray
        H x W mask (nonzero: outside); the pixels that are not outside are the features, at
        least one.
    device : str, optional
        OpenCL device selector (``clblur.opencl.device``).

    Returns
    -------
    dist : numpy.ndarray
        H x W float64: ``scipy.ndimage.distance_transform_edt(outside)`` bit for bit (0 at
        the features).
    flat : numpy.ndarray
        H x W int64: ``row * W + col`` of a nearest feature pixel (a feature pixel's own
        index; between equally near ones, possibly another than scipy's).

    Raises
    ------
    ValueError
        If ``outside`` is not 2-D, too large, or has no feature pixel.
    """
    outside = _mask(outside, "outside")
    if outside.size == 0:
        return np.zeros(outside.shape), np.zeros(outside.shape, np.int64)
    if outside.all():
        raise ValueError("nearest_transform: no feature pixel (every pixel is outside)")
    d2, index = _transform(outside, False, True, device)
    return np.sqrt(d2.astype(np.float64)), index.astype(np.int64)


def distance(inside: np.ndarray, at: tuple[np.ndarray, np.ndarray] | None = None,
             device: str | None = None) -> np.ndarray:
    """The Euclidean distance from every pixel to the nearest ``inside`` pixel:
    ``clblur.layer_planes.distance_to(inside, at)`` on the device, bit for bit.

    Parameters
    ----------
    inside : numpy.ndarray
        H x W mask, at least one pixel nonzero.
    at : tuple of numpy.ndarray, optional
        (rows, cols): return the distances at those pixels only.
    device : str, optional
        OpenCL device selector (``clblur.opencl.device``).

    Returns
    -------
    numpy.ndarray
        float64, H x W (``scipy.ndimage.distance_transform_edt(~inside)``), or at ``at``
        (the shape of ``inside[at]``).

    Raises
    ------
    ValueError
        If ``inside`` is not 2-D, too large, or has no True pixel.
    """
    inside = _mask(inside, "inside")
    if inside.size == 0:
        d = np.zeros(inside.shape)
        return d if at is None else d[at]
    if not inside.any():
        raise ValueError("distance: no inside pixel to measure the distance to")
    d2, _ = _transform(inside, True, False, device)
    if at is not None:
        d2 = d2[at]
    return np.sqrt(d2.astype(np.float64))
