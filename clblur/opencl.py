"""OpenCL backend: the pipeline of ``clblur.reference`` in float32 kernels.

Conventions
-----------
* Device selection: the ``device`` argument, else ``$CLBLUR_DEVICE``, else the first GPU, else
  the first device.  A selector is ``"P:D"`` (platform and device indices, as ``clblur info``
  lists them) or a case-insensitive substring of ``"<platform name> <device name>"``.
* Nothing is created at import.  Each process builds one context and queue per selector on
  first use (a forked Dask worker notices the new pid and builds its own); programs are
  cached by build options, device buffers are reused between calls.  No OpenCL object is
  ever handed out, so nothing here needs to be pickled.
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

import os
import re
import threading
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from clblur import opencl_prep as prep
from clblur.motion import Field, sample_counts
from clblur.pixels import linearisation_table
from clblur.plan import BlurPlan

ENV_DEVICE = "CLBLUR_DEVICE"
LANES = 8  # consecutive pixels of a row per work-item, run as vector lanes (integrate.cl)
# Work-items per work-group along x, fixed so that drivers which specialise code per
# work-group size (PoCL) build each kernel once, not once per image size.  Image kernels use
# wide groups (fewer scheduling rounds); the box kernel has one work-item per 8 lines, so it
# uses small groups to keep both cores busy.
GROUP_SIZE = 64
BOX_GROUP_SIZE = 8
KERNEL_FILES = ("response.cl", "integrate.cl")
_OUT_KINDS = {np.dtype(np.uint8): 0, np.dtype(np.uint16): 1, np.dtype(np.float32): 2,
              np.dtype(np.float64): 2}  # float64 output: computed in float32, widened on host
_IN_KINDS = {np.dtype(np.uint8): 0, np.dtype(np.uint16): 1}
_IN_FLOAT = 2

_PROBE_SOURCE = "__kernel void probe(__global float *x) { x[get_global_id(0)] += 1.5f; }"


class OpenCLUnavailable(RuntimeError):
    """No OpenCL platform, or the device cannot create a context."""


class DeviceNotFound(OpenCLUnavailable, ValueError):
    """The selector names no device (bad input: the CLI reports it as one line)."""


def _cl():
    import pyopencl  # imported lazily: `import clblur` must stay free of OpenCL

    return pyopencl


def _selector(device: str | None) -> str:
    sel = device if device is not None else os.environ.get(ENV_DEVICE, "")
    if not isinstance(sel, str):
        raise TypeError(f"OpenCL device selector must be a string, got {sel!r}")
    return sel.strip()


def _enumerate() -> list[tuple[int, int, object, object]]:
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error as e:
        raise OpenCLUnavailable(f"no OpenCL platform found ({e})") from None
    found = []
    for pi, platform in enumerate(platforms):
        try:
            devs = platform.get_devices()
        except cl.Error:
            continue
        found += [(pi, di, platform, d) for di, d in enumerate(devs)]
    return found


def _label(platform, device) -> str:
    return f"{platform.name.strip()} {device.name.strip()}"


def _pick(selector: str):
    found = _enumerate()
    if not found:
        raise OpenCLUnavailable("no OpenCL device found")
    if not selector:
        cl = _cl()
        gpus = [f for f in found if f[3].type & cl.device_type.GPU]
        return (gpus or found)[0]
    m = re.fullmatch(r"(\d+):(\d+)", selector)
    for pi, di, platform, device in found:
        if (m and (pi, di) == (int(m[1]), int(m[2]))) or \
                (not m and selector.lower() in _label(platform, device).lower()):
            return pi, di, platform, device
    names = "; ".join(f"{pi}:{di} {_label(p, d)}" for pi, di, p, d in found)
    raise DeviceNotFound(f"no OpenCL device matches {selector!r} (available: {names})")


def _kernel_source() -> str:
    try:
        root = resources.files("clblur.kernels")
        return "\n".join(root.joinpath(name).read_text() for name in KERNEL_FILES)
    except (ModuleNotFoundError, FileNotFoundError):
        # Source tree: kernels/ sits next to the package and is only a package once installed.
        root = Path(__file__).resolve().parent.parent / "kernels"
        return "\n".join((root / name).read_text() for name in KERNEL_FILES)


@dataclass
class _Runtime:
    """One device's context, queue, programs and reusable buffers (per process)."""

    label: str
    index: str
    device: object
    context: object
    queue: object
    fp64: bool
    unified: bool  # device memory is host memory (CPU devices)
    pid: int = field(default_factory=os.getpid)
    lock: threading.Lock = field(default_factory=threading.Lock)
    programs: dict = field(default_factory=dict)
    kernels: dict = field(default_factory=dict)
    buffers: dict = field(default_factory=dict)

    def build_options(self, half: bool) -> tuple[str, ...]:
        cl = _cl()
        opts = []
        if self.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
            opts.append("-cl-fp32-correctly-rounded-divide-sqrt")  # v / (N-1) exact if integer
        if half:
            opts.append("-DSTORE_HALF")
        if self.fp64:
            opts.append("-DHAVE_FP64")
        return tuple(opts)

    def kernel(self, half: bool, name: str):
        opts = self.build_options(half)
        if opts not in self.programs:
            cl = _cl()
            self.programs[opts] = cl.Program(self.context, _kernel_source()).build(
                options=list(opts))
        key = (opts, name)
        if key not in self.kernels:
            self.kernels[key] = getattr(self.programs[opts], name)
        return self.kernels[key]

    def buffer(self, role: str, nbytes: int):
        """A device buffer of at least ``nbytes`` for ``role``, reused across calls."""
        nbytes = max(int(nbytes), 16)
        old = self.buffers.get(role)
        if old is None or old.size < nbytes:
            cl = _cl()
            old = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, nbytes)
            self.buffers[role] = old
        return old

    def upload(self, role: str, array: np.ndarray):
        array = np.ascontiguousarray(array)
        buf = self.buffer(role, array.nbytes)
        _cl().enqueue_copy(self.queue, buf, array, is_blocking=True)
        return buf

    def share(self, role: str, array: np.ndarray):
        """A read-only view of a large input: the host array itself on devices that share
        host memory (CPUs; no copy), else an upload into the reused ``role`` buffer."""
        if not self.unified:
            return self.upload(role, array)
        cl = _cl()
        return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR,
                         hostbuf=np.ascontiguousarray(array))  # keeps the array alive


