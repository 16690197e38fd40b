"""Gigapixel blur in bounded memory, next to the in-memory throughput.

What it does (every file under --workdir, deleted at the end unless --keep):

1. Writes a procedural RGB uint8 image of --width x --height into an uncompressed BigTIFF and a
   per-pixel flow field into a float16 ``.npy`` on disk (both in row bands, so generating them
   needs little memory).  Flow: a smooth analytic field (swirl + shear),
   ``|v| <= --max-motion`` pixels, stored on disk and memory-mapped window by window.
2. Blurs the BigTIFF into another BigTIFF with ``clblur.tiling.blur_file`` in a *child process*
   and reports its wall time, CPU time and peak resident memory (``VmHWM`` of that process,
   which counts mapped file pages as well as the heap; Linux only).
3. Blurs a smaller image of the same content (--small-width x --small-height) in memory with
   ``clblur.blur`` (child process, same backend) for the in-memory throughput, and checks that
   the tiled file path gives the bitwise identical result on it.

Writes a markdown table to --results (default bench/results_large.md).

    python bench/bench_large.py --backend auto --memory-budget 1G --workdir /tmp/clblur-bench
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


# --------------------------------------------------------------------------- synthetic data
def texture(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Procedural RGB uint8 content for pixel rows x cols: gradients, fine stripes, blobs and
    a bright (saturated) grid, so edges of every scale and clipped highlights are present."""
    y = rows[:, None].astype(np.float32)
    x = cols[None, :].astype(np.float32)
    stripes = 0.5 + 0.5 * np.sin(x * 0.35 + 0.2 * y)
    blobs = 0.5 + 0.5 * np.sin(x / 97.0) * np.cos(y / 61.0)
    grad = (x + y) / float(rows.max() + cols.max() + 2)
    img = np.empty((len(rows), len(cols), 3), np.float32)
    img[..., 0] = 0.55 * stripes + 0.45 * grad
    img[..., 1] = 0.7 * blobs + 0.3 * (1 - grad)
    img[..., 2] = 0.5 * stripes * blobs + 0.5 * grad
    grid = ((rows[:, None] % 512) < 6) | ((cols[None, :] % 512) < 6)
    img[grid] = 1.0
    return np.rint(np.clip(img, 0, 1) * 255).astype(np.uint8)


def flow_field(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int],
               max_motion: float) -> np.ndarray:
    """A smooth swirl plus shear, |v| <= max_motion (float32 H x W x 2)."""
    h, w = shape
    y = (rows[:, None].astype(np.float32) / h) * 2 * np.pi
    x = (cols[None, :].astype(np.float32) / w) * 2 * np.pi
    a = max_motion / np.sqrt(2.0)
    dx = a * np.sin(3 * y) * np.cos(2 * x)
    dy = a * np.cos(5 * x + y)
    return np.stack(np.broadcast_arrays(dx, dy), axis=-1).astype(np.float32)


def write_inputs(workdir: Path, shape: tuple[int, int], max_motion: float,
                 band: int = 512) -> tuple[Path, Path, float]:
    """BigTIFF image + float16 .npy flow, written band by band; returns (image, flow, s)."""
    import tifffile

    h, w = shape
    img_path, flow_path = workdir / "src.tif", workdir / "flow.npy"
    start = time.perf_counter()
    img = tifffile.memmap(img_path, shape=(h, w, 3), dtype=np.uint8, bigtiff=True,
                          photometric="rgb")
    offset = img.offset
    del img
    flow = np.lib.format.open_memmap(flow_path, mode="w+", dtype=np.float16, shape=(h, w, 2))
    flow_offset = flow.offset
    del flow
    from clblur.io import MappedRaster

    img = MappedRaster(img_path, np.uint8, (h, w, 3), offset, writable=True)
    flow = MappedRaster(flow_path, np.float16, (h, w, 2), flow_offset, writable=True)
    cols = np.arange(w)
    for r in range(0, h, band):
        rows = np.arange(r, min(r + band, h))
        img[r:r + len(rows)] = texture(rows, cols)
        flow[r:r + len(rows)] = flow_field(rows, cols, shape, max_motion).astype(np.float16)
    return img_path, flow_path, time.perf_counter() - start


