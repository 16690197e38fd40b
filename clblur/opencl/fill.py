"""The harmonic fill of occlusion layers on the OpenCL device.

:func:`harmonic_fill` is :func:`clblur.layer_planes.harmonic_fill` (the specification: a
cascadic multigrid over a pull-push pyramid) computed by the kernels of
``clblur/opencl/fill.cl``, with the same result to within float32 rounding.

Conventions
-----------
* Every level stays on the device: one buffer holds the whole pyramid (each level at an
  element offset), two ping-pong buffers the estimate; the values and the mask go up once
  and the result comes down once.  The launches are queued without waiting on any of
  them: one per Jacobi sweep at the large levels, one for all the sweeps of a small level
  (one work-group, ``fill_sweeps_group``), where the ~100 - 400 launches a call would cost
  more host time than the sweeps take.
* The pyramid's depth is decided on the host from ``known`` alone: a pixel of a coarser level
  has weight exactly when a known pixel lies under its 5 x 5 reflect-101 footprint (the
  weights are sums of positive terms), so the boolean pyramid of the mask gives the
  reference's stopping level without reading weights back.  This holds while no weight
  underflows float32, i.e. below about 15 levels (images under 2^15 pixels a side).
* Arithmetic: ``fill.cl`` (operation for operation as the reference in float32; cv2.pyrDown
  summed in its vectorised loops' order).
"""

from __future__ import annotations

import numpy as np

from clblur.layer_planes import FILL_SWEEPS, FILL_SWEEPS_MAX
from clblur.opencl.device import pyopencl_module
from clblur.opencl.program import Program

__all__ = ["MAX_CHANNELS", "harmonic_fill", "pyramid_shapes"]

MAX_CHANNELS = 15  # value channels a kernel build takes (one more, the weight, rides along)
# work-group shapes: a GPU reads rows of 32 pixels together; a CPU work-group (PoCL: one
# task, looped over its items) of whole row segments keeps the task count and its
# scheduling cost low
_GPU_GROUP = (32, 4)
_CPU_GROUP = (64, 1)
# Levels of at most this many pixels run all their Jacobi sweeps in one launch of one
# work-group (fill_sweeps_group), a barrier between sweeps: a launch costs 35 - 65 us of host
# time (pyopencl setting its arguments, most of it), more than a sweep of a few thousand
# pixels by one core or a GPU's one multiprocessor.  Per sweep, C = 3, launched / one group
# (2026-11-26): PoCL on this 2-core VM, 38 x 50: 36 / 14 us, 75 x 100: 40 / 50 us; an H100,
# 75 x 100: 59 / 7.5 us, 150 x 200: 69 / 28 us, 300 x 400: 54 / 106 us
_GROUP_PIXELS_CPU = 4096
_GROUP_PIXELS_GPU = 65536
_GROUP_ITEMS_MAX = 1024  # work-items of that one group, at most (and at most the kernel's)


def _program(rt, channels: int) -> Program:
    """The fill program for ``channels`` value channels, built once per runtime and options
    (kept in the runtime's program cache, keyed by its build options)."""
    cl = pyopencl_module()
    options = (f"-DCHANNELS={channels}",)
    if rt.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
        # value / weight rounded as numpy rounds it (OpenCL's default allows 2.5 ulp)
        options += ("-cl-fp32-correctly-rounded-divide-sqrt",)
    return rt.built(("fill.cl",), *options)


def _support_down(mask: np.ndarray) -> np.ndarray:
    """Where ``cv2.pyrDown`` of a nonnegative array positive at ``mask`` is positive: any
    ``mask`` pixel under the 5 x 5 footprint of the even source pixels, reflect-101 border
    (numpy's ``reflect`` padding)."""
    h, w = mask.shape
    dh, dw = (h + 1) // 2, (w + 1) // 2
    p = np.pad(mask, 2, mode="reflect")
    rows = p[0:2 * dh - 1:2] | p[1:2 * dh:2] | p[2:2 * dh + 1:2] | p[3:2 * dh + 2:2] \
        | p[4:2 * dh + 3:2]
    return rows[:, 0:2 * dw - 1:2] | rows[:, 1:2 * dw:2] | rows[:, 2:2 * dw + 1:2] \
        | rows[:, 3:2 * dw + 2:2] | rows[:, 4:2 * dw + 3:2]


def pyramid_shapes(known: np.ndarray) -> list[tuple[int, int]]:
    """The (height, width) of every level of the reference's pyramid for the mask ``known``,
    finest first: halved (rounding up) until every pixel of the coarsest level has weight or
    one side is a single pixel (module Conventions)."""
    mask = np.asarray(known, bool)
    shapes = [mask.shape]
    while min(mask.shape) > 1 and not mask.all():
        mask = _support_down(mask)
        shapes.append(mask.shape)
    return shapes


