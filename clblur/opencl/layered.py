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
  the layers are built by ``clblur.layered_exposure.prepare`` (shared with the numpy
  reference), composited in float32 by ``clblur/opencl/layered.cl``, and finished on the host.
  By default (``integrator``'s ``build``) the region, the layer labels, the distance
  transforms and the membrane fill run on the device (``clblur/opencl/region.cl``,
  ``labels.cl``, ``nearest.cl``, ``fill.cl``), and the compositing kernels count their own
  samples on a device with fp64; the rest of ``prepare`` (the split of mixed
  pixels, the planes' assembly) is still host work.
  Tolerance against the numpy reference: ``docs/tolerances.md`` ("Layered exposure").
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from clblur import layered_exposure as layered
from clblur import reference
from clblur.layer_planes import Transforms
from clblur.opencl.constants import LANES, LAYERED_MAXK
from clblur.opencl.device import pyopencl_module
from clblur.opencl.program import Program
from clblur.request import BlurPlan
from clblur.responses import response

__all__ = ["BUILDS", "OpenCLStages", "composite", "integrator", "transforms"]

MAXC = 16  # channels + coverage a work-item holds in registers (layered.cl)
GROUP = 64
LANE_GROUP = 16  # work-items (of LANES pixels each) per group of the CPU kernel


def _program(rt, channels: int, curved: bool = False,
             steps: int = layered.INVERSE_STEPS) -> Program:
    """The compositing program for ``channels`` light channels, straight or curved paths and
    ``steps`` fixed-point steps of the inverse motion, built once per runtime and options
    (kept in the runtime's program cache, keyed by its build options)."""
    # counts.cl first: the sample counts the gather uses too (one home for the formula)
    return rt.built(("counts.cl", "layered.cl"), f"-DCHANNELS={channels}",
                    f"-DCURVED={int(curved)}", f"-DINVERSE_STEPS={int(steps)}",
                    *(("-DHAVE_FP64",) if rt.fp64 else ()))


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
              device: str | None = None, lanes: bool | None = None,
              ends: bool = False, own_counts: bool | None = None) -> np.ndarray:
    """:func:`clblur.layered_exposure.composite` on the device, for ``layers.region`` only.

    ``lanes``: use the CPU layout (``composite_lanes``, LANES pixels of a row per work-item;
    three light channels only) or not (``composite_layers``, one pixel per work-item); the
    default picks it for three channels on a CPU device.  Both give the same bits.
    ``ends``: the ``continuous`` exposure with per-pixel counts (``BlurPlan.ends``).
    ``own_counts``: whether the kernel counts each pixel's samples itself (exact, the host's
    ``clblur.layered_exposure.counts``); only where it can (a device with fp64, straight
    paths, per-pixel counts, no ``Layers.reach``), which is the default.
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
    if k > LAYERED_MAXK:
        raise ValueError(f"layered exposure on OpenCL takes at most {LAYERED_MAXK} layers")
    # the linear image padded to the planes' layout (one zero channel): one load per tap
    linear = np.zeros((h, w, cp), np.float32)
    linear[..., :channels] = layers.linear
    weighted = weights is not None
    wts = weights.astype(np.float32) if weighted else np.zeros(1, np.float32)
    out = np.empty((n, channels), np.float32)
    rt = runtime(device)
    mf = cl.mem_flags

    def buf(a):
        return cl.Buffer(rt.context, mf.READ_ONLY | mf.COPY_HOST_PTR,
                         hostbuf=np.ascontiguousarray(a))

    def large(role: str, a: np.ndarray):
        # the planes and fields: read in place on a device that shares host memory (a CPU:
        # copying tens of MB per call was a tenth of a real-flow frame), else uploaded
        # into a buffer kept for the role
        return rt.share("layered." + role, a.astype(np.float32, copy=False))
    with rt.lock:
        program = _program(rt, channels, layers.curvature is not None, layered.steps_of(layers))
        fh, fw = full_shape
        r0, c0 = layers.origin
        args = dict(planes=large("planes", layers.planes),
                    vectors=large("vectors", layers.vectors),
                    flow=large("flow", layers.flow), linear=large("linear", linear),
                    present=buf(np.ascontiguousarray(layers.present, bool).view(np.uint8)),
                    warped=buf(np.ascontiguousarray(layers.warped, bool).view(np.uint8)),
                    curvature=buf(np.zeros(2, np.float32) if layers.curvature is None
                                  else layers.curvature.astype(np.float32, copy=False)),
                    weights=buf(wts),
                    weighted=weighted, ends=int(bool(ends) and not weighted), layers=k,
                    h=h, w=w, r0=r0, c0=c0, fh=fh, fw=fw,
                    anchor=anchor)
        if lanes and cp != 4:
            raise ValueError("the CPU compositing layout takes three light channels")
        # the kernel counts samples itself where it can (a host pass over the region's
        # pixels and every layer cost 5 ms on an H100 host, the kernel's whole run 0.7 ms;
        # 13 ms of a 0.5 s real-flow half-exposure on PoCL)
        can_count = (rt.fp64 and samples is None and layers.curvature is None
                     and layers.reach is None)
        own = can_count if own_counts is None else bool(own_counts) and can_count
        if lanes or (lanes is None and cp == 4 and not rt.gpu):
            # own counts: 1 marks a lane on the region, the kernel counts its samples
            counts = np.ones(n, np.int32) if own else \
                layered.counts(layers, samples, (rows, cols)).astype(np.int32)
            # CPU: LANES consecutive pixels of a row per work-item (layered.cl); the chunks
            # of LANES columns that hold region pixels, row-major
            wide = -(-w // LANES) * LANES
            occupied = np.zeros((h, wide), bool)
            occupied[:, :w] = layers.region
            occupied = occupied.reshape(h, wide // LANES, LANES)
            crow, cchunk = np.nonzero(occupied.any(axis=2))
            on = occupied[crow, cchunk]  # lanes on the region (none past the crop)
            ccol = cchunk * LANES
            # the lanes on the region by flat index (boolean masks of this size are slow)
            lanes_on = np.flatnonzero(on)
            lane_n = np.zeros(on.size, np.int32)
            lane_n[lanes_on] = counts  # row-major, as (rows, cols)
            lanes_out = np.empty((crow.size * LANES, channels), np.float32)
            out_buf = cl.Buffer(rt.context, mf.WRITE_ONLY, lanes_out.nbytes)
            items = -(-crow.size // LANE_GROUP) * LANE_GROUP
            program.run("composite_lanes", rt.queue, (items,), (LANE_GROUP,),
                        chunks=buf(np.stack([crow, ccol], axis=1).astype(np.int32)),
                        counts=buf(lane_n), own_counts=int(own), n=crow.size, out=out_buf,
                        **args)
            cl.enqueue_copy(rt.queue, lanes_out, out_buf, is_blocking=True)
            return np.take(lanes_out, lanes_on, axis=0)
        out_buf = cl.Buffer(rt.context, mf.WRITE_ONLY, max(out.nbytes, 16))
        pix = np.stack([rows, cols], axis=1).astype(np.int32)
        counts = np.zeros(1, np.int32) if own else \
            layered.counts(layers, samples, (rows, cols)).astype(np.int32)
        program.run("composite_layers", rt.queue, (-(-n // GROUP) * GROUP,), (GROUP,),
                    pix=buf(pix), counts=buf(counts), own_counts=int(own), n=n,
                    out=out_buf, **args)
        cl.enqueue_copy(rt.queue, out, out_buf, is_blocking=True)
    return out


def transforms(device: str | None = None) -> Transforms:
    """The device's layer labels, distance transforms and membrane fill for building layers
    (``clblur.layer_planes.Transforms``): ``clblur.opencl.labels``, ``clblur.opencl.nearest``
    and ``clblur.opencl.fill``, looked up at each call."""
    from clblur.opencl import fill, labels, nearest

    return Transforms(nearest=lambda outside: nearest.nearest_transform(outside, device),
                      distance=lambda inside, at=None: nearest.distance(inside, at, device),
                      fill=lambda values, known: fill.harmonic_fill(values, known, device),
                      labels=lambda order, rule="depth": labels.layer_labels(
                          order, rule=rule, device=device),
                      threads=False)


BUILDS = ("auto", "device", "host")


def integrator(device: str | None = None, build: str | None = None,
               curvature: np.ndarray | None = None):
    """The sparse layered integrator on the device (``clblur.pipeline`` Conventions).

    ``build``: where the layered region is found and the layers' labels, distance transforms
    and membrane fill run: ``"device"`` (``clblur.opencl.region`` and :func:`transforms`),
    ``"host"`` (``clblur.layered_exposure.region_mask``, ``clblur.layer_planes.HOST``), or
    ``"auto"``: the device, whatever its type.  On a GPU the host's versions were most of a
    layered call's time (``bench/results_occlusion_gpu.md``); on PoCL the device's kernels
    use every core where scipy's transforms use one, and a real-flow frame (GoPro frame 10,
    63 % of it layered) took 1.0 s against 1.16 s with the host build, the bench frames the
    same (``bench/results_occlusion.md``, 2026-11-27).  None: the environment variable
    ``CLBLUR_LAYER_BUILD``, else ``"auto"``.  Both builds are held to the reference
    (``docs/tolerances.md``).  ``curvature``: a curved path's quadratic term
    (``clblur.layered_exposure.integrator``); its region is found on the host."""
    if build is None:
        build = os.environ.get("CLBLUR_LAYER_BUILD", "auto").strip().lower() or "auto"
    if build not in BUILDS:
        raise ValueError(f"layer build must be one of {', '.join(BUILDS)} "
                         f"(CLBLUR_LAYER_BUILD), got {build!r}")

    def integrate(linear, plan: BlurPlan):
        ordered = layered.plan_order(plan)
        if ordered is None:
            return None
        on_device = build != "host"
        v, order, rule = ordered
        ops = transforms(device) if on_device else None  # None: layer_planes.HOST
        if on_device and curvature is None:
            from clblur.opencl import region as device_region

            region, r = device_region.region_and_reach(v, plan.anchor, device=device)
        else:
            region, r = layered.region_and_reach(v, plan.anchor, curvature)
        if not region.any():
            return None
        def crop_linear(crop):  # linearise only the crop the layers need, in float32 (the planes')
            return reference.linearise(replace(plan, image=plan.image[crop], background=None),
                                       np.float32)
        found = []  # (rows, cols, values) of each part built as layers
        for layers in layered.built_parts(crop_linear, v, order, plan.anchor, region, r,
                                          layered.background_linear(plan), rule=rule,
                                          dtype=np.float32, transforms=ops,
                                          curvature=curvature):
            values = composite(layers, plan.anchor, plan.samples, plan.weights,
                               plan.full_shape, device, ends=plan.ends)
            rows, cols = np.nonzero(layers.region)
            r0, c0 = layers.origin
            found.append((rows + r0, cols + c0, values.astype(np.float64)))
        if not found:
            return None
        return tuple(np.concatenate(parts) for parts in zip(*found, strict=True))
    integrate.sparse = True
    return integrate
