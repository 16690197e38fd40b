"""Device-resident blurs: ``pyopencl.array.Array`` in, ``pyopencl.array.Array`` out.

Conventions
-----------
* The image is an H x W or H x W x C ``uint8``/``uint16`` array on the selected device's
  context; the result is a new array of the same shape and dtype on that context.  Float
  images are read back, blurred by the host entry (which refuses NaN and infinite values
  and bounds the exposures for the box kernels) and the result uploaded.
* ``motion``: ``(dx, dy)``, a PSF (numpy), a numpy flow, or an H x W x 2 float32/float16
  ``pyopencl.array.Array`` flow, read on the device and validated there.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from clblur.errors import InputError
from clblur.motion import Field
from clblur.opencl.backend import run_plan
from clblur.opencl.device import runtime
from clblur.request import make_plan

__all__ = ["blur_array"]


def _is_device_array(x) -> bool:
    return type(x).__module__.startswith("pyopencl")


def blur_array(image, motion, response="exp", *, anchor: str = "center",
               samples: int | None = None, weights=None, saturation: float = 1.0,
               device: str | None = None, exposure: str = "frames"):
    """``clblur.blur`` for a ``pyopencl.array.Array`` image; returns one (same context).

    Parameters are those of ``clblur.blur`` (without ``backend``: this is the OpenCL backend).
    """
    import pyopencl.array as cla

    rt = runtime(device)
    if image.context != rt.context:
        raise InputError("the image array lives in another OpenCL context than the selected "
                         "device's (create it with clblur.opencl.runtime(device).context)")
    dtype = np.dtype(image.dtype)
    if dtype.kind == "f":
        from clblur.blur import blur

        host_motion = motion.get() if _is_device_array(motion) else motion
        out = blur(image.get(), host_motion, response, anchor=anchor, samples=samples,
                   weights=weights, saturation=saturation, backend="opencl", device=device,
                   exposure=exposure)
        return cla.to_device(rt.queue, out)
    if image.ndim not in (2, 3):
        raise InputError(f"image must be H x W or H x W x C, got shape {image.shape}")
    shape3 = image.shape if image.ndim == 3 else (*image.shape, 1)
    if not image.flags.c_contiguous:
        raise InputError("the image array must be C-contiguous")
    # a zero-strided stand-in: validation reads shape and dtype only, never the pixels
    proxy = np.broadcast_to(np.zeros((), dtype), shape3)
    flow = None
    if _is_device_array(motion):
        h, w = shape3[:2]
        if motion.shape != (h, w, 2) or np.dtype(motion.dtype) not in (np.float32, np.float16):
            raise InputError(f"flow array must be ({h}, {w}, 2) float32 or float16, got "
                             f"{motion.shape} {motion.dtype}")
        if motion.context != rt.context or not motion.flags.c_contiguous:
            raise InputError("the flow array must be C-contiguous on the image's context")
        flow = motion
        # a zero-strided stand-in of the flow's shape and dtype: the plan is a per-pixel
        # one (a continuous exposure's per-pixel sample counts, for one), never a uniform one
        motion = np.broadcast_to(np.zeros((), flow.dtype), flow.shape)
    plan = make_plan(proxy, motion, response, anchor=anchor, samples=samples, weights=weights,
                     saturation=saturation, check_flow=False, exposure=exposure)
    if image.ndim == 2:
        plan = dataclasses.replace(plan, squeeze=True)
    if flow is not None:  # the kernels read the device's flow: hold no host copy meanwhile
        plan = dataclasses.replace(plan, motion=Field(motion))
    out = cla.empty(rt.queue, image.shape, dtype)
    with rt.lock:
        run_plan(rt, plan, resident_image=image.base_data, resident_flow=flow,
                 resident_out=out.base_data)
    return out
