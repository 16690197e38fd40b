"""Peak memory of the layered path (``depth=``) against the plain gather, per pixel.

Why: layered exposure needs the whole image (its layers are cut and ordered over the whole
depth map), so ``--memory-budget`` cannot tile it: a user needs to know what a frame costs.
Each cell runs in a fresh interpreter on OpenCL (PoCL here): the inputs are built and every
kernel is built on a small crop first, then the peak resident set (``VmHWM``) is read before
and after one call; the table gives the growth per pixel of the frame.

Cases: the 1280 x 720 bench frame of ``bench_occlusion.speed_scene`` (two discs, static
background: 5 % of the pixels layered), the 1920 x 1080 frame of
``bench_occlusion.spread_scene`` (three discs far apart: layered on three small crops),
GoPro frame 10 of ``docs/studies/occlusion.md`` (bent
path, 360-degree shutter, the study's depth proxy: 63 % layered) and the same frame's
whole-shutter flow with ``depth="departure"`` (every pixel layered: the worst case).  The
GoPro rows need ``$CLBLUR_DATA`` (``../shared/data``) and are left out without it.

Run:  python bench/bench_layered_memory.py [--out bench/results_layered_memory.md]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

CHILD = r'''
import json, sys
sys.path.insert(0, "bench"); sys.path.insert(0, "docs/studies")
import numpy as np
import clblur

def hwm():  # peak resident set of this process so far (bytes)
    line = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")][0]
    return int(line.split()[1]) * 1024

case, layered = sys.argv[1], sys.argv[2] == "layered"
if case in ("bench frame", "three objects far apart"):
    from bench_occlusion import speed_scene, spread_scene
    img, flow, depth = speed_scene() if case == "bench frame" else spread_scene()
    def run(crop=None):
        c = crop or (slice(None), slice(None))
        return clblur.blur(img[c], flow[c], "srgb", backend="opencl",
                           **({"depth": depth[c]} if layered else {}))
else:
    import occlusion_study as study
    from clblur import video
    from clblur.flow import FlowEstimator
    from clblur.io import gopro_frames, read_image
    frames = [read_image(p) for p in gopro_frames()[2:19:8]]  # frames 2, 10, 18
    est = FlowEstimator("dis")
    bwd, fwd = est(frames[1], frames[0]), est(frames[1], frames[2])
    img = frames[1]
    if case == "GoPro frame 10":
        def run(crop=None):
            c = crop or (slice(None), slice(None))
            if layered:
                return study.depth_blur_frame(img[c], bwd[c], fwd[c], "opencl")
            return video.blur_frame(img[c], bwd[c], fwd[c], "srgb", shutter=360,
                                    backend="opencl")
    else:  # the whole-shutter chord, departure order: every pixel on the layered path
        flow = (fwd - bwd).astype(np.float32)
        def run(crop=None):
            c = crop or (slice(None), slice(None))
            return clblur.blur(img[c], flow[c], "srgb", backend="opencl",
                               **({"depth": "departure"} if layered else {}))
run((slice(300, 396), slice(600, 696)))  # every kernel built, caches filled
before = hwm()
run()
print("RESULT " + json.dumps({"before": before, "after": hwm(),
                              "pixels": img.shape[0] * img.shape[1]}))
'''

CASES = ("bench frame", "three objects far apart", "GoPro frame 10",
         "GoPro frame 10, whole shutter, departure")


def child(case: str, mode: str) -> dict:
    env = dict(os.environ, CLBLUR_QUIET="1",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", CHILD, case, mode], cwd=REPO, env=env,
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{case} / {mode} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results_layered_memory.md")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from clblur.io import gopro_frames

    cases = CASES if gopro_frames() else [c for c in CASES if not c.startswith("GoPro")]
    rows = ["| frame | plain gather: peak growth, MiB (B/px) | depth layers: peak growth, "
            "MiB (B/px) | ratio |", "|---|---|---|---|"]
    print("\n".join(rows), flush=True)
    for case in cases:
        got = {mode: child(case, mode) for mode in ("plain", "layered")}
        cells = []
        for mode in ("plain", "layered"):
            g = got[mode]
            grow = g["after"] - g["before"]
            cells.append(f"{grow / 2**20:.0f} ({grow / g['pixels']:.0f})")
        ratio = (got["layered"]["after"] - got["layered"]["before"]) / max(
            got["plain"]["after"] - got["plain"]["before"], 1)
        rows.append(f"| {case} | {cells[0]} | {cells[1]} | {ratio:.1f} |")
        print(rows[-1], flush=True)
    from results_file import write_results

    head = ("# Peak memory of the layered path\n\n"
            "`python bench/bench_layered_memory.py`: growth of the peak resident set "
            "(`VmHWM`) over one call, after the inputs and every kernel are built, in a fresh "
            "interpreter per cell; OpenCL on PoCL.  The frames are RGB uint8, 1280 x 720 "
            "except the three objects' 1920 x 1080.\n")
    write_results(args.out, head + "\n" + "\n".join(rows) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
