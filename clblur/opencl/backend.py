"""OpenCL backend: the pipeline of ``clblur.reference`` in float32 kernels, as stage functions.

Conventions
-----------
* Stages, per group of up to four channels (``response_pack.channel_groups``):
  ``upload_input`` (the image, once; float32 images are linearised there, on the device) ->
  ``linearise`` (codes through per-channel tables, or float exposures, into an RGBA
  intermediate, or channel planes
  for the CPU field kernel: half floats for uint8 outputs when ``half_float.half_storage_ok``
  allows, except in the CPU field kernel) ->
  ``integrate_field``
  / ``integrate_taps`` / ``integrate_box``, each with the *finish* stage (forward response and
  quantisation, ``finish_args``) fused into its store.  Integer outputs are quantised by
  comparing the exposure with float64 code boundaries (``quantisation``).
* Strategies: per-pixel field (bilinear), space-invariant integer taps (uniform motion and
  PSFs, ``taps``), running sums for boxes (exact 64-bit fixed point, cost independent of the
  length).  Every kernel argument is passed by name (``program.Program.run``).
* CPU devices (host-unified memory) read the caller's arrays in place and write the returned
  array in place.  Other devices (GPUs)
  get the image in row bands (``transfers``): upload (through reused pinned staging, unless
  the caller's array is already pinned, ``pinned_empty``), linearise, integrate and download
  of different bands overlap on two queues.
* The flow is validated on the device while it is read (non-finite components and components
  beyond ``FLOW_LIMIT`` px are counted into a flag buffer); a non-zero count is refused with
  the message of ``clblur.motion.check_flow``.  float16 flows are read as they are.
* Tolerances against the numpy reference are stated in ``docs/tolerances.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError
from clblur.motion import Field, flow_error, sample_counts
from clblur.opencl import half_float, quantisation, response_pack, taps
from clblur.opencl.constants import FIELD_LANES, IN_F32, IN_KINDS, LANES, OUT_F32, OUT_KINDS
from clblur.opencl.device import Runtime, pyopencl_module, runtime
from clblur.opencl.linearisation import (
    exposure_bound,
    float_inverse_args,
    linearisation_tables,
    linearise_float_image,
)
from clblur.opencl.program import Program
from clblur.opencl.transfers import bands_of, download, pinned_empty, upload_rows
from clblur.request import BlurPlan

__all__ = ["DeviceInput", "FieldInput", "blur", "check_flow", "collect_output", "finish_args",
           "integrate_box", "integrate_field", "integrate_taps", "linearise", "output_target",
           "pinned_empty", "run_plan", "sync_host", "upload_flow", "upload_input"]

# Work-items per work-group along x, fixed so that drivers which specialise code per
# work-group size (PoCL) build each kernel once, not once per image size.  Image kernels use
# wide groups (fewer scheduling rounds); the box kernel has one work-item per LANES lines.
GROUP_SIZE = 64
BOX_GROUP_SIZE = 8
GPU_GROUP = (16, 8)  # GPU variants: one pixel per work-item, compact 2-D patches
# CPU field kernel: 16 x 8 work-items = 256 x 8 pixels per group (FIELD_LANES = 16).
# Measured on PoCL (4K, |v| 10..40, one thread, kernel ms): (16, 8) 229-237, (32, 8) 234-237,
# (8, 8) 236-247, (4, 8) 259-285, (16, 4) 245-256, (8, 16) 241; at |v| 25..100 (1080p)
# (16, 8) 241, (8, 16) 247, (4, 16) 248.  (With 8 lanes, 2-D groups were 1.13x over rows
# of work-items at |v| ~ 80, where rows leave the cache.)
FIELD_GROUP = (16, 8)


def blur(plan: BlurPlan, device: str | None = None) -> np.ndarray:
    """Run ``plan`` on the selected OpenCL device; same output layout as the reference."""
    rt = runtime(device)
    with rt.lock:
        return run_plan(rt, plan)


def _grid(*sizes: int, group: int = GROUP_SIZE) -> tuple[int, ...]:
    """Global size: the first dimension rounded up to whole work-groups (kernels bound-check)."""
    first = -(-sizes[0] // group) * group
    return (first, *sizes[1:])


def _round_up(n: int, m: int) -> int:
    return -(-n // m) * m


@dataclass
class DeviceInput:
    """The uploaded image: integer codes with float64 linearisation tables, or float32
    exposures.  ``ready``: events a reader of rows must wait for, per band (``bands``: row
    ranges).  ``max_abs``: the largest ``|exposure|``, None until asked for
    (``exposure_bound``)."""

    buffer: object
    kind: int
    luts: np.ndarray | None  # float64 (channels, Imax + 1) for integer images
    max_abs: float | None
    bands: list[tuple[int, int]]
    ready: list
    # what queued commands still read (the raw float image behind ``buffer``): a buffer over
    # a host array frees that array with it, queued or not
    held: tuple = ()


def upload_input(rt: Runtime, plan: BlurPlan, resident=None,
                 gpu: bool | None = None) -> DeviceInput:
    """Stage 0: the image on the device: integer codes, or float32 exposures.  float32
    images are linearised on the device (``linearise_float``, band by band behind each
    band's upload; ``gpu``: the kernel variant, default the device's type), float64 images on
    the host in float64 (``clblur.opencl.linearisation``).  ``resident``: a device buffer that
    already holds the integer image."""
    img = plan.image
    bands = bands_of(rt, img.shape[0])
    if img.dtype.kind == "u":
        luts = linearisation_tables(plan.responses, img.dtype, plan.saturation)
        if resident is not None:
            buf, ready = resident, [[] for _ in bands]
        else:
            buf, ready = upload_rows(rt, "image", img, bands)
        return DeviceInput(buf, IN_KINDS[img.dtype], luts, float(np.max(np.abs(luts))), bands,
                           ready)
    if img.dtype == np.float64:
        linear = linearise_float_image(img, plan.responses, plan.saturation)
        buf, ready = upload_rows(rt, "image", linear, bands)
        return DeviceInput(buf, IN_F32, None, float(np.max(np.abs(linear))), bands, ready)
    raw, uploaded = upload_rows(rt, "image", img, bands)
    params, tables, limits = float_inverse_args(plan.responses, plan.saturation)
    args = {"resp": rt.upload("inv_resp", params, table=True),
            "tables": rt.upload("inv_tables", tables, table=True),
            "limits": rt.upload("inv_limits", limits, table=True)}
    prog = rt.program(False, rt.gpu if gpu is None else gpu)
    w, channels = img.shape[1], img.shape[2]
    linear_buf = rt.buffer("linear_input", img.size * 4)
    ready = []
    for k, (r0, r1) in enumerate(bands):
        queue = rt.all_queues()[k % len(rt.all_queues())]
        pixels = (r1 - r0) * w
        ready.append([prog.run("linearise_float", queue,
                               _grid(-(-pixels // LANES), channels), (GROUP_SIZE, 1),
                               wait_for=uploaded[k], image=raw, channels=channels,
                               start=r0 * w, stop=r1 * w, lin=linear_buf, **args)])
    return DeviceInput(linear_buf, IN_F32, None, None, bands, ready, held=(raw,))


def finish_args(rt: Runtime, plan: BlurPlan, cbase: int, cg: int, out_buf) -> dict:
    """The finish stage (forward response + quantisation) of one channel group, as the named
    kernel arguments ``STORE_PARAMS`` of the integrating kernels."""
    group = plan.responses[cbase:cbase + cg]
    params, tables = response_pack.response_params(group)
    if plan.dtype.kind == "u":
        thresholds = quantisation.quantisation_thresholds(response_pack.four_channels(group),
                                                          plan.dtype)
        buckets = quantisation.quantisation_buckets(thresholds)
    else:
        thresholds, buckets = np.zeros(1, np.float32), np.zeros(8, np.int32)
    return {"resp": rt.upload("resp", params, table=True),
            "tables": rt.upload("tables", tables, table=True),
            "thresholds": rt.upload("thresholds", thresholds, table=True),
            "buckets": rt.upload("buckets", buckets, table=True), "out": out_buf,
            "out_kind": OUT_KINDS[plan.dtype], "channels": plan.image.shape[2], "cbase": cbase,
            "cg": cg}


def _grid_args(rt: Runtime, plan: BlurPlan, cbase: int, cg: int) -> dict:
    """The box kernels' code grid (``quantisation.box_code_grid``); ``cells = 0`` (the search)
    where there is none."""
    grid = quantisation.box_code_grid(plan.responses[cbase:cbase + cg], plan.dtype)
    table, cells, scale, stride = grid or (np.zeros(1, np.int32), 0, 0.0, 0)
    return {"grid": rt.upload("grid", table, table=True), "cells": cells, "gstride": stride,
            "gscale": float(scale)}


def _lut(src: DeviceInput, cbase: int, cg: int) -> np.ndarray:
    return (src.luts[cbase:cbase + cg].astype(np.float32) if src.luts is not None
            else np.zeros((1, 1), np.float32))


def linearise(rt: Runtime, prog: Program, src: DeviceInput, plan: BlurPlan, cbase: int,
              cg: int, lin_buf, planes: bool = False) -> list:
    """Stage 1: one channel group into the padded (h + 1) x (w + 1) RGBA intermediate, or
    into ``cg`` channel planes of that size (``planes``: the CPU field kernel's layout), band
    by band after each band's upload.  Returns the events of every band."""
    h, w = plan.image.shape[:2]
    table = _lut(src, cbase, cg)
    lut = rt.upload("lut", table, table=True)
    events = []
    for k, (r0, r1) in enumerate(src.bands):
        r1 = h + 1 if r1 == h else r1  # the last band also writes the padding row
        queue = rt.all_queues()[k % len(rt.all_queues())]
        events.append(prog.run(
            "linearise_planes" if planes else "linearise", queue, _grid(w + 1, r1 - r0),
            (GROUP_SIZE, 1), global_offset=(0, r0),
            wait_for=src.ready[k], image=src.buffer, in_kind=src.kind,
            channels=plan.image.shape[2], cbase=cbase, cg=cg, lut=lut,
            lut_len=table.shape[1], lin=lin_buf, w=w, h=h))
    return events


def _item_grid(gpu: bool, w: int, rows: int, field: bool = False):
    """(global size, local size) of the image kernels for ``rows`` rows: GPU variants one
    pixel per work-item in GPU_GROUP patches; CPU variants LANES pixels per work-item, the
    field kernel in FIELD_GROUP patches (rows of a long blur stay in cache), the taps kernel
    in rows of GROUP_SIZE work-items."""
    if gpu:
        gx, gy = GPU_GROUP
        return (_round_up(w, gx), _round_up(rows, gy)), GPU_GROUP
    if field:
        items = (w + FIELD_LANES - 1) // FIELD_LANES
        gx, gy = FIELD_GROUP
        return (_round_up(items, gx), _round_up(rows, gy)), FIELD_GROUP
    return _grid((w + LANES - 1) // LANES, rows), (GROUP_SIZE, 1)


def _per_band(rt: Runtime, plan: BlurPlan, gpu: bool, src: DeviceInput, launch,
              wait_for, field: bool = False) -> list:
    """Launch ``launch(queue, global, local, offset, wait_for(k))`` once per band, on
    alternating queues; returns the events."""
    w = plan.image.shape[1]
    events = []
    for k, (r0, r1) in enumerate(src.bands):
        queue = rt.all_queues()[k % len(rt.all_queues())]
        glob, local = _item_grid(gpu, w, r1 - r0, field)
        events.append(launch(queue, glob, local, (0, r0), wait_for(k)))
    return events


def integrate_taps(rt: Runtime, prog: Program, gpu: bool, plan: BlurPlan, src: DeviceInput,
                   lin_buf, tap_set: taps.IntegerTaps, finish: dict, after: list) -> list:
    """Stage 2 + finish for space-invariant integer taps (uniform motion, PSFs)."""
    h, w = plan.image.shape[:2]
    args = dict(lin=lin_buf, tap_dx=rt.upload("tap_dx", tap_set.dx, table=True),
                tap_dy=rt.upload("tap_dy", tap_set.dy, table=True),
                tap_w=rt.upload("tap_w", tap_set.w.astype(np.float32), table=True),
                ntaps=tap_set.w.size,
                dx_min=tap_set.dx.min(), dx_max=tap_set.dx.max(), dy_min=tap_set.dy.min(),
                dy_max=tap_set.dy.max(), w=w, h=h, **finish)

    def launch(queue, glob, local, offset, wait_for):
        return prog.run("integrate_taps", queue, glob, local, global_offset=offset,
                        wait_for=wait_for, **args)
    return _per_band(rt, plan, gpu, src, launch, lambda k: after)


@dataclass
class FieldInput:
    """The flow on the device: buffer, half or float, counts, validation counters."""

    flow: object
    half: bool
    counts: object
    host_counts: bool
    bad: object
    ready: list


def upload_flow(rt: Runtime, plan: BlurPlan, src: DeviceInput, resident=None,
                role: str = "flow") -> FieldInput:
    """The flow (float32, or float16 as given) and, for devices without fp64, the host
    sample counts; a zeroed pair of validation counters.  ``resident``: a
    ``pyopencl.array.Array`` that already holds the flow.  ``role`` names the reused device
    buffers (two flows in flight need two roles)."""
    assert isinstance(plan.motion, Field)
    flow = plan.motion.flow
    half = flow.dtype == np.float16
    host_counts = plan.samples is None and not rt.fp64
    if resident is not None:
        buf, ready = resident.base_data, [[] for _ in src.bands]
        flow = resident.get(queue=rt.queue) if host_counts else flow
    else:
        buf, ready = upload_rows(rt, role, flow, src.bands)
    counts = (sample_counts(flow[..., 0], flow[..., 1]) if host_counts
              else np.zeros(1, np.int32))
    bad = rt.upload(f"bad_{role}", np.zeros(2, np.int32))
    return FieldInput(buf, half, rt.upload(f"{role}_counts", counts), host_counts, bad, ready)


def integrate_field(rt: Runtime, prog: Program, gpu: bool, plan: BlurPlan, src: DeviceInput,
                    lin_buf, field: FieldInput, finish: dict, after: list) -> list:
    """Stage 2 + finish for a per-pixel flow field (bilinear samples)."""
    h, w = plan.image.shape[:2]
    time_w = (plan.weights.astype(np.float32) if plan.weights is not None
              else np.zeros(1, np.float32))
    args = dict(lin=lin_buf, flow=field.flow, flow_half=int(field.half), bad_flow=field.bad,
                counts=field.counts, host_counts=int(field.host_counts),
                fixed_n=plan.samples or 0, time_w=rt.upload("time_weights", time_w, table=True),
                weighted=int(plan.weights is not None), ends=int(plan.ends),
                anchor=plan.anchor, w=w, h=h, **finish)

    def launch(queue, glob, local, offset, wait_for):
        return prog.run("integrate_field", queue, glob, local, global_offset=offset,
                        wait_for=wait_for, **args)
    return _per_band(rt, plan, gpu, src, launch, lambda k: after + field.ready[k], field=True)


def integrate_box(rt: Runtime, prog: Program, plan: BlurPlan, src: DeviceInput,
                  box: tuple[int, int, int], finish: dict, cbase: int, cg: int,
                  after: list) -> list:
    """The box as exact fixed-point running sums, finish fused.  Lanes run across the box:
    columns for a vertical box, rows for a horizontal one.  Integer images are read as codes
    through fixed-point tables (linearisation fused); float images' exposures are laid out in
    a float4 plane (transposed for a horizontal box) first."""
    h, w = plan.image.shape[:2]
    axis, lo, hi, ends = box
    # with ends the kernels sum 2 S - (first + last): twice the values' count of headroom
    max_abs = src.max_abs
    if max_abs is None:
        max_abs = exposure_bound(plan.image, plan.responses, plan.saturation)
    scale = taps.fixed_point_scale(max_abs, (2 if ends else 1) * (hi - lo + 1))
    transposed = axis == 0
    across, length = (h, w) if transposed else (w, h)
    grid = _grid(-(-across // LANES), group=BOX_GROUP_SIZE)
    ready = [ev for band in src.ready for ev in band] + after
    channels = plan.image.shape[2]
    table = _lut(src, cbase, cg)
    finish = {**finish, **_grid_args(rt, plan, cbase, cg)}
    if src.luts is not None:  # integer codes: fixed-point tables, no plane
        lutq = np.rint(table.astype(np.float64) * scale).astype(np.int64)
        return [prog.run("integrate_box_codes", rt.queue, grid, (BOX_GROUP_SIZE,),
                         wait_for=ready, image=src.buffer, in_kind=src.kind,
                         lutq=rt.upload("lutq", lutq, table=True), lut_len=table.shape[1],
                         across=across,
                         len=length, transposed=int(transposed), lo=lo, hi=hi,
                         ends=int(ends), scale=scale, w=w, **finish)]
    stride = _round_up(across, LANES)  # whole 8-pixel vectors stay in bounds
    plane = rt.buffer("plane", stride * length * 16)
    shape = dict(ps=stride, across=across, len=length, transposed=int(transposed), w=w)
    ev = prog.run("linearise_plane", rt.queue, _grid(stride, length), (GROUP_SIZE, 1),
                  wait_for=ready, image=src.buffer, in_kind=src.kind, channels=channels,
                  cbase=cbase, cg=cg, lut=rt.upload("lut", table, table=True),
                  lut_len=table.shape[1],
                  plane=plane, **shape)
    return [prog.run("integrate_box", rt.queue, grid, (BOX_GROUP_SIZE,), wait_for=[ev],
                     plane=plane, lo=lo, hi=hi, ends=int(ends), scale=scale, **shape,
                     **finish)]


def run_plan(rt: Runtime, plan: BlurPlan, gpu: bool | None = None, *, half: bool | None = None,
             resident_image=None, resident_flow=None,
             resident_out=None) -> np.ndarray | None:
    """The whole pipeline for ``plan`` on ``rt`` (the caller holds ``rt.lock``).

    ``gpu`` forces the GPU (True) or CPU (False) kernel variants; default: the device's type.
    ``half`` allows (True) or forbids (False) half-float storage of the intermediate where
    its error bound holds; default: allowed except for the CPU field kernel.
    ``resident_image`` (a buffer holding the integer image), ``resident_flow`` (a
    ``pyopencl.array.Array``) and ``resident_out`` (a buffer for the output codes) keep data on
    the device; with ``resident_out`` nothing is downloaded and None is returned.
    """
    gpu = rt.gpu if gpu is None else gpu
    img = plan.image
    h, w, channels = img.shape
    src = upload_input(rt, plan, resident_image, gpu)
    out, out_buf = (None, resident_out) if resident_out is not None else output_target(rt, img)
    tap_set = taps.space_invariant_taps(plan)
    box = tap_set.box() if tap_set is not None else None
    # Half storage halves the memory traffic.  The CPU field kernel is bound by instructions,
    # not traffic, and the conversions cost more than they save (PoCL, 4K: 17.6 vs 19.6 MP per
    # CPU-second with float); the taps kernel streams rows and gains (4K diagonal: 60 vs 47).
    if half is None:
        half = gpu or tap_set is not None
    half = half and box is None and half_float.half_storage_ok(plan, src.luts)
    prog = rt.program(half, gpu)
    # The CPU field kernel reads channel planes: a tap's weights then apply lane for lane
    # (no shuffles, no idle fourth channel).  Same values, same size as the RGBA layout.
    planes = tap_set is None and not gpu
    field = None
    lin_buf = None if box is not None else rt.buffer("linear",
                                                     (h + 1) * (w + 1) * 4 * (2 if half else 4))
    done: list = []
    for cbase, cg in response_pack.channel_groups(channels):
        finish = finish_args(rt, plan, cbase, cg, out_buf)
        if box is not None:
            done = integrate_box(rt, prog, plan, src, box, finish, cbase, cg, done)
            continue
        linear = linearise(rt, prog, src, plan, cbase, cg, lin_buf, planes)
        after = linear + done  # the next group reuses the intermediate
        if tap_set is None and field is None:  # queued behind the image: linearise first
            field = upload_flow(rt, plan, src, resident_flow)
        if field is None:
            done = integrate_taps(rt, prog, gpu, plan, src, lin_buf, tap_set, finish, after)
        else:
            done = integrate_field(rt, prog, gpu, plan, src, lin_buf, field, finish, after)
        pyopencl_module().wait_for_events(done)  # host-side tables are re-uploaded per group
    if field is not None:
        check_flow(rt, field)
    if resident_out is not None:
        return None
    return collect_output(rt, plan, out, out_buf, src.bands, done)


def output_target(rt: Runtime, img: np.ndarray) -> tuple[np.ndarray | None, object]:
    """(host array or None, device buffer) for the output codes of ``img`` (H x W x C).
    Devices that share host memory (CPUs) write straight into the returned array: no
    download copy (4K RGB uint8: 25 MB, ~5 % of a box blur)."""
    h, w, channels = img.shape
    out_dtype = _out_dtype(img)
    if rt.unified:
        out = np.empty((h, w, channels), dtype=out_dtype)
        return out, rt.wrap(out)
    return None, rt.buffer("output", h * w * channels * np.dtype(out_dtype).itemsize)


def _out_dtype(img: np.ndarray) -> np.dtype:
    """What the kernels store for ``img``: its integer dtype, else float32."""
    return np.dtype(np.float32) if OUT_KINDS[img.dtype] == OUT_F32 else img.dtype


def collect_output(rt: Runtime, plan: BlurPlan, out: np.ndarray | None, out_buf,
                   bands: list[tuple[int, int]], done: list) -> np.ndarray:
    """The output of ``output_target`` on the host, after ``done``, in the input's layout
    (float64 inputs widened from the float32 the kernels store)."""
    img = plan.image
    if out is not None:
        sync_host(rt, out_buf, out, done)
    else:
        out = np.empty(img.shape, dtype=_out_dtype(img))
        download(rt, out, out_buf, bands, done)
    if img.dtype == np.float64:
        out = out.astype(np.float64)
    return plan.finish(out)


def sync_host(rt: Runtime, buf, out: np.ndarray, done: list) -> None:
    """Make the kernels' writes to ``buf`` (a USE_HOST_PTR buffer over ``out``) visible in
    ``out``: map it after ``done`` (PoCL uses ``out`` itself, aligned or not: no copy; the
    map is what the OpenCL specification asks for), then unmap."""
    cl = pyopencl_module()
    mapped, _ = cl.enqueue_map_buffer(rt.queue, buf, cl.map_flags.READ, 0, (out.nbytes,),
                                      np.uint8, wait_for=done, is_blocking=True)
    mapped.base.release(queue=rt.queue)
    rt.queue.finish()


def check_flow(rt: Runtime, field: FieldInput) -> None:
    """Refuse the request when the device counted bad flow components (module
    Conventions)."""
    counts = np.zeros(2, np.int32)
    pyopencl_module().enqueue_copy(rt.queue, counts, field.bad, is_blocking=True)
    if counts.any():
        raise InputError(flow_error(int(counts[0]), int(counts[1])))
