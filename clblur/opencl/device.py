"""OpenCL devices: selection, per-process contexts and queues, programs, reusable buffers.

Conventions
-----------
* Selection: the ``device`` argument, else ``$CLBLUR_DEVICE``, else the first GPU, else the
  first device.  A selector is ``"P:D"`` (platform and device indices, as ``clblur info``
  lists them) or a case-insensitive substring of ``"<platform name> <device name>"``.
* Nothing is created at import (pyopencl itself is imported on first use).  Each process
  builds one context and queue per selector on first use; programs are cached by build
  options, device buffers are reused between calls.  No OpenCL object leaves this module's
  state, so nothing needs pickling.
* Processes: a worker started with ``spawn`` or ``forkserver`` (or forked before this process
  touched OpenCL) builds its own.  A worker forked *after* it did cannot: the drivers' threads
  and device state do not survive ``fork`` (PoCL's workers hung forever in the child's first
  upload), so there OpenCL is unusable, with a message that says why; ``backend="auto"``
  falls back to numpy with its one warning.
* Devices that do not share host memory (GPUs) get two in-order queues (bands of an image
  overlap upload, kernel and download across them) and pinned (``ALLOC_HOST_PTR``) staging
  buffers, reused across calls; CPU devices read the caller's arrays in place.
"""

from __future__ import annotations

import os
import re
import threading
from dataclasses import dataclass, field
from importlib import resources

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.opencl.constants import BOX_RING_CPU, BOX_RING_GPU, build_defines
from clblur.opencl.program import Program, build, kernel_source

__all__ = ["ENV_DEVICE", "DeviceNotFound", "OpenCLUnavailable", "Runtime", "current_device",
           "devices", "pyopencl_module", "runtime", "runtimes", "usable"]

ENV_DEVICE = "CLBLUR_DEVICE"
_PROBE_SOURCE = "__kernel void probe(__global float *x) { x[get_global_id(0)] += 1.5f; }"


class OpenCLUnavailable(RuntimeError):
    """No OpenCL platform, or the device cannot create a context."""


class DeviceNotFound(OpenCLUnavailable, InputError):
    """The selector names no device (bad input: the CLI reports it as one line)."""


def pyopencl_module():
    """pyopencl, imported on first use: `import clblur` must stay free of OpenCL."""
    import pyopencl

    return pyopencl


def _selector(device: str | None) -> str:
    sel = device if device is not None else os.environ.get(ENV_DEVICE, "")
    if not isinstance(sel, str):
        raise InputTypeError(f"OpenCL device selector must be a string, got {sel!r}")
    return sel.strip()


# the process that first called into an OpenCL driver (None: none has in this process line)
_touched_in: int | None = None


def _check_not_forked() -> None:
    """Refuse OpenCL in a process forked after its parent initialised a driver (module
    Conventions): the child would hang in its first command."""
    if _touched_in is not None and _touched_in != os.getpid():
        raise OpenCLUnavailable(
            f"OpenCL was initialised in process {_touched_in} before it forked this one, and "
            "OpenCL drivers do not survive fork; start workers with the 'spawn' method "
            "(multiprocessing.get_context('spawn'); a torch DataLoader's "
            "multiprocessing_context='spawn'), or fork before the first OpenCL call")


def _enumerate() -> list[tuple[int, int, object, object]]:
    global _touched_in
    _check_not_forked()
    cl = pyopencl_module()
    _touched_in = os.getpid()
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
        cl = pyopencl_module()
        gpus = [f for f in found if f[3].type & cl.device_type.GPU]
        return (gpus or found)[0]
    m = re.fullmatch(r"(\d+):(\d+)", selector)
    for pi, di, platform, device in found:
        if (m and (pi, di) == (int(m[1]), int(m[2]))) or \
                (not m and selector.lower() in _label(platform, device).lower()):
            return pi, di, platform, device
    names = "; ".join(f"{pi}:{di} {_label(p, d)}" for pi, di, p, d in found)
    raise DeviceNotFound(f"no OpenCL device matches {selector!r} (available: {names})")


