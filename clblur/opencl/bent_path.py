"""The bent shutter path of ``clblur.video`` on the device, end to end.

Why: ``clblur.video.blur_frame`` integrates two straight halves of the shutter and finishes
their mean once.  Run through the generic pipeline, that linearised the frame on the host,
uploaded the float image twice, downloaded two float exposures and finished them on the host.
Here the frame's codes go up once, are linearised once on the device, both halves integrate
from that same intermediate into float32 exposures that stay on the device, and their mean is
finished there: one upload of the frame and of each half's vectors, one download of the
codes.

Conventions
-----------
* ``first`` ends at the frame time (anchor ``end``), ``second`` starts there (anchor
  ``start``), as ``clblur.video.half_paths`` gives them; ``samples`` per half.
* The intermediate is float32 (no half storage: the error bound of ``half_float`` is stated
  for one finish of one exposure, not for a mean of two).
* Tolerance against the numpy reference: ``docs/tolerances.md`` ("Video bent path").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from clblur.motion import Field
from clblur.opencl import response_pack
from clblur.opencl.backend import (
    GROUP_SIZE,
    check_flow,
    collect_output,
    finish_args,
    integrate_field,
    linearise,
    output_target,
    upload_flow,
    upload_input,
)
from clblur.opencl.device import Runtime, pyopencl_module, runtime
from clblur.request import BlurPlan, retime
from clblur.responses import response

__all__ = ["blur_bent", "run_bent"]


def blur_bent(plan: BlurPlan, first: np.ndarray, second: np.ndarray, samples: int | None,
              device: str | None = None, exposure: str = "frames") -> np.ndarray:
    """Blur ``plan.image`` along the bent path ``first`` then ``second`` (H x W x 2 float32)
    on the device; the output has the image's dtype and layout (``plan.finish``)."""
    rt = runtime(device)
    with rt.lock:
        return run_bent(rt, plan, first, second, samples, exposure=exposure)


def run_bent(rt: Runtime, plan: BlurPlan, first: np.ndarray, second: np.ndarray,
             samples: int | None, gpu: bool | None = None,
             exposure: str = "frames") -> np.ndarray:
    """:func:`blur_bent` on ``rt`` (the caller holds ``rt.lock``); ``gpu`` forces the GPU
    (True) or CPU (False) kernel variants, default: the device's type."""
    cl = pyopencl_module()
    gpu = rt.gpu if gpu is None else gpu
    img = plan.image
    h, w, channels = img.shape
    halves = [retime(plan, motion=Field(v), anchor=a, samples=samples, weights=None,
                     exposure=exposure) for v, a in ((first, 1.0), (second, 0.0))]
    src = upload_input(rt, plan, gpu=gpu)
    prog = rt.program(False, gpu)
    planes = not gpu  # the CPU field kernel reads channel planes
    lin_buf = rt.buffer("linear", (h + 1) * (w + 1) * 4 * 4)
    # each half's exposure: integrate_field's float32 store with the identity response
    exposure = np.broadcast_to(np.zeros((), np.float32), img.shape)  # shape and dtype only
    linear_plan = replace(plan, image=exposure, responses=(response("linear"),) * channels)
    exposures = [rt.buffer(f"exposure_{k}", h * w * channels * 4) for k in range(2)]
    out, out_buf = output_target(rt, img)
    fields = []
    done: list = []
    for cbase, cg in response_pack.channel_groups(channels):
        linear = linearise(rt, prog, src, plan, cbase, cg, lin_buf, planes) + done
        if not fields:  # queued behind the image, as in run_plan
            fields = [upload_flow(rt, half, src, role=f"flow_{k}")
                      for k, half in enumerate(halves)]
        ends = []
        for half, field, buf in zip(halves, fields, exposures, strict=True):
            store = finish_args(rt, linear_plan, cbase, cg, buf)
            ends += integrate_field(rt, prog, gpu, half, src, lin_buf, field, store, linear)
        # the tables below are re-uploaded per group: the halves must have read theirs
        cl.wait_for_events(ends)
        store = finish_args(rt, plan, cbase, cg, out_buf)
        n = h * w
        done = [prog.run("finish_mean", rt.queue, (-(-n // GROUP_SIZE) * GROUP_SIZE,),
                         (GROUP_SIZE,), first=exposures[0], second=exposures[1], n=n,
                         **store)]
        cl.wait_for_events(done)
    for field in fields:
        check_flow(rt, field)
    return collect_output(rt, plan, out, out_buf, [(0, h)], done)
