"""GPU section of bench_blur.py: written only where the OpenCL device is a GPU (or when asked
with --gpu-section, to exercise it elsewhere).

Rows, 4K field case unless --size says otherwise:
  end-to-end, numpy in / numpy out        clblur.blur(ndarray, ndarray)
  end-to-end, pinned in / numpy out       inputs in clblur.opencl.pinned_empty arrays
  device-resident                         clblur.blur(pyopencl Array, pyopencl Array)
  upload / kernel / download split        the copies timed alone, the kernels as resident
Each is the fastest of --repeats after a warm-up; the device is synchronised in every timing.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from peers import best_time  # noqa: E402  (bench/peers.py, beside this file)

import clblur  # noqa: E402
from clblur import opencl  # noqa: E402
from clblur.io import atomic_write_text  # noqa: E402

__all__ = ["gpu_section"]


def gpu_section(args, img: np.ndarray, flow: np.ndarray, source: str, mean_n: float) -> None:
    """Time the GPU paths and write ``args.gpu_out``."""
    import pyopencl as cl
    import pyopencl.array as cla

    rt = opencl.runtime(args.device)
    dev = rt.device
    mp = img.shape[0] * img.shape[1] / 1e6
    rows = []

    def add(what, seconds, note=""):
        rows.append((what, mp / seconds, seconds * 1e3, note))
        print(f"GPU {what:44s} {mp / seconds:9.1f} MP/s {seconds * 1e3:8.2f} ms  {note}",
              flush=True)

    want = clblur.blur(img, flow, backend="opencl", device=args.device)
    add("end-to-end, numpy in / numpy out",
        best_time(lambda: clblur.blur(img, flow, backend="opencl", device=args.device),
              args.repeats))
    p_img = opencl.pinned_empty(img.shape, img.dtype, args.device)
    p_flow = opencl.pinned_empty(flow.shape, flow.dtype, args.device)
    p_img[...], p_flow[...] = img, flow
    add("end-to-end, pinned in / numpy out",
        best_time(lambda: clblur.blur(p_img, p_flow, backend="opencl", device=args.device),
              args.repeats))
    flow16 = flow.astype(np.float16)
    add("end-to-end, numpy in, float16 flow",
        best_time(lambda: clblur.blur(img, flow16, backend="opencl", device=args.device),
              args.repeats), "flow rounded to half by the caller")
    d_img, d_flow = cla.to_device(rt.queue, img), cla.to_device(rt.queue, flow)
    got = clblur.blur(d_img, d_flow, device=args.device).get()
    same = "same codes as numpy in/out" if np.array_equal(got, want) else "DIFFERS"

    def resident():
        clblur.blur(d_img, d_flow, device=args.device)
        rt.queue.finish()
    t_kernel = best_time(resident, args.repeats)
    add("device-resident (kernels only)", t_kernel, same)
    d_buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, img.nbytes + flow.nbytes)

    def upload():
        cl.enqueue_copy(rt.queue, d_buf, p_img)
        cl.enqueue_copy(rt.queue, d_buf, p_flow, dst_offset=img.nbytes)
        rt.queue.finish()
    out_host = opencl.pinned_empty(img.shape, img.dtype, args.device)

    def download():
        cl.enqueue_copy(rt.queue, out_host, d_buf)
        rt.queue.finish()
    t_up, t_down = best_time(upload, args.repeats), best_time(download, args.repeats)
    lines = [
        "# GPU benchmark", "",
        "Command: `" + " ".join(["python bench/bench_blur.py", *sys.argv[1:]]) + "`", "",
        f"- Device: {rt.index} {rt.label}; driver {dev.driver_version}; "
        f"{dev.version.strip()}; {dev.global_mem_size / 2**30:.0f} GiB",
        f"- Image: {img.shape[1]}x{img.shape[0]} RGB uint8 ({source}); per-pixel flow, mean "
        f"N = {mean_n:.1f}; response exp; anchor center",
        f"- Fastest of {args.repeats} runs after a warm-up; every timing ends with the queue "
        "finished", "",
        "| path | MP/s | ms | note |", "|---|---:|---:|---|"]
    lines += [f"| {w} | {r:.1f} | {ms:.2f} | {n} |" for w, r, ms, n in rows]
    lines += ["", "Split of one frame (pinned host memory):", "",
              "| step | ms | GB/s |", "|---|---:|---:|",
              f"| upload image + flow | {t_up * 1e3:.2f} | "
              f"{(img.nbytes + flow.nbytes) / t_up / 1e9:.1f} |",
              f"| kernels (linearise + integrate + finish) | {t_kernel * 1e3:.2f} | |",
              f"| download output | {t_down * 1e3:.2f} | {img.nbytes / t_down / 1e9:.1f} |", ""]
    atomic_write_text(Path(args.gpu_out), "\n".join(lines))
    print(f"wrote {args.gpu_out}")