_runtimes: dict[str, _Runtime] = {}
_usable: dict[str, tuple[bool, str]] = {}
_registry_lock = threading.Lock()


def _runtime(device: str | None) -> _Runtime:
    sel = _selector(device)
    with _registry_lock:
        rt = _runtimes.get(sel)
        if rt is not None and rt.pid == os.getpid():
            return rt
        cl = _cl()
        pi, di, platform, dev = _pick(sel)
        try:
            ctx = cl.Context([dev])
            queue = cl.CommandQueue(ctx)
        except cl.Error as e:
            raise OpenCLUnavailable(f"cannot create a context on {_label(platform, dev)}: "
                                    f"{e}") from None
        rt = _Runtime(label=_label(platform, dev), index=f"{pi}:{di}", device=dev, context=ctx,
                      queue=queue, fp64=bool(dev.double_fp_config),
                      unified=dev.type == cl.device_type.CPU and bool(dev.host_unified_memory))
        _runtimes[sel] = rt
        return rt


def current_device(device: str | None = None) -> str:
    """``"P:D <platform> <device>"`` of the device the selector picks (creates its context)."""
    rt = _runtime(device)
    return f"{rt.index} {rt.label}"


def _probe(context, queue) -> None:
    """Build and run a tiny kernel; raise if the result is wrong."""
    cl = _cl()
    prog = cl.Program(context, _PROBE_SOURCE).build()
    host = np.arange(8, dtype=np.float32)
    buf = cl.Buffer(context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=host)
    prog.probe(queue, (8,), None, buf)
    got = np.empty_like(host)
    cl.enqueue_copy(queue, got, buf, is_blocking=True)
    if not np.array_equal(got, host + 1.5):
        raise OpenCLUnavailable("probe kernel returned wrong values")