@dataclass
class Runtime:
    """One device's context, queue, programs and reusable buffers (per process)."""

    label: str
    index: str
    device: object
    context: object
    queue: object
    fp64: bool
    unified: bool  # device memory is host memory (CPU devices)
    gpu: bool  # pick the GPU kernel variants (work-group tiles, no 8-lane unroll)
    queues: tuple = ()  # extra in-order queues for overlapping bands (devices with own memory)
    pid: int = field(default_factory=os.getpid)
    lock: threading.Lock = field(default_factory=threading.Lock)
    programs: dict = field(default_factory=dict)
    tables: dict = field(default_factory=dict)  # role -> (buffer, bytes it holds): upload
    buffers: dict = field(default_factory=dict)
    pinned: dict = field(default_factory=dict)

    def build_options(self, half: bool, gpu: bool | None = None) -> tuple[str, ...]:
        """Build options: the shared constants, ``half`` (half-float intermediate), the GPU
        kernel variants (default: this device's type) and the device's capabilities."""
        cl = pyopencl_module()
        opts = list(build_defines())
        if self.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
            opts.append("-cl-fp32-correctly-rounded-divide-sqrt")  # v / (N-1) exact if integer
        if half:
            opts.append("-DSTORE_HALF")
        if self.fp64:
            opts.append("-DHAVE_FP64")
        if self.gpu if gpu is None else gpu:
            opts.append("-DGPU_VARIANT")
        # by the device, not the variant: tests run either variant on any device
        opts.append(f"-DBOX_RING={box_ring(self.device)}")
        return tuple(opts)

    def program(self, half: bool, gpu: bool | None = None) -> Program:
        """The program built with ``build_options(half, gpu)`` (built once, then cached)."""
        opts = self.build_options(half, gpu)
        if opts not in self.programs:
            self.programs[opts] = Program(self.context, kernel_source(), opts)
        return self.programs[opts]

    def built(self, files: tuple[str, ...], *options: str) -> Program:
        """The program of this package's kernel ``files`` (their sources joined in order)
        built with the shared constants (``build_defines``) and ``options``: built once, then
        kept in ``programs``, keyed by the files and the options."""
        opts = (*build_defines(), *options)
        key = (*files, *opts)
        if key not in self.programs:
            root = resources.files("clblur.opencl")
            source = "\n".join(root.joinpath(name).read_text() for name in files)
            self.programs[key] = Program(self.context, source, opts)
        return self.programs[key]

    def all_queues(self) -> tuple:
        """The main queue first, then the extra ones."""
        return (self.queue, *self.queues)

    def buffer(self, role: str, nbytes: int):
        """A device buffer of at least ``nbytes`` for ``role``, reused across calls."""
        nbytes = max(int(nbytes), 16)
        old = self.buffers.get(role)
        if old is None or old.size < nbytes:
            cl = pyopencl_module()
            old = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, nbytes)
            self.buffers[role] = old
        return old

    def upload(self, role: str, array: np.ndarray, *, table: bool = False):
        """Copy ``array`` into the reused ``role`` buffer and return the buffer.  On devices
        with one in-order queue (CPUs) the copy is queued (pyopencl keeps ``array`` alive
        until it is done) and later commands see it; elsewhere it completes before return,
        so kernels on any queue may read it.

        ``table``: ``role`` is a small table that only this method writes (kernels only read
        it), so a copy of the bytes it already holds is skipped (each copy is a queued
        command: ~0.1 ms on PoCL, several per call)."""
        array = np.ascontiguousarray(array)
        buf = self.buffer(role, array.nbytes)
        if table:
            held = self.tables.get(role)
            if (held is not None and held[0] is buf and held[1].dtype == array.dtype
                    and np.array_equal(held[1], array)):
                return buf
            self.tables[role] = (buf, array.copy())
        else:
            self.tables.pop(role, None)
        pyopencl_module().enqueue_copy(self.queue, buf, array, is_blocking=not self.unified)
        return buf

    def staging(self, role: str, nbytes: int) -> np.ndarray:
        """A pinned host array (``ALLOC_HOST_PTR``, mapped) of at least ``nbytes`` bytes for
        ``role``, reused across calls: copies from it run at the bus's full speed."""
        nbytes = max(int(nbytes), 16)
        old = self.pinned.get(role)
        if old is None or old[1].nbytes < nbytes:
            cl = pyopencl_module()
            buf = cl.Buffer(self.context, cl.mem_flags.READ_WRITE | cl.mem_flags.ALLOC_HOST_PTR,
                            nbytes)
            host, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ |
                                            cl.map_flags.WRITE, 0, (nbytes,), np.uint8,
                                            is_blocking=True)
            old = (buf, host)  # the buffer stays mapped for the runtime's life
            self.pinned[role] = old
        return old[1]

    def wrap(self, array: np.ndarray):
        """A writable buffer over ``array`` itself (devices that share host memory): kernels
        write into it in place; map it before reading ``array`` (``backend.sync_host``)."""
        cl = pyopencl_module()
        return cl.Buffer(self.context, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR,
                         hostbuf=array)

    def share(self, role: str, array: np.ndarray):
        """A read-only view of a large input: the host array itself on devices that share
        host memory (CPUs; no copy), else an upload into the reused ``role`` buffer."""
        if not self.unified:
            return self.upload(role, array)
        cl = pyopencl_module()
        return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR,
                         hostbuf=np.ascontiguousarray(array))  # keeps the array alive


