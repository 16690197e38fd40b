"""Layered exposure: accuracy against sub-frame truth, and its cost against the plain gather.

Accuracy: every scene of ``tests/layered_scenes.py`` (textured discs over a textured static
background, two crossings, a static one), truth = K sub-frame renders with exact occlusion
averaged in linear light; PSNR (sRGB-encoded float, peak 1) over the swept region for the
gather, speed-ordered layers, depth-ordered layers and depth layers with the clean plate.

Speed: a 1280 x 720 RGB uint8 frame (textured background, static or panning, two textured
discs moving 26 and 40 px over the shutter, the faster one behind) with a per-pixel flow and a
depth map; median wall time and median process CPU time (all threads) of ``clblur.blur``
with and without ``depth`` on the chosen backend (PoCL here).

Size sweep: one textured disc of radius R (8 - 128 px) moving 0.4 R px over the static
frame: what the layered call adds to the gather as the object and the layers' crop grow,
fitted as a fixed part plus a part per crop pixel.

Curved path: ``clblur.video.blur_frame`` of GoPro frame 10 (``$CLBLUR_DATA/gopro240``, DIS
flows to frames 2 and 18, 360-degree shutter, skipped without the data) along the bent path
(the default: two straight halves gathered) and along the parabola through the three
positions (``curved=True``), alone and with the departure ordering.

Run:  python bench/bench_occlusion.py [--backend opencl] [--k 64] [--repeat 5]
          [--timing-only] [--results PATH]
Prints four tables and writes them at the top of bench/results_occlusion.md, or PATH (the notes
below its marker line, written by hand, are kept).  ``--timing-only`` skips the accuracy table
(the numpy reference's, the same on every device): the GPU run writes
``bench/results_occlusion_gpu.md`` that way.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
RESULTS = Path(__file__).resolve().parent / "results_occlusion.md"


def accuracy(k: int) -> list[str]:
    from layered_scenes import psnr, scenes

    import clblur
    from clblur.responses import response

    r = response("srgb")
    rows = ["| scene | gather | speed layers | depth layers | depth layers + clean plate |",
            "|---|---|---|---|---|"]
    for name, sc in scenes().items():
        frame = r.forward(sc.render(sc.anchor))
        truth = r.forward(sc.truth(k))
        flow, depth = sc.maps()
        swept = sc.swept()
        if not swept.any():
            swept[:] = True
        plate = r.forward(sc.background())
        runs = [dict(), dict(depth="speed"), dict(depth=depth),
                dict(depth=depth, background=plate)]
        scores = [psnr(clblur.blur(frame, flow, "srgb", backend="numpy", **o), truth, swept)
                  for o in runs]
        rows.append(f"| {name} | " + " | ".join(
            "exact" if s >= 199 else f"{s:.2f}" for s in scores) + " |")
        print(rows[-1], flush=True)
    return rows


def discs_scene(h: int, w: int, discs, pan: tuple[float, float] = (0.0, 0.0)):
    """Textured background moving by ``pan`` with textured discs ``(cx, cy, radius, (dx, dy),
    depth)`` over it (a nearer disc covers a farther one): (image, flow, depth)."""
    import cv2

    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8), (w, h),
                      interpolation=cv2.INTER_CUBIC)
    img = base.copy()
    flow = np.zeros((h, w, 2), np.float32) + np.float32(pan)
    depth = np.full((h, w), 100.0)
    yy, xx = np.mgrid[0:h, 0:w]
    for (cx, cy, rad, v, z) in discs:
        inside = (np.hypot(xx - cx, yy - cy) < rad) & (z < depth)
        img[inside] = np.roll(base, 37, axis=0)[inside]
        flow[inside] = v
        depth[inside] = z
    return img, flow, depth


def speed_scene(h: int = 720, w: int = 1280, pan: tuple[float, float] = (0.0, 0.0)):
    """Textured background moving by ``pan`` and two textured discs (vectors of 40 and 26 px
    over the shutter), the faster one behind."""
    return discs_scene(h, w, ((500, 360, 110, (40.0, 0.0), 20.0),
                              (620, 330, 90, (-24.0, 6.0), 10.0)), pan)


def spread_scene(h: int = 1080, w: int = 1920):
    """Textured static background and three textured discs far apart (top left, top right,
    bottom middle; vectors of 40, 25 and 32 px): layers built on three small crops, not on
    the frame between them (``clblur.layered_exposure.region_parts``)."""
    return discs_scene(h, w, ((260, 220, 90, (40.0, 0.0), 20.0),
                              (1650, 260, 80, (-24.0, 6.0), 10.0),
                              (960, 840, 100, (10.0, -30.0), 15.0)))


def timing(backend: str, repeat: int) -> list[str]:
    rows = ["| RGB uint8 frame, backend | plain gather: wall / CPU (s) | "
            "depth layers: wall / CPU (s) | ratio wall / CPU | MP per CPU-second, gather / "
            "layers | pixels on the layered path |",
            "|---|---|---|---|---|---|"]
    for label, scene in (
            ("1280 x 720, static background", lambda: speed_scene()),
            ("1280 x 720, background panning 16 px", lambda: speed_scene(pan=(16.0, 2.0))),
            ("1920 x 1080, three objects far apart", spread_scene)):
        rows.append(_timing_row(backend, repeat, label, *scene()))
        print(rows[-1], flush=True)
    return rows


def _medians(backend: str, repeat: int, img, flow, **opts) -> tuple[float, float]:
    """Median wall time and median CPU time of the process (all its threads, PoCL's
    included) of ``clblur.blur``: on a shared machine the wall time also counts other
    people's work."""
    import clblur

    clblur.blur(img, flow, "srgb", backend=backend, **opts)  # build, warm caches
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        clblur.blur(img, flow, "srgb", backend=backend, **opts)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def _timing_row(backend: str, repeat: int, label: str, img, flow, depth) -> str:
    from clblur.layered_exposure import region_mask

    share = region_mask(flow, 0.5).mean()
    plain = _medians(backend, repeat, img, flow)
    layered = _medians(backend, repeat, img, flow, depth=depth)
    mp = img.shape[0] * img.shape[1] / 1e6
    return (f"| {label}, {backend} | {plain[0]:.3f} / {plain[1]:.3f} | "
            f"{layered[0]:.3f} / {layered[1]:.3f} | {layered[0] / plain[0]:.2f} / "
            f"{layered[1] / plain[1]:.2f} | {mp / plain[1]:.1f} / {mp / layered[1]:.1f} | "
            f"{100 * share:.1f} % |")


