"""Where one layered call's time goes: wall and process CPU time of each stage.

Times ``clblur.blur(..., depth=...)`` on ``bench_occlusion.speed_scene`` (1280 x 720 RGB
uint8, OpenCL on the first device) with every stage wrapped in a timer.  The stages run one
after the other (the threads that overlap them in a normal call are replaced by a serial
stand-in), so each CPU time is that stage's own; indented rows are parts of the stages above
them (the distance transforms counted wherever they run).  Stages a tree does not have are
left out, so the same script profiles an older tree:
``PYTHONPATH=BEFORE python bench/profile_occlusion.py``.

Run:  python bench/profile_occlusion.py [--scene static|panning] [--calls 10]
(``CLBLUR_LAYER_BUILD=device|host`` picks where the layers' transforms run; default: the
device)
Prints a Markdown table (per call, mean over the calls after one warm-up call); the
``kernel`` rows time each OpenCL launch to its completion (their CPU is all the process's
threads, the device's included).
"""

from __future__ import annotations

import argparse
import concurrent.futures as futures
import dataclasses
import importlib
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


class _Serial:
    """A stand-in for ThreadPoolExecutor that runs each task at once, on the caller's
    thread (so that the stages' CPU times do not overlap)."""

    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args, **kwargs):
        done = futures.Future()
        done.set_result(fn(*args, **kwargs))
        return done

    def map(self, fn, items):
        return [fn(x) for x in items]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=("static", "panning"), default="panning")
    ap.add_argument("--calls", type=int, default=10)
    args = ap.parse_args()

    import cv2
    import scipy.ndimage as ndimage
    from bench_occlusion import speed_scene

    import clblur
    from clblur import layer_planes, opencl
    from clblur import layered_exposure as layered
    from clblur.opencl import layered as device_layered

    def optional(name: str):  # a module an older tree does not have: its rows are left out
        try:
            return importlib.import_module(f"clblur.opencl.{name}")
        except ImportError:
            return None
    device_nearest, device_fill, device_region, device_labels = (
        optional(n) for n in ("nearest", "fill", "region", "labels"))

    totals: dict[str, list[float]] = {}

    def timed(name: str, fn):
        def wrapper(*a, **k):
            t, c = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                cell = totals.setdefault(name, [0.0, 0.0])
                cell[0] += time.perf_counter() - t
                cell[1] += time.process_time() - c
        return wrapper

    rows = [  # (module, attribute, label): outer stages first, nested ones indented
        (opencl, "blur", "plain gather (the result outside the region)"),
        (device_layered.layered, "region_mask", "region_mask (tile culling, motion edges)"),
        (device_region, "region_and_reach", "region_and_reach (the region on the device)"),
        (device_layered.layered, "prepare", "prepare (layers on the host)"),
        (layer_planes, "layer_labels", "  layer_labels (depth to layers)"),
        (ndimage, "distance_transform_edt", "  scipy distance transforms (wherever they run)"),
        (layer_planes, "distance_to", "  distance_to (OpenCV exact distances)"),
        (layer_planes, "_inpaint", "  _inpaint (hidden background)"),
        (cv2, "inpaint", "    cv2.inpaint (Navier-Stokes, before 2026-11-24)"),
        (layer_planes, "harmonic_fill", "    harmonic_fill (the fill itself)"),
        (device_labels, "layer_labels", "  device layer_labels"),
        (device_nearest, "nearest_transform", "  device nearest transforms"),
        (device_nearest, "distance", "  device distances"),
        (device_fill, "harmonic_fill", "    device harmonic_fill"),
        (device_layered, "composite", "composite (counts, upload, kernel)"),
        (layered, "counts", "  counts (samples per pixel)"),
    ]
    for module, attr, label in rows:
        if module is not None and hasattr(module, attr):
            setattr(module, attr, timed(label, getattr(module, attr)))
    if hasattr(layer_planes, "HOST"):  # the host's transforms, held by reference: the timed ones
        layer_planes.HOST = dataclasses.replace(
            layer_planes.HOST, nearest=layer_planes._nearest_transform,
            distance=layer_planes.distance_to, fill=layer_planes.harmonic_fill,
            **({"labels": layer_planes.layer_labels}
               if "labels" in {f.name for f in dataclasses.fields(layer_planes.HOST)} else {}))
    # each kernel launch waits for its event: the kernels' own time (wall) as rows too
    from clblur.opencl.program import Program

    launch = Program.run

    def run_and_wait(self, name, queue, *a, **k):
        t, c = time.perf_counter(), time.process_time()
        event = launch(self, name, queue, *a, **k)
        event.wait()
        cell = totals.setdefault(f"kernel {name}", [0.0, 0.0])
        cell[0] += time.perf_counter() - t
        cell[1] += time.process_time() - c
        return event

    Program.run = run_and_wait
    futures.ThreadPoolExecutor = _Serial
    if hasattr(layer_planes, "ThreadPoolExecutor"):
        layer_planes.ThreadPoolExecutor = _Serial

    pan = (16.0, 2.0) if args.scene == "panning" else (0.0, 0.0)
    img, flow, depth = speed_scene(pan=pan)
    clblur.blur(img, flow, "srgb", backend="opencl", depth=depth)  # build, warm caches
    totals.clear()
    t, c = time.perf_counter(), time.process_time()
    for _ in range(args.calls):
        clblur.blur(img, flow, "srgb", backend="opencl", depth=depth)
    whole = (time.perf_counter() - t, time.process_time() - c)
    n = args.calls
    print(f"| stage ({args.scene} background, per call) | wall ms | CPU ms |")
    print("|---|---|---|")
    for _, _, label in rows:
        if label in totals:
            w, cpu = totals[label]
            name = label.replace("  ", "&nbsp;&nbsp;") if label.startswith(" ") else label
            print(f"| {name} | {1000 * w / n:.1f} | {1000 * cpu / n:.1f} |")
    for label in sorted(k for k in totals if k.startswith("kernel ")):
        w, cpu = totals[label]
        print(f"| {label} | {1000 * w / n:.1f} | {1000 * cpu / n:.1f} |")
    print(f"| whole layered call | {1000 * whole[0] / n:.1f} | {1000 * whole[1] / n:.1f} |")


if __name__ == "__main__":
    main()
