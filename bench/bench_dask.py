"""Dask arrays: each chunk's own halo against one halo for every chunk.

``clblur.dask_array.blur`` grows each chunk of a flow-driven blur by the reach of that chunk's
own vectors; with ``max_displacement`` (the caller's bound, no pass over the flow) every chunk
gets the halo of the largest vector, as ``map_overlap`` needs.  The scene makes the difference
visible: a still frame with one fast object (a square of ``--object`` px moving at each of
``--speeds`` px to the right), the case of a compositing shot or a gigapixel scan with one
moving thing.

Reports, for both: wall time (building the graph, the own halos' pass over the flow included,
and computing), process CPU time, Mpx per CPU-second, the pixels the windows read over the
image's pixels and the largest window (what one task holds); checks that both give the
in-memory blur bit for bit.

Run:  python bench/bench_dask.py [--size 4096] [--chunk 512] [--speeds 200 1000] [--repeat 3]
Prints a Markdown table and writes bench/results_dask.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def scene(size: int, obj: int, speed: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    import cv2

    img = cv2.resize(rng.integers(0, 256, (size // 8, size // 8, 3), dtype=np.uint8),
                     (size, size), interpolation=cv2.INTER_CUBIC)
    flow = np.zeros((size, size, 2), np.float32)
    r0 = c0 = size // 3
    flow[r0:r0 + obj, c0:c0 + obj] = (speed, 0.0)
    return img, flow


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4096, help="image side (px)")
    ap.add_argument("--chunk", type=int, default=512, help="chunk side (px)")
    ap.add_argument("--object", type=int, default=512, help="moving square's side (px)")
    ap.add_argument("--speeds", type=float, nargs="+", default=[200.0, 1000.0],
                    help="its motion (px), one scene each")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--results", default=str(Path(__file__).resolve().parent /
                                              "results_dask.md"))
    args = ap.parse_args()

    import dask
    import dask.array as da
    from results_file import write_results

    import clblur
    from clblur import dask_array

    read = {}
    real = dask_array._blur_window

    def counted(image, motion, **kw):  # the pixels each window reads
        read[kw["chunk"]] = image.shape[0] * image.shape[1]
        return real(image, motion, **kw)

    dask_array._blur_window = counted
    lines = [f"| {args.size} x {args.size} RGB uint8, chunks {args.chunk}, backend "
             f"{args.backend} | wall (s) | CPU (s) | Mpx per CPU-s | pixels read / image | "
             "largest window (Mpx) | identical to in-memory |",
             "|---|---:|---:|---:|---:|---:|---|"]
    ratios = []
    for speed in args.speeds:
        img, flow = scene(args.size, args.object, speed)
        x = da.from_array(img, chunks=(args.chunk, args.chunk, 3))
        ref = clblur.blur(img, flow, backend=args.backend)  # also builds the kernels
        bound = tuple(float(b) for b in np.abs(flow).max(axis=(0, 1)))
        runs = {"own halo per chunk (default)": {},
                "one halo for all (max_displacement)": {"max_displacement": bound}}
        mpx = img.shape[0] * img.shape[1] / 1e6
        got = []
        for label, opts in runs.items():
            walls, cpus = [], []
            for _ in range(args.repeat):
                read.clear()
                t, c = time.perf_counter(), time.process_time()
                with dask.config.set(scheduler="threads"):
                    out = dask_array.blur(x, flow, backend=args.backend, **opts).compute()
                walls.append(time.perf_counter() - t)
                cpus.append(time.process_time() - c)
            same = np.array_equal(out, ref)
            wall, cpu = float(np.median(walls)), float(np.median(cpus))
            got.append((wall, cpu))
            lines.append(f"| {label}, square moving {speed:g} px | {wall:.2f} | {cpu:.2f} | "
                         f"{mpx / cpu:.1f} | {sum(read.values()) / mpx / 1e6:.2f} | "
                         f"{max(read.values()) / 1e6:.2f} | {'yes' if same else 'NO'} |")
            print(lines[-1], flush=True)
        ratios.append(f"{speed:g} px: {got[1][0] / got[0][0]:.2f}x wall, "
                      f"{got[1][1] / got[0][1]:.2f}x CPU")
    dask_array._blur_window = real
    lines.append("")
    lines.append(f"One halo for all / own halos (medians of {args.repeat}): "
                 + "; ".join(ratios) + ".")
    table = "\n".join(lines)
    print(table)
    load = os.getloadavg()[0]
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    head = ("# Dask arrays: each chunk's own halo\n\n"
            f"`python bench/bench_dask.py --size {args.size} --chunk {args.chunk} --object "
            f"{args.object} --speeds {' '.join(f'{v:g}' for v in args.speeds)} --backend "
            f"{args.backend} --repeat {args.repeat}`\n\n"
            f"Machine: {platform.node()}, {platform.machine()}, {os.cpu_count()} logical CPUs, "
            f"load average {load:.1f} at the end; {stamp}.\n\n"
            f"A still frame with one {args.object} px square moving right (anchor centre): "
            "the own-halo windows grow only around the chunks the square covers.  Dask's "
            "threaded scheduler; CPU is the process's (all threads); the own halos' wall "
            "and CPU include their pass over the flow, which max_displacement skips.\n\n")
    write_results(Path(args.results), head + table + "\n")
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
