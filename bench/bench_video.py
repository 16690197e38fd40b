"""Frames per second of ``clblur video`` at 1080p and 4K, split into decode, flow, blur, encode.

A synthetic clip (a textured scene that pans and rotates, so the flow varies per pixel) is
encoded with libx264 to a temporary .mp4, then blurred with ``clblur.video.blur_video``, whose
per-stage timers give the split.  Flow counts both directions (two DIS runs per frame).

Run:  python bench/bench_video.py [--backend auto] [--frames 6] [--sizes 1080p,4k]
                                  [--scene pan|object] [--layers]
Prints a table and writes bench/results_video.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from fractions import Fraction
from pathlib import Path

import numpy as np

SIZES = {"720p": (720, 1280), "1080p": (1080, 1920), "4k": (2160, 3840)}
RESULTS = Path(__file__).resolve().parent / "results_video.md"


def synthetic_clip(path: Path, size: tuple[int, int], frames: int, fps: int = 30,
                   scene: str = "pan") -> None:
    """``pan``: pan by 1% of the width per frame and rotate 0.5 degree per frame around the
    centre (1080p: 19 px/frame of pan, up to ~10 px more from the rotation at the corners).
    ``object``: a static background with a textured disc (radius 1/8 of the height) crossing
    it at 2% of the width per frame (the case ``--layers`` is for)."""
    import av
    import cv2

    h, w = size
    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8), (w, h),
                      interpolation=cv2.INTER_CUBIC)
    disc = np.ascontiguousarray(base[::-1, ::-1])
    yy, xx = np.mgrid[0:h, 0:w]
    c = av.open(str(path), "w")
    vs = c.add_stream("libx264", rate=fps)
    vs.height, vs.width, vs.pix_fmt = h, w, "yuv420p"
    vs.options = {"crf": "18", "preset": "veryfast"}
    for i in range(frames):
        if scene == "object":
            cx = w / 4 + 0.02 * w * i
            inside = np.hypot(xx - cx, yy - h / 2) < h / 8
            img = np.where(inside[..., None], np.roll(disc, int(0.02 * w * i), axis=1), base)
        else:
            m = cv2.getRotationMatrix2D((w / 2, h / 2), 0.5 * i, 1.0)
            m[0, 2] += 0.01 * w * i
            img = cv2.warpAffine(base, m, (w, h), borderMode=cv2.BORDER_REFLECT)
        f = av.VideoFrame.from_ndarray(img, format="rgb24")
        f.pts, f.time_base = i, Fraction(1, fps)
        c.mux(vs.encode(f))
    c.mux(vs.encode(None))
    c.close()


def bench(size_name: str, frames: int, backend: str, shutter: float, flow: str,
          scene: str, layers: bool) -> dict:
    from clblur.video import blur_video

    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.mp4", Path(tmp) / "out.mp4"
        synthetic_clip(src, SIZES[size_name], frames, scene=scene)
        t0 = time.perf_counter()
        result = blur_video(src, dst, response="srgb", shutter=shutter, flow=flow,
                            backend=backend, layers=layers)
        total = time.perf_counter() - t0
    row = {"size": size_name + (", --layers" if layers else ""), "frames": result.frames,
           "total_s": total}
    row.update({k: v for k, v in result.seconds.items()})
    return row


def table(rows: list[dict]) -> str:
    lines = ["| size | frames | decode fps | flow fps | blur fps | encode fps | overall fps |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        n = r["frames"]
        cells = [f"{n / r[k]:.2f}" if r[k] > 0 else "-"
                 for k in ("decode", "flow", "blur", "encode", "total_s")]
        lines.append(f"| {r['size']} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--sizes", default="1080p,4k")
    ap.add_argument("--shutter", type=float, default=180)
    ap.add_argument("--flow", default="dis")
    ap.add_argument("--scene", choices=["pan", "object"], default="pan")
    ap.add_argument("--layers", action="store_true", help="also time clblur video --layers")
    ap.add_argument("--device", default=None, help="OpenCL device (sets CLBLUR_DEVICE)")
    ap.add_argument("--output", default=str(RESULTS))
    args = ap.parse_args()
    if args.device:
        os.environ["CLBLUR_DEVICE"] = args.device
    rows = [bench(s, args.frames, args.backend, args.shutter, args.flow, args.scene, layers)
            for s in args.sizes.split(",") for layers in ([False, True] if args.layers
                                                          else [False])]
    from clblur.blur import resolve_backend

    try:
        used = resolve_backend(args.backend, args.device)
    except Exception as e:  # report what was asked for if the helper is unavailable
        used = f"{args.backend} ({e})"
    header = (f"`python bench/bench_video.py --backend {args.backend} --frames {args.frames} "
              f"--sizes {args.sizes} --shutter {args.shutter:g} --flow {args.flow} "
              f"--scene {args.scene}{' --layers' if args.layers else ''}`\n\n"
              f"Machine: {platform.node() or '?'}, {platform.processor() or platform.machine()},"
              f" {os.cpu_count()} logical CPUs, load average {os.getloadavg()[0]:.1f} at the "
              f"end (the box is shared); blur backend: {used}; "
              f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.\n\n"
              "Stage fps = frames / seconds spent in that stage (flow: two DIS runs per frame, "
              "forward and backward); overall = frames / wall time of the whole blur_video "
              "call (making the synthetic input is not counted).\n\n")
    text = header + table(rows) + "\n"
    print(text)
    out = Path(args.output)
    previous = out.read_text() if out.exists() else "# clblur video throughput\n\n"
    from clblur.io import atomic_write_text

    atomic_write_text(out, previous.rstrip("\n") + "\n\n" + text)


if __name__ == "__main__":
    main()