def usable(device: str | None = None) -> tuple[bool, str]:
    """Whether the selected device builds and runs a tiny kernel; (ok, device or reason).

    The answer is cached per selector for the life of the process."""
    sel = _selector(device)
    if sel in _usable:
        return _usable[sel]
    try:
        rt = _runtime(sel)
        with rt.lock:
            _probe(rt.context, rt.queue)
        answer = (True, f"{rt.index} {rt.label}")
    except ImportError as e:
        answer = (False, f"pyopencl is not importable ({e})")
    except OpenCLUnavailable as e:
        answer = (False, str(e))
    except Exception as e:  # noqa: BLE001 - any driver failure means "not usable"
        answer = (False, f"{type(e).__name__}: {e}")
    _usable[sel] = answer
    return answer


def _device_type(bits: int) -> str:
    cl = _cl()
    names = [name for name in ("GPU", "CPU", "ACCELERATOR", "CUSTOM")
             if bits & getattr(cl.device_type, name)]
    return " | ".join(names) or str(bits)


def devices() -> list[dict]:
    """Every OpenCL device with its properties and whether it builds and runs a kernel."""
    cl = _cl()
    rows = []
    try:
        found = _enumerate()
    except OpenCLUnavailable:
        return rows
    for pi, di, platform, dev in found:
        row = {"index": f"{pi}:{di}", "platform": platform.name.strip(),
               "device": dev.name.strip(), "type": _device_type(dev.type),
               "version": dev.version.strip(), "fp64": bool(dev.double_fp_config)}
        try:
            ctx = cl.Context([dev])
            _probe(ctx, cl.CommandQueue(ctx))
            row.update(works=True, error="")
        except Exception as e:  # noqa: BLE001 - report, do not raise
            row.update(works=False, error=f"{type(e).__name__}: {e}")
        rows.append(row)
    return rows


def blur(plan: BlurPlan, device: str | None = None) -> np.ndarray:
    """Run ``plan`` on the selected OpenCL device; same output layout as the reference."""
    rt = _runtime(device)
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


def _upload_input(rt: _Runtime, plan: BlurPlan, img: np.ndarray) -> _Input:
    if img.dtype.kind == "u":
        luts = np.stack([linearisation_table(r, img.dtype, plan.saturation)
                         for r in plan.responses])
        return _Input(rt.share("image", img), _IN_KINDS[img.dtype], luts,
                      float(np.max(np.abs(luts))))
    linear = prep.linearise_float_image(img, plan.responses, plan.saturation)
    return _Input(rt.share("image", linear), _IN_FLOAT, None, float(np.max(np.abs(linear))))


def _run(rt: _Runtime, plan: BlurPlan) -> np.ndarray:
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
        buckets = (prep.quantisation_buckets(thresholds) if img.dtype == np.uint8
                   else np.zeros(4, np.int32))
        store_args = (rt.upload("resp", params), rt.upload("tables", tables),
                      rt.upload("thresholds", thresholds), rt.upload("buckets", buckets),
                      out_buf, np.int32(out_kind),
                      np.int32(channels), np.int32(cbase), np.int32(cg))
        integrate(cbase, cg, store_args)
    _cl().enqueue_copy(rt.queue, out, out_buf, is_blocking=True)
    if img.dtype == np.float64:
        out = out.astype(np.float64)
    return plan.finish(out)


def _integrator(rt: _Runtime, plan: BlurPlan, src: _Input):
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