_runtimes: dict[str, Runtime] = {}


def box_ring(device) -> int:
    """Taps whose values a work-item of ``integrate_box_codes`` keeps in its private ring on
    ``device`` (a ``pyopencl.Device``): ``BOX_RING_CPU`` on a CPU device, whose threads have
    the stack for it, else ``BOX_RING_GPU``."""
    cl = pyopencl_module()
    return BOX_RING_CPU if device.type & cl.device_type.CPU else BOX_RING_GPU


def runtimes() -> dict[str, Runtime]:
    """The runtimes this process has created so far, by selector (a copy)."""
    return dict(_runtimes)


_usable: dict[tuple[str, int], tuple[bool, str]] = {}
_registry_lock = threading.Lock()


def runtime(device: str | None = None) -> Runtime:
    """The selected device's runtime for this process, created on first use."""
    sel = _selector(device)
    with _registry_lock:
        rt = _runtimes.get(sel)
        if rt is not None and rt.pid == os.getpid():
            return rt
        _check_not_forked()
        cl = pyopencl_module()
        pi, di, platform, dev = _pick(sel)
        try:
            ctx = cl.Context([dev])
            queue = cl.CommandQueue(ctx)
            unified = dev.type == cl.device_type.CPU and bool(dev.host_unified_memory)
            extra = () if unified else (cl.CommandQueue(ctx),)
        except cl.Error as e:
            raise OpenCLUnavailable(f"cannot create a context on {_label(platform, dev)}: "
                                    f"{e}") from None
        rt = Runtime(label=_label(platform, dev), index=f"{pi}:{di}", device=dev, context=ctx,
                      queue=queue, fp64=bool(dev.double_fp_config), unified=unified,
                      gpu=bool(dev.type & cl.device_type.GPU), queues=extra)
        _runtimes[sel] = rt
        return rt


def current_device(device: str | None = None) -> str:
    """``"P:D <platform> <device>"`` of the device the selector picks (creates its context)."""
    rt = runtime(device)
    return f"{rt.index} {rt.label}"


def _probe(context, queue) -> None:
    """Build and run a tiny kernel; raise if the result is wrong."""
    cl = pyopencl_module()
    prog = build(context, _PROBE_SOURCE)
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
    key = (sel, os.getpid())  # a forked child asks again (module Conventions)
    if key in _usable:
        return _usable[key]
    try:
        rt = runtime(sel)
        with rt.lock:
            _probe(rt.context, rt.queue)
        answer = (True, f"{rt.index} {rt.label}")
    except ImportError as e:
        answer = (False, f"pyopencl is not importable ({e})")
    except OpenCLUnavailable as e:
        answer = (False, str(e))
    except Exception as e:  # noqa: BLE001 - any driver failure means "not usable"
        answer = (False, f"{type(e).__name__}: {e}")
    _usable[key] = answer
    return answer


def _device_type(bits: int) -> str:
    cl = pyopencl_module()
    names = [name for name in ("GPU", "CPU", "ACCELERATOR", "CUSTOM")
             if bits & getattr(cl.device_type, name)]
    return " | ".join(names) or str(bits)


def devices() -> list[dict]:
    """Every OpenCL device with its properties and whether it builds and runs a kernel."""
    cl = pyopencl_module()
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
