"""OpenCL backend: the pipeline of ``clblur.reference`` in float32 kernels.

Conventions
-----------
* Devices, contexts, programs and buffers: ``clblur.opencl_device`` (selection by argument,
  ``$CLBLUR_DEVICE``, first GPU, first device; nothing is created at import).
* Pipeline per group of up to four channels: linearise once per pixel (tables for integer
  inputs, float64 on the host for float inputs) into an RGBA intermediate (half floats for
  uint8 outputs when the propagated error bound allows, else float), then integrate with the
  forward response and quantisation fused into the store.  Integer outputs are quantised by
  comparing the exposure with host-computed float64 code boundaries (no response evaluation
  on the device).  Strategies (``clblur.opencl_prep``): per-pixel field (bilinear, 8 pixels
  per work-item as vector lanes), space-invariant integer taps (uniform motion and PSFs),
  running sums for boxes (exact 64-bit fixed point, cost independent of the length).
* Tolerances against the numpy reference are stated in ``docs/tolerances.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clblur import opencl_prep as prep
from clblur.motion import Field, sample_counts
from clblur.opencl_device import (  # noqa: F401 - re-exported: the backend's interface
    ENV_DEVICE,
    DeviceNotFound,
    OpenCLUnavailable,
    Runtime,
    _runtimes,  # the per-selector runtimes of this process (inspected by tests)
    current_device,
    devices,
    pyopencl_module,
    runtime,
    usable,
)
from clblur.pixels import linearisation_table
from clblur.plan import BlurPlan

LANES = 8  # consecutive pixels of a row per work-item, run as vector lanes (integrate.cl)
# Work-items per work-group along x, fixed so that drivers which specialise code per
# work-group size (PoCL) build each kernel once, not once per image size.  Image kernels use
# wide groups (fewer scheduling rounds); the box kernel has one work-item per 8 lines, so it
# uses small groups to keep both cores busy.
GROUP_SIZE = 64
BOX_GROUP_SIZE = 8
_OUT_KINDS = {np.dtype(np.uint8): 0, np.dtype(np.uint16): 1, np.dtype(np.float32): 2,
              np.dtype(np.float64): 2}  # float64 output: computed in float32, widened on host
_IN_KINDS = {np.dtype(np.uint8): 0, np.dtype(np.uint16): 1}
_IN_FLOAT = 2


def blur(plan: BlurPlan, device: str | None = None) -> np.ndarray:
    """Run ``plan`` on the selected OpenCL device; same output layout as the reference."""
    rt = runtime(device)
    with rt.lock:
        return _run(rt, plan)


def _grid(*sizes: int, group: int = GROUP_SIZE) -> tuple[int, ...]:
    """Global size: the first dimension rounded up to whole work-groups (kernels bound-check)."""
    first = -(-sizes[0] // group) * group
    return (first, *sizes[1:])


@dataclass
class _Input:
    """The uploaded image: integer codes with float64 linearisation tables, or float32
    exposures linearised on the host."""

    buffer: object
    kind: int
    luts: np.ndarray | None  # float64 (channels, Imax + 1) for integer images
    max_abs: float


def _upload_input(rt: Runtime, plan: BlurPlan, img: np.ndarray) -> _Input:
    if img.dtype.kind == "u":
        luts = np.stack([linearisation_table(r, img.dtype, plan.saturation)
                         for r in plan.responses])
        return _Input(rt.share("image", img), _IN_KINDS[img.dtype], luts,
                      float(np.max(np.abs(luts))))
    linear = prep.linearise_float_image(img, plan.responses, plan.saturation)
    return _Input(rt.share("image", linear), _IN_FLOAT, None, float(np.max(np.abs(linear))))


def _run(rt: Runtime, plan: BlurPlan) -> np.ndarray:
    img = np.ascontiguousarray(plan.image)
    h, w, channels = img.shape
    src = _upload_input(rt, plan, img)
    out_kind = _OUT_KINDS[img.dtype]
    out = np.empty((h, w, channels), dtype=np.float32 if out_kind == 2 else img.dtype)
    out_buf = rt.buffer("output", out.nbytes)
    integrate = _integrator(rt, plan, src)
    for cbase, cg in prep.channel_groups(channels):
        group = plan.responses[cbase:cbase + cg]
        params, tables = prep.response_params(group)
        thresholds = (prep.quantisation_thresholds(prep.four_channels(group), img.dtype)
                      if img.dtype.kind == "u" else np.zeros(1, np.float32))
        buckets = (prep.quantisation_buckets(thresholds) if img.dtype.kind == "u"
                   else np.zeros(prep.QHEAD + 1, np.int32))
        store_args = (rt.upload("resp", params), rt.upload("tables", tables),
                      rt.upload("thresholds", thresholds), rt.upload("buckets", buckets),
                      out_buf, np.int32(out_kind),
                      np.int32(channels), np.int32(cbase), np.int32(cg))
        integrate(cbase, cg, store_args)
    pyopencl_module().enqueue_copy(rt.queue, out, out_buf, is_blocking=True)
    if img.dtype == np.float64:
        out = out.astype(np.float64)
    return plan.finish(out)


def _integrator(rt: Runtime, plan: BlurPlan, src: _Input):
    """Upload what the strategy needs once; return ``run(cbase, cg, store_args)``, which
    integrates one channel group into the output buffer."""
    h, w = plan.image.shape[:2]
    fh, fw = plan.full_shape
    r0, c0 = plan.origin
    geometry = tuple(np.int32(v) for v in (w, h, r0, c0, fw, fh))
    taps = prep.space_invariant_taps(plan)
    box = taps.box() if taps is not None else None

    if box is not None:
        axis, lo, hi = box
        scale = np.float32(prep.fixed_point_scale(src.max_abs, hi - lo + 1))
        # Lanes run across the box: columns for a vertical box, rows (transposed) for a
        # horizontal one.
        transposed = axis == 0
        across, length = (h, w) if transposed else (w, h)
        stride = -(-across // LANES) * LANES  # whole 8-pixel vectors stay in bounds
        plane = rt.buffer("plane", stride * length * 16)
        to_plane, kern = rt.kernel(False, "linearise_plane"), rt.kernel(False, "integrate_box")
        channels = plan.image.shape[2]
        shape_args = (np.int32(stride), np.int32(across), np.int32(length),
                      np.int32(transposed))

        def run_box(cbase, cg, store_args):
            lut = (src.luts[cbase:cbase + cg].astype(np.float32) if src.luts is not None
                   else np.zeros((1, 1), np.float32))
            to_plane(rt.queue, _grid(stride, length), (GROUP_SIZE, 1), src.buffer,
                     np.int32(src.kind), np.int32(channels), np.int32(cbase), np.int32(cg),
                     rt.upload("lut", lut), np.int32(lut.shape[1]), plane, *shape_args,
                     np.int32(w))
            kern(rt.queue, _grid(-(-across // LANES), group=BOX_GROUP_SIZE), (BOX_GROUP_SIZE,),
                 plane, *shape_args, np.int32(lo), np.int32(hi), scale, np.int32(w),
                 *store_args)
        return run_box

    half = prep.half_storage_ok(plan, src.luts)
    lin_buf = rt.buffer("linear", (h + 1) * (w + 1) * 4 * (2 if half else 4))  # padded
    linearise = rt.kernel(half, "linearise")
    channels = plan.image.shape[2]

    def to_linear(cbase, cg):
        lut = (src.luts[cbase:cbase + cg].astype(np.float32) if src.luts is not None
               else np.zeros((1, 1), np.float32))
        linearise(rt.queue, _grid(w + 1, h + 1), (GROUP_SIZE, 1), src.buffer,
                  np.int32(src.kind),
                  np.int32(channels), np.int32(cbase), np.int32(cg), rt.upload("lut", lut),
                  np.int32(lut.shape[1]), lin_buf, np.int32(w), np.int32(h))

    items = _grid((w + LANES - 1) // LANES, h)
    if taps is not None:
        dx_buf, dy_buf = rt.upload("tap_dx", taps.dx), rt.upload("tap_dy", taps.dy)
        w_buf = rt.upload("tap_w", taps.w.astype(np.float32))
        extent = tuple(np.int32(v) for v in (taps.dx.min(), taps.dx.max(), taps.dy.min(),
                                              taps.dy.max()))
        kern = rt.kernel(half, "integrate_taps")

        def run_taps(cbase, cg, store_args):
            to_linear(cbase, cg)
            kern(rt.queue, items, (GROUP_SIZE, 1), lin_buf, dx_buf, dy_buf, w_buf,
                 np.int32(taps.w.size), *extent, *geometry, *store_args)
        return run_taps

    assert isinstance(plan.motion, Field)
    flow = plan.motion.flow
    flow_buf = rt.share("flow", flow)
    host_counts = plan.samples is None and not rt.fp64
    counts = sample_counts(flow[..., 0], flow[..., 1]) if host_counts else np.zeros(1, np.int32)
    counts_buf = rt.upload("counts", counts)
    weighted = plan.weights is not None
    time_w = plan.weights.astype(np.float32) if weighted else np.zeros(1, np.float32)
    time_w_buf = rt.upload("time_weights", time_w)
    kern = rt.kernel(half, "integrate_field")

    def run_field(cbase, cg, store_args):
        to_linear(cbase, cg)
        kern(rt.queue, items, (GROUP_SIZE, 1), lin_buf, flow_buf, counts_buf,
             np.int32(host_counts),
             np.int32(plan.samples or 0), time_w_buf, np.int32(weighted),
             np.float32(plan.anchor), *geometry, *store_args)
    return run_field
