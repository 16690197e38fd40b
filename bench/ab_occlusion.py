"""Before / after timing of the layered path: two source trees, interleaved runs.

On a shared machine the wall time swings between runs; timing two trees in alternation and
keeping the best of each cell compares them under the same load.  Each run times
``clblur.blur`` on ``bench_occlusion.speed_scene`` (static and panning background), plain and
with ``depth``, on PoCL, in a fresh interpreter with that tree first on the path; with
``--gopro`` also GoPro frame 10 of ``docs/studies/occlusion.md`` (bent path, 360-degree
shutter, DIS flows to frames 2 and 18) plain and with the study's depth proxy.

Run:  python bench/ab_occlusion.py BEFORE_TREE AFTER_TREE [--rounds 2] [--gopro]
(e.g. ``git archive 0ca3731 | tar -x -C /tmp/before``).  Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CHILD = r'''
import json, sys, time
sys.path.insert(0, sys.argv[1])
from bench_occlusion import speed_scene
import clblur
res = {}
for label, pan in (("static", (0.0, 0.0)), ("panning", (16.0, 2.0))):
    img, flow, depth = speed_scene(pan=pan)
    for name, o in (("plain", {}), ("layered", {"depth": depth})):
        clblur.blur(img, flow, "srgb", backend="opencl", **o)
        wall, cpu = [], []
        for _ in range(5):
            t0, c0 = time.perf_counter(), time.process_time()
            clblur.blur(img, flow, "srgb", backend="opencl", **o)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        res[label + " " + name] = (min(wall), min(cpu))
if len(sys.argv) > 2:  # --gopro: frame 10 of docs/studies/occlusion.md with the depth proxy
    import numpy as np
    sys.path.insert(0, "docs/studies")
    import occlusion_study as study
    from clblur import video
    from clblur.flow import FlowEstimator
    from clblur.io import gopro_frames, read_image
    names = gopro_frames()
    frames = [read_image(p) for p in names[2:19:8]]  # frames 2, 10, 18
    est = FlowEstimator("dis")
    bwd, fwd = est(frames[1], frames[0]), est(frames[1], frames[2])
    for name, run in (("plain", lambda: video.blur_frame(frames[1], bwd, fwd, "srgb",
                                                          shutter=360, backend="opencl")),
                      ("layered", lambda: study.depth_blur_frame(frames[1], bwd, fwd,
                                                                  "opencl"))):
        run()
        wall, cpu = [], []
        for _ in range(3):
            t0, c0 = time.perf_counter(), time.process_time()
            run()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        res["GoPro frame 10 " + name] = (min(wall), min(cpu))
print(json.dumps(res))
'''


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--gopro", action="store_true",
                    help="also GoPro frame 10 of docs/studies/occlusion.md, depth proxy "
                         "(needs $CLBLUR_DATA)")
    args = ap.parse_args()
    bench = str(Path(__file__).resolve().parent)  # the scene of this tree, for both
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    best: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.rounds):
        for tag, root in trees.items():
            # the tree first; what the path held already after it (a machine whose
            # packages are found through PYTHONPATH keeps them)
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(
                [str(root)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
            argv = [sys.executable, "-c", CHILD, bench] + (["gopro"] if args.gopro else [])
            out = subprocess.run(argv, env=env, cwd=root,
                                 capture_output=True, text=True, check=True)
            for key, (wall, cpu) in json.loads(out.stdout.splitlines()[-1]).items():
                cell = best.setdefault((tag, key), [float("inf"), float("inf")])
                cell[0], cell[1] = min(cell[0], wall), min(cell[1], cpu)
    print("| tree | background | plain gather | depth layers | ratio wall / CPU |")
    print("|---|---|---|---|---|")
    for tag in trees:
        for scene in ("static", "panning") + (("GoPro frame 10",) if args.gopro else ()):
            p, q = best[(tag, scene + " plain")], best[(tag, scene + " layered")]
            print(f"| {tag} | {scene} | {p[0]:.3f} / {p[1]:.3f} | {q[0]:.3f} / {q[1]:.3f} | "
                  f"{q[0] / p[0]:.1f} / {q[1] / p[1]:.1f} |")


if __name__ == "__main__":
    main()