# --------------------------------------------------------------------------- child runs
CHILD = r"""
import json, os, resource, sys, time
import numpy as np
args = json.loads(sys.argv[1])
import clblur
# Warm up: build the kernels (and fill PoCL's cache) outside the timed region.
clblur.blur(np.zeros((16, 16, 3), np.uint8), np.ones((16, 16, 2), np.float32),
            backend=args["backend"])
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
if args["mode"] == "file":
    from clblur.tiling import blur_file
    c = cpu()
    t = time.perf_counter()
    run = blur_file(args["src"], args["dst"], args["flow"], backend=args["backend"],
                    memory_budget=args["budget"])
    info = {"seconds": time.perf_counter() - t, "backend": run.backend, "tile": run.tile,
            "tiles": run.tiles, "halo": run.halo, "cpu_seconds": cpu() - c}
else:
    import tifffile
    from clblur.blur import resolve_backend
    image = tifffile.imread(args["src"])
    flow = np.load(args["flow"]).astype(np.float32)
    c = cpu()
    t = time.perf_counter()
    out = clblur.blur(image, flow, backend=args["backend"])
    info = {"seconds": time.perf_counter() - t, "backend": resolve_backend(args["backend"])}
    info["cpu_seconds"] = cpu() - c
    tifffile.imwrite(args["dst"], out, photometric="rgb")
# VmHWM: peak RSS of this process's own address space.  ru_maxrss is no good here: Linux
# carries it over execve from the forked copy of the parent, so the child would report the
# bench's own (input-generating) peak.
hwm = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")]
info["peak_rss_bytes"] = int(hwm[0].split()[1]) * 1024
info["load_after"] = os.getloadavg()[0]
print("RESULT " + json.dumps(info))
"""


def child(**args) -> dict:
    env = dict(os.environ, CLBLUR_QUIET="1",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", CHILD, json.dumps(args)], env=env,
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def same_pixels(a: Path, b: Path) -> bool:
    import tifffile

    return bool(np.array_equal(tifffile.imread(a), tifffile.imread(b)))


# --------------------------------------------------------------------------- working set
WORKING_SET_TITLE = "## Working set of the numpy reference per window pixel"


def reference_working_set(side: int = 512) -> list[tuple[str, float]]:
    """Peak bytes per pixel ``tracemalloc`` sees while the numpy reference blurs a
    side x side RGB uint8 window (what ``clblur.tiling.window_bytes_per_px`` must bound)."""
    import tracemalloc

    from clblur import reference
    from clblur.request import make_plan
    from clblur.tiling import window_bytes_per_px

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (side, side, 3), dtype=np.uint8)
    flow = flow_field(np.arange(side), np.arange(side), (side, side), 8.0)
    rows = []
    for label, motion in (("uniform (5, 2)", (5.0, 2.0)), ("per-pixel flow", flow)):
        plan = make_plan(img, motion)
        tracemalloc.start()
        reference.blur(plan)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        rows.append((label, peak / side**2))
    rows.append(("estimate used for tiling (flow)", float(window_bytes_per_px(3, 1, True))))
    return rows