SIZES = (8, 16, 32, 64, 128)  # disc radii (px) of the size sweep


def size_timing(backend: str, repeat: int) -> list[str]:
    """What the layered call adds to the gather as one moving object grows: a textured disc
    of radius R moving 0.4 R px over a static 1280 x 720 frame.  The layers are built on a
    crop around the region (``clblur.layer_planes.prepare``); the added time is fitted as a
    fixed part plus a part per crop pixel (least squares over the sizes)."""
    from clblur.halo import reach
    from clblur.layer_planes import bounding_box, crop_margin
    from clblur.layered_exposure import region_mask

    rows = ["| disc radius R (px), moving 0.4 R | layers' crop (px) | pixels on the layered "
            "path | plain gather, wall (s) | depth layers, wall (s) | ratio wall / CPU | "
            "added wall (ms) |", "|---|---|---|---|---|---|---|"]
    crops, added = [], []
    for radius in SIZES:
        img, flow, depth = discs_scene(720, 1280, ((640, 360, radius, (0.4 * radius, 0.0),
                                                    10.0),))
        region = region_mask(flow, 0.5)
        box = bounding_box(region, crop_margin(reach(flow, 0.5)))
        crop = (box[0].stop - box[0].start) * (box[1].stop - box[1].start)
        plain = _medians(backend, repeat, img, flow)
        layered = _medians(backend, repeat, img, flow, depth=depth)
        crops.append(crop)
        added.append(layered[0] - plain[0])
        rows.append(f"| {radius} | {crop} | {100 * region.mean():.2f} % | {plain[0]:.3f} | "
                    f"{layered[0]:.3f} | {layered[0] / plain[0]:.2f} / "
                    f"{layered[1] / plain[1]:.2f} | {1000 * added[-1]:.1f} |")
        print(rows[-1], flush=True)
    slope, fixed = np.polyfit(np.asarray(crops, float), np.asarray(added), 1)
    rows += ["", f"Added wall time fitted over the sizes: {1000 * fixed:.1f} ms + "
             f"{1e6 * slope:.2f} us per pixel of the layers' crop."]
    print(rows[-1], flush=True)
    return rows


