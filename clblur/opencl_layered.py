"""OpenCL pipeline stages and the layered-exposure integrator on the device.

Conventions
-----------
* ``OpenCLStages`` is the OpenCL backend seen through ``clblur.pipeline``: ``fused(plan)`` is
  the existing backend's one-call blur (gather + response + quantisation in one kernel);
  ``linearise``/``finish`` run on the host in float64 (``clblur.reference``), and
  ``integrate`` is the device gather of a float32 linear image (the existing kernels with the
  identity response).  The staged path serves plans the fused kernel cannot (alpha).
* The layered integrator is *sparse*: outside the pixels that ``boundary_mask`` flags, the
  result is the plain gather of the backend, bit for bit (the fused output); at flagged pixels
  the layers are built on the host (``clblur.layered_exposure.prepare``, shared with the
  numpy reference), composited in float32 by ``kernels/layered.cl``, and finished on the host.
  Tolerance against the numpy reference: ``docs/tolerances.md`` ("Layered exposure").
"""

from __future__ import annotations

from dataclasses import replace
from importlib import resources
from pathlib import Path

import numpy as np

from clblur import layered_exposure as layered
from clblur import reference
from clblur.opencl_device import pyopencl_module
from clblur.plan import BlurPlan
from clblur.responses import response

__all__ = ["OpenCLStages", "composite", "integrator"]

MAXC = 16  # channels + coverage a work-item holds in registers (kernels/layered.cl)
MAXK = 8  # layers a work-item holds (kernels/layered.cl)
GROUP = 64


def _source() -> str:
    try:
        return resources.files("clblur.kernels").joinpath("layered.cl").read_text()
    except (ModuleNotFoundError, FileNotFoundError):
        return (Path(__file__).resolve().parent.parent / "kernels" / "layered.cl").read_text()


def _kernel(rt, channels: int):
    """The compositing kernel for ``channels`` light channels, built once per runtime and
    channel count (kept in the runtime's caches)."""
    key = ("layered.cl", channels, "composite_layers")
    if key not in rt.kernels:
        cl = pyopencl_module()
        program = cl.Program(rt.context, _source()).build(options=[f"-DCHANNELS={channels}"])
        rt.programs[key[:2]] = program
        rt.kernels[key] = cl.Kernel(program, key[2])
    return rt.kernels[key]


class OpenCLStages:
    """The OpenCL backend's pipeline stages (module Conventions)."""

    name = "opencl"

    def __init__(self, device: str | None = None):
        self.device = device

    @staticmethod
    def can_fuse(plan: BlurPlan) -> bool:
        return not plan.alpha

    def fused(self, plan: BlurPlan) -> np.ndarray:
        from clblur import opencl

        return opencl.blur(plan, device=self.device)

    @staticmethod
    def linearise(plan: BlurPlan) -> np.ndarray:
        return reference.linearise(plan)

    def integrate(self, linear: np.ndarray, plan: BlurPlan) -> np.ndarray:
        """The plain gather of a linear image on the device (float32), as float64."""
        from clblur import opencl

        c = linear.shape[2]
        lin_plan = replace(plan, image=np.ascontiguousarray(linear, np.float32), squeeze=False,
                           responses=(response("linear"),) * c, saturation=1.0, alpha=False,
                           depth=None, background=None)
        return opencl.blur(lin_plan, device=self.device).astype(np.float64)

    @staticmethod
    def finish(linear: np.ndarray, plan: BlurPlan) -> np.ndarray:
        return reference.finish(linear, plan)


def composite(layers: layered.Layers, anchor: float, samples: int | None,
              weights: np.ndarray | None, full_shape: tuple[int, int],
              device: str | None = None) -> np.ndarray:
    """:func:`clblur.layered_exposure.composite` on the device, for ``layers.region`` only.

    Returns the exposures of the region's pixels (n x C float32, row-major order of the
    region)."""
    from clblur.opencl import runtime

    cl = pyopencl_module()
    rows, cols = np.nonzero(layers.region)
    n = rows.size
    k, h, w, cp = layers.planes.shape
    channels = cp - 1
    if cp > MAXC:
        raise ValueError(f"layered exposure on OpenCL takes at most {MAXC - 1} channels")
    if k > MAXK:
        raise ValueError(f"layered exposure on OpenCL takes at most {MAXK} layers")
    # the linear image padded to the planes' layout (one zero channel): one load per tap
    linear = np.zeros((h, w, cp), np.float32)
    linear[..., :channels] = layers.linear
    counts = layered.counts(layers, samples, (rows, cols)).astype(np.int32)
    weighted = weights is not None
    wts = weights.astype(np.float32) if weighted else np.zeros(1, np.float32)
    out = np.empty((n, channels), np.float32)
    rt = runtime(device)
    mf = cl.mem_flags

    def buf(a):
        return cl.Buffer(rt.context, mf.READ_ONLY | mf.COPY_HOST_PTR,
                         hostbuf=np.ascontiguousarray(a))
    with rt.lock:
        kern = _kernel(rt, channels)
        out_buf = cl.Buffer(rt.context, mf.WRITE_ONLY, max(out.nbytes, 16))
        pix = np.stack([rows, cols], axis=1).astype(np.int32)
        fh, fw = full_shape
        r0, c0 = layers.origin
        kern(rt.queue, (-(-n // GROUP) * GROUP,), (GROUP,),
             buf(layers.planes.astype(np.float32)), buf(layers.vectors.astype(np.float32)),
             buf(layers.flow.astype(np.float32)), buf(linear),
             buf(layers.present.astype(np.uint8)), buf(pix), buf(counts), buf(wts),
             np.int32(weighted), np.int32(n), np.int32(k), np.int32(h), np.int32(w),
             np.int32(r0), np.int32(c0),
             np.int32(fh), np.int32(fw), np.float32(anchor), out_buf)
        cl.enqueue_copy(rt.queue, out, out_buf, is_blocking=True)
    return out


def integrator(device: str | None = None):
    """The sparse layered integrator on the device (``clblur.pipeline`` Conventions)."""

    def integrate(linear, plan: BlurPlan):
        ordered = layered.plan_order(plan)
        if ordered is None:
            return None
        v, order = ordered
        region = layered.region_mask(v, plan.anchor)
        if not region.any():
            return None
        def crop_linear(crop):  # linearise only the crop the layers need
            return reference.linearise(replace(plan, image=plan.image[crop], background=None))
        layers = layered.prepare(crop_linear, v, order, plan.anchor, region,
                                 layered.background_linear(plan))
        if layers is None:
            return None
        values = composite(layers, plan.anchor, plan.samples, plan.weights, plan.full_shape,
                           device)
        rows, cols = np.nonzero(layers.region)
        r0, c0 = layers.origin
        return rows + r0, cols + c0, values.astype(np.float64)
    integrate.sparse = True
    return integrate