def write_working_set(path: Path) -> None:
    from clblur.io import atomic_write_text

    text = path.read_text() if path.is_file() else ""
    text = text.split(WORKING_SET_TITLE)[0].rstrip("\n")
    lines = ["", "", WORKING_SET_TITLE, "",
             "    python bench/bench_large.py --working-set-only", "",
             "| 512 x 512 RGB uint8 window | bytes per pixel |", "|---|---:|"]
    lines += [f"| {label} | {v:.0f} |" for label, v in reference_working_set()]
    atomic_write_text(path, text + "\n".join(lines) + "\n")
    print(f"wrote {path}")


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--width", type=int, default=40000)
    p.add_argument("--height", type=int, default=25000)
    p.add_argument("--small-width", type=int, default=4000)
    p.add_argument("--small-height", type=int, default=3000)
    p.add_argument("--max-motion", type=float, default=8.0)
    p.add_argument("--backend", default="auto", choices=["auto", "numpy", "opencl"])
    p.add_argument("--memory-budget", default="1G")
    p.add_argument("--workdir", default="/tmp/clblur-bench-large")
    p.add_argument("--results", default=str(REPO / "bench" / "results_large.md"))
    p.add_argument("--keep", action="store_true", help="keep the generated files")
    p.add_argument("--working-set-only", action="store_true",
                   help="only measure the numpy reference's bytes per window pixel and add "
                        "that section to --results")
    args = p.parse_args(argv)
    sys.path.insert(0, str(REPO))
    if args.working_set_only:
        write_working_set(Path(args.results))
        return 0

    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    need = args.width * args.height * (3 + 3 + 4) + args.small_width * args.small_height * 20
    free = shutil.disk_usage(work).free
    if free < need * 1.05:
        raise SystemExit(f"{work}: {free / 2**30:.1f} GiB free, need {need / 2**30:.1f} GiB")
    try:
        rows = []
        for label, shape in (("small", (args.small_height, args.small_width)),
                             ("large", (args.height, args.width))):
            d = work / label
            d.mkdir(exist_ok=True)
            src, flow, gen_s = write_inputs(d, shape, args.max_motion)
            print(f"{label}: wrote {shape[1]} x {shape[0]} inputs in {gen_s:.1f} s", flush=True)
            tiled = child(mode="file", src=str(src), dst=str(d / "tiled.tif"), flow=str(flow),
                          backend=args.backend, budget=args.memory_budget)
            tiled.update(label=label, shape=shape, mode=f"tiled, budget {args.memory_budget}")
            rows.append(tiled)
            print(tiled, flush=True)
            if label == "small":
                mem = child(mode="memory", src=str(src), dst=str(d / "memory.tif"),
                            flow=str(flow), backend=args.backend)
                mem.update(label=label, shape=shape, mode="in memory (clblur.blur)")
                tiled["identical"] = same_pixels(d / "tiled.tif", d / "memory.tif")
                rows.insert(0, mem)
                print(mem, flush=True)
            if not args.keep:
                shutil.rmtree(d)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    write_results(Path(args.results), rows, args, argv)
    return 0


def write_results(path: Path, rows: list[dict], args, argv) -> None:
    from clblur.io import atomic_write_text

    cmd = "python bench/bench_large.py " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        "# Large images: tiled blur in bounded memory",
        "",
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.node()} "
        f"({os.cpu_count()} CPUs, shared with other jobs; {platform.machine()}), with",
        "",
        f"    {cmd.strip()}",
        "",
        f"Content: procedural RGB uint8; motion: per-pixel float16 flow on disk (smooth swirl + "
        f"shear, |v| <= {args.max_motion:g} px, anchor center, default samples "
        "ceil(|v|)+1).  Peak RSS is `VmHWM` (/proc/self/status) of the child process that "
        "blurred, mapped file pages included (not `ru_maxrss`, which Linux carries over exec "
        "from the forked parent, so a child would report the bench's own peak); times "
        "exclude generating the inputs, a warm-up blur that builds the kernels, and, for the "
        "in-memory row, reading and writing the files.",
        "",
        "Wall time depends on what else the shared CPUs run (1-minute load average after "
        "each run in the last column); CPU time (user + system, all threads) is the steadier "
        "figure for comparing rows.",
        "",
        "| image | mode | backend | tiles (size) | wall (s) | Mpx/s wall | CPU (s) | "
        "Mpx per CPU-s | peak RSS (MiB) | identical to in-memory | load |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        h, w = r["shape"]
        mpx = h * w / 1e6
        tiles = f"{r['tiles']} ({r['tile'][0]} x {r['tile'][1]})" if "tiles" in r else "-"
        ident = {True: "yes", False: "NO"}.get(r.get("identical"), "-")
        lines.append(f"| {w} x {h} ({mpx:,.1f} Mpx) | {r['mode']} | {r['backend']} | {tiles} | "
                     f"{r['seconds']:.1f} | {mpx / r['seconds']:.2f} | "
                     f"{r['cpu_seconds']:.1f} | {mpx / r['cpu_seconds']:.2f} | "
                     f"{r['peak_rss_bytes'] / 2**20:,.0f} | {ident} | {r['load_after']:.1f} |")
    small_tiled = next((r for r in rows if r["label"] == "small" and "tiles" in r), None)
    if small_tiled is not None:
        lines += ["", "The tiled run on the small image is checked bitwise against the in-memory "
                  "blur (last column)."]
    atomic_write_text(path, "\n".join(lines) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