def curved_timing(backend: str, repeat: int) -> list[str]:
    """Wall and process CPU time of one GoPro frame's blur along the bent and curved paths."""
    from clblur import video
    from clblur.flow import FlowEstimator
    from clblur.io import gopro_frames, read_image

    names = gopro_frames()
    if len(names) < 19:
        return []
    frames = [read_image(names[i]) for i in (2, 10, 18)]
    est = FlowEstimator("dis")
    bwd, fwd = est(frames[1], frames[0]), est(frames[1], frames[2])
    mp = frames[1].shape[0] * frames[1].shape[1] / 1e6
    rows = [f"| GoPro frame 10 ({frames[1].shape[1]} x {frames[1].shape[0]}), {backend} | "
            "wall / CPU (s) | ratio to the bent gather, wall / CPU | MP per CPU-second |",
            "|---|---|---|---|"]
    base = None
    for label, opts in (("bent path, gather (the default)", {}),
                        ("curved path", dict(curved=True)),
                        ("curved path, departure layers",
                         dict(curved=True, layers=True, depth="departure"))):
        video.blur_frame(frames[1], bwd, fwd, "srgb", shutter=360, backend=backend, **opts)
        wall, cpu = [], []
        for _ in range(repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            video.blur_frame(frames[1], bwd, fwd, "srgb", shutter=360, backend=backend, **opts)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        w, c = float(np.median(wall)), float(np.median(cpu))
        base = base or (w, c)
        rows.append(f"| {label} | {w:.3f} / {c:.3f} | {w / base[0]:.1f} / {c / base[1]:.1f} | "
                    f"{mp / c:.1f} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--k", type=int, default=64, help="sub-frames of the truth (default 64)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--timing-only", action="store_true",
                    help="skip the accuracy table (the numpy reference's, device-independent)")
    ap.add_argument("--results", type=Path, default=RESULTS,
                    help=f"results file (default {RESULTS.name})")
    args = ap.parse_args()
    from results_file import write_results

    acc = [] if args.timing_only else [
        f"PSNR (dB, sRGB-encoded, peak 1) over the swept region against K = {args.k} "
        "sub-frames with exact occlusion averaged in linear light (`tests/layered_scenes.py`; "
        "the numpy reference, response srgb, default sample counts):", "",
        *accuracy(args.k), ""]
    spd = timing(args.backend, args.repeat)
    sizes = size_timing(args.backend, args.repeat)
    curved = curved_timing(args.backend, args.repeat)
    load = os.getloadavg()[0]
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    command = " ".join(["python bench/bench_occlusion.py", *sys.argv[1:]])
    text = "\n".join([
        "# Layered exposure: accuracy and cost", "",
        f"`{command}`", "",
        f"Machine: {platform.node()}, {platform.machine()}, {os.cpu_count()} logical CPUs, "
        f"load average {load:.1f} at the end; {stamp}; {_device(args.backend)}.",
        "",
        *acc,
        "Cost against the plain gather (median wall time and median process CPU time of "
        "`clblur.blur`, per-pixel flow, response srgb):", "", *spd, "",
        "Cost by the size of one moving object (the same measures; the region and the "
        "layers' crop grow with the object, the gather's work does not):", "", *sizes, "",
        *(["Curved path against the bent path on real flow (`clblur.video.blur_frame`, "
           "median of the runs; their PSNR against the GoPro truth: docs/studies/occlusion.md, "
           "GoPro table):", "", *curved, ""] if curved else [])])
    write_results(args.results, text)
    print(f"wrote {args.results}")


def _device(backend: str) -> str:
    """The device the timings ran on, in words."""
    if backend != "opencl":
        return "numpy backend"
    from clblur import opencl

    return f"OpenCL device {opencl.current_device()}"


if __name__ == "__main__":
    main()
