"""Multi-layer renders (``clblur.blur_layers``): cost against the plain gather of one frame.

A 1280 x 720 scene of ``clblur.scenes`` (textured background, a slow near disc and a fast far
one crossing, a spinning rectangle): its sharp frame with the renderer's vectors through
``clblur.blur`` (the plain gather), and its multi-layer render (every object alone, then the
background: four RGBA uint8 layers) through ``clblur.blur_layers``, straight and bent, and
through the peer that blurs each layer alone and merges them with ``over`` afterwards
(``peers.layers_apart_then_over``: the compositor's way without per-sample occlusion).  Best
wall time and best process CPU time (all threads) of ``--repeat`` runs each, and megapixels
of output per CPU-second.  ``blur_layers`` composites only the pixels that a moving layer can
reach (``clblur.render_layers`` Conventions, culling); the still background elsewhere passes
through.

Run:  python bench/bench_render_layers.py [--backend opencl] [--repeat 5]
Prints a table and writes it at the top of bench/results_render_layers.md (the notes
below its marker line, written by hand, are kept).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results_render_layers.md"


def scene():
    from clblur.scenes import Disc, Rect, Scene, SceneObject
    from clblur.scenes.description import Background, wave_texture

    w, h = 1280, 720
    return Scene(w, h, Background(wave_texture(1, (0.16, 0.14, 0.10), 0.6)), (
        SceneObject(Disc(60), wave_texture(2, (0.62, 0.35, 0.18), 0.5), (560, 360), (24, 0),
                    1.0, name="slow, near"),
        SceneObject(Disc(40), wave_texture(3, (0.20, 0.42, 0.55), 0.55), (660, 380),
                    (-80, -10), 2.0, name="fast, far"),
        SceneObject(Rect(160, 70), wave_texture(4, (0.7, 0.66, 0.3), 0.3), (980, 200),
                    (40, 20), 1.5, angle=0.3, spin=0.4, name="box")), "bench")


def timed(fn, repeat: int) -> tuple[float, float]:
    walls, cpus = [], []
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return min(walls), min(cpus)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    import peers

    import clblur
    from clblur.scenes import object_layers, render

    sc = scene()
    r = render(sc, "srgb", np.uint8, samples=2)  # the passes; the exposure is not scored
    layers = object_layers(sc, "srgb", np.uint8)
    straight = [(image, flow) for image, flow, _, _ in layers]
    bent = [(image, (first, second)) for image, _, first, second in layers]
    runs = {
        "plain gather (sharp frame, clblur.blur)":
            lambda: clblur.blur(r.sharp, r.flow, "srgb", backend=args.backend),
        "peer: each layer blurred alone, then over (peers.layers_apart_then_over)":
            lambda: peers.layers_apart_then_over(straight, "srgb", backend=args.backend),
        "blur_layers, 4 layers, straight":
            lambda: clblur.blur_layers(straight, "srgb", backend=args.backend),
        "blur_layers, 4 layers, bent":
            lambda: clblur.blur_layers(bent, "srgb", backend=args.backend),
        "blur_layers, 4 layers, straight, exposure=\"continuous\"":
            lambda: clblur.blur_layers(straight, "srgb", backend=args.backend,
                                       exposure="continuous"),
    }
    for fn in runs.values():  # build the kernels, warm the caches
        fn()
    mp = sc.width * sc.height / 1e6
    rows = ["| run | wall (s) | CPU (s) | ratio to the gather, wall / CPU | MP per CPU-s |",
            "|---|---|---|---|---|"]
    base = None
    for name, fn in runs.items():
        wall, cpu = timed(fn, args.repeat)
        base = base or (wall, cpu)
        rows.append(f"| {name} | {wall:.3f} | {cpu:.3f} | {wall / base[0]:.1f} / "
                     f"{cpu / base[1]:.1f} | {mp / cpu:.1f} |")
    table = "\n".join(rows)
    print(table)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_file import write_results

    write_results(RESULTS, (
        "# Multi-layer renders: cost against the plain gather\n\n"
        f"`python bench/bench_render_layers.py --backend {args.backend} --repeat "
        f"{args.repeat}`\n\n"
        f"Machine: {platform.node()}, {platform.machine()}, {os.cpu_count()} logical CPUs, "
        f"load average {load:.1f} at the end; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}."
        "\n\n1280 x 720 RGB(A) uint8, srgb, best of the runs:\n\n" + table + "\n"))


if __name__ == "__main__":
    main()
