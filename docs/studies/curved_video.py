"""The curved path (``clblur video --curved``) against the default bent path on the GoPro frames.

Two shutters on the shared 240 fps frames ($CLBLUR_DATA/gopro240), gamma 2.2 truth as in
video.md (the trapezoid-weighted mean of the 240 fps frames the exposure spans, linearised
as clblur does), DIS flows, 360-degree shutter, response srgb, OpenCL (PoCL here):

* flows to frames c - 8 and c + 8 (a 30 fps frame interval), truth over c - 4 .. c + 4,
  centres 8 .. 12 (the frames of video.md and occlusion.md);
* flows to c - 4 and c + 4 (60 fps), truth over c - 2 .. c + 2, centres 4 .. 16: half the
  motion, thirteen frames.

Run:  python docs/studies/curved_video.py    (about 20 s here)
Writes docs/studies/figures/video/curved.json and prints a Markdown table.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from clblur import video
from clblur.flow import FlowEstimator
from clblur.io import gopro_frames, read_image
from clblur.pixels import linearise, normalise, quantise
from clblur.responses import response

OUT = Path(__file__).resolve().parent / "figures" / "video" / "curved.json"
TRUTH = "gamma:2.2"  # video.md's primary truth (Nah et al. 2017 built GOPRO_Large with it)
RESPONSE = "srgb"  # clblur video's default


def truth_exposure(frames: list[np.ndarray], c: int, half: int) -> np.ndarray:
    """The trapezoid-weighted mean over frames ``c - half .. c + half`` in the truth's
    linear domain (video_study.truth_exposure for any span)."""
    r = response(TRUTH)
    w = np.ones(2 * half + 1)
    w[[0, -1]] = 0.5
    w /= w.sum()
    acc = sum(wk * linearise(normalise(frames[c - half + k]), r, np.uint8, 1.0)
              for k, wk in enumerate(w))
    return quantise(r.forward(acc), np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / mse))


def main() -> None:
    names = gopro_frames()
    if not names:
        raise SystemExit("GoPro frames not found ($CLBLUR_DATA/gopro240/frames)")
    frames = [read_image(p) for p in names]
    est = FlowEstimator("dis")
    results = {}
    for step, centres in ((8, range(8, 13)), (4, range(4, len(frames) - 4))):
        rows: dict[str, dict[str, float]] = {"bent path (default)": {}, "curved path": {}}
        for c in centres:
            truth = truth_exposure(frames, c, step // 2)
            bwd, fwd = est(frames[c], frames[c - step]), est(frames[c], frames[c + step])
            for name, curved in (("bent path (default)", False), ("curved path", True)):
                got = video.blur_frame(frames[c], bwd, fwd, RESPONSE, shutter=360,
                                       curved=curved)
                rows[name][str(c)] = psnr(got, truth)
            print(f"flows to c -/+ {step}, frame {c}: "
                  + ", ".join(f"{m} {v[str(c)]:.2f}" for m, v in rows.items()), flush=True)
        gain = [rows["curved path"][c] - rows["bent path (default)"][c]
                for c in rows["curved path"]]
        results[f"flows to c -/+ {step}"] = {
            "per_frame": rows, "mean": {m: float(np.mean(list(v.values())))
                                        for m, v in rows.items()},
            "gain_db": [float(min(gain)), float(max(gain))]}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps({"truth": TRUTH, "response": RESPONSE, "shutter": 360,
                               "results": results}, indent=1) + "\n")
    print("\n| flows | frames | bent path (default) | curved path | gain per frame |")
    print("|---|---|---|---|---|")
    for key, r in results.items():
        frames_scored = list(r["per_frame"]["curved path"])
        print(f"| {key} | {frames_scored[0]} - {frames_scored[-1]} | "
              f"{r['mean']['bent path (default)']:.2f} | {r['mean']['curved path']:.2f} | "
              f"+{r['gain_db'][0]:.2f} to +{r['gain_db'][1]:.2f} |")


if __name__ == "__main__":
    main()