def _round_up(n: int, m: int) -> int:
    return -(-n // m) * m


def harmonic_fill(values: np.ndarray, known: np.ndarray,
                  device: str | None = None) -> np.ndarray:
    """:func:`clblur.layer_planes.harmonic_fill` on the OpenCL device ``device`` (a selector
    as :func:`clblur.opencl.runtime` takes; default: the current device).

    Parameters
    ----------
    values : numpy.ndarray
        h x w x C float32 (C from 1 to ``MAX_CHANNELS``).
    known : numpy.ndarray
        h x w bool, at least one True: the pixels whose values are kept.
    device : str, optional
        The OpenCL device selector.

    Returns
    -------
    numpy.ndarray
        h x w x C float32: ``values`` at the known pixels (bit for bit), the fill elsewhere,
        within float32 rounding of the reference's (``tests/test_opencl_fill.py`` gives the
        bound).
    """
    from clblur.opencl import runtime

    cl = pyopencl_module()
    values = np.ascontiguousarray(values, np.float32)
    if values.ndim != 3:
        raise ValueError(f"values must be h x w x C, got shape {values.shape}")
    h, w, c = values.shape
    if not 1 <= c <= MAX_CHANNELS:
        raise ValueError(f"the fill on OpenCL takes 1 to {MAX_CHANNELS} channels, got {c}")
    known = np.asarray(known, bool)
    if known.shape != (h, w):
        raise ValueError(f"known must be {h} x {w}, got shape {known.shape}")
    if not known.any():
        raise ValueError("harmonic_fill needs at least one known pixel")
    shapes = pyramid_shapes(known)
    cp = c + 1
    offsets = np.concatenate([[0], np.cumsum([lh * lw * cp for lh, lw in shapes])])
    out = np.empty_like(values)
    rt = runtime(device)
    group = _GPU_GROUP if rt.gpu else _CPU_GROUP
    group_pixels = _GROUP_PIXELS_GPU if rt.gpu else _GROUP_PIXELS_CPU

    def grid(lh: int, lw: int) -> tuple[int, int]:
        return _round_up(lw, group[0]), _round_up(lh, group[1])

    with rt.lock:
        program = _program(rt, c)
        items = min(_GROUP_ITEMS_MAX, program.kernel("fill_sweeps_group").get_work_group_info(
            cl.kernel_work_group_info.WORK_GROUP_SIZE, rt.device))
        q = rt.queue
        vals = rt.upload("fill.values", values)
        mask = rt.upload("fill.known", known.view(np.uint8))
        levels = rt.buffer("fill.levels", int(offsets[-1]) * 4)  # offsets[-1]: the total
        est = [rt.buffer("fill.estimate0", h * w * c * 4),
               rt.buffer("fill.estimate1", h * w * c * 4)]
        res = rt.buffer("fill.out", h * w * c * 4)
        program.run("fill_pack", q, grid(h, w), group, values=vals, known=mask, level=levels,
                    h=h, w=w)
        for d in range(1, len(shapes)):
            (sh, sw), (dh, dw) = shapes[d - 1], shapes[d]
            program.run("fill_down", q, grid(dh, dw), group, src=levels, soff=offsets[d - 1],
                        sh=sh, sw=sw, dst=levels, doff=offsets[d], dh=dh, dw=dw)
        ch, cw = shapes[-1]
        program.run("fill_coarsest", q, grid(ch, cw), group, level=levels, off=offsets[-2],
                    h=ch, w=cw, est=est[0])
        cur = 0  # which ping-pong buffer holds the current estimate
        for depth in range(len(shapes) - 2, -1, -1):
            lh, lw = shapes[depth]
            program.run("fill_up", q, grid(lh, lw), group, level=levels, off=offsets[depth],
                        lh=lh, lw=lw, coarse=est[cur], ch=ch, cw=cw, est=est[1 - cur],
                        finest=int(depth == 0))
            cur = 1 - cur
            sweeps = min(FILL_SWEEPS << depth, FILL_SWEEPS_MAX)
            if lh * lw <= group_pixels:
                program.run("fill_sweeps_group", q, (items, 1), (items, 1), level=levels,
                            off=offsets[depth], lh=lh, lw=lw, a=est[cur], b=est[1 - cur],
                            sweeps=sweeps)
                cur ^= sweeps & 1  # the result is in b after an odd count
                sweeps = 0
            for _ in range(sweeps):
                program.run("fill_sweep", q, grid(lh, lw), group, level=levels,
                            off=offsets[depth], lh=lh, lw=lw, src=est[cur], dst=est[1 - cur])
                cur = 1 - cur
            ch, cw = lh, lw
        program.run("fill_out", q, grid(h, w), group, values=vals, known=mask, est=est[cur],
                    out=res, h=h, w=w)
        # blocking, inside the lock: the reused buffers are free again once this returns
        cl.enqueue_copy(q, out, res, is_blocking=True)
    return out
