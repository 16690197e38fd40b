"""Cameras nobody here calibrated: random response curves from the EMoR span, real radiance.

    CLBLUR_DATA=../shared/data python docs/studies/emor_cameras.py /tmp/emor_cameras [--cameras 10]

Each camera's curve is drawn from Grossberg & Nayar's EMoR model (``$CLBLUR_DATA/crf``: the
mean curve and principal components of 201 measured camera curves), with **8** components:
more than the 5 of ``clblur calibrate``'s ``emor`` family, so no fitted model contains
the truth. Coefficient ``m`` is drawn with standard deviation ``1.2 / m^1.2``;
the three channels share a draw and differ by a quarter of it. Draws that are not strictly
increasing within [0, 1] are redrawn.

The radiance is a GoPro frame (``$CLBLUR_DATA/gopro240``, its sRGB codes linearised), 960 x
540, under an illumination ramp of 1 - 8x across the frame, scaled to a median of 0.3 at the
longest exposure. Each camera takes five exposures one stop apart, with shot noise
(variance ``2e-4 x``) and read noise (``0.001``), clipped and stored as 8-bit PNGs with a
manifest of the true relative exposures.

Each bracket is then calibrated twice with the command line: ``clblur calibrate`` with every
family (the held-out-best curve is written), and ``--model exp``, the paper's Eq. 3. The
score is what a user sees. The 1/4 exposure is blurred along (24, 6) px with the calibrated
curve, with Eq. 3, with an assumed sRGB or gamma 2.2 curve, and in code values. Each result
is compared (PSNR, 8-bit) with the same blur through the camera's true curve.

Writes the brackets, the fitted curves and ``rows.json`` under the output folder and prints a
Markdown table (about 10 min for 10 cameras on the shared 2-core box). Quoted in
``docs/studies/memorial-calibration.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

import clblur
from clblur.responses import response
from clblur.responses.emor import EmorBasis
from clblur.responses.kernel_curves import Table
from clblur.scenes import psnr

H, W = 540, 960
COMPONENTS = 8
RELATIVE = (1, 1 / 2, 1 / 4, 1 / 8, 1 / 16)
PHOTO = 2  # the exposure that is blurred (1/4)
MOTION = (24, 6)
SPECS = (("calibrated", None), ("Eq. 3 calibrated", None), ("sRGB assumed", "srgb"),
         ("gamma 2.2 assumed", "gamma:2.2"), ("code values", "linear"))


def srgb_decode(codes: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes to linear light (the library's curve)."""
    return response("srgb").inverse(codes / 255.0)


def draw_curve(basis: EmorBasis, rng, around: np.ndarray | None = None):
    """EMoR coefficients and the normalised curve on the basis grid: a camera's draw, or
    (``around``) one channel's, a quarter of the spread around the camera's."""
    sigma = 1.2 / np.arange(1, COMPONENTS + 1) ** 1.2
    while True:
        c = (rng.normal(size=COMPONENTS) * sigma if around is None
             else around + 0.25 * rng.normal(size=COMPONENTS) * sigma)
        f = basis.mean + c @ basis.components[:COMPONENTS]
        if np.all(np.diff(f) > 1e-6) and f.min() >= 0.0 and f.max() <= 1.0 + 1e-9:
            return c, (f - f[0]) / (f[-1] - f[0])


def bracket(out: Path, cam: int, frame: Path, truth: list[Table], rng) -> Path:
    """Five PNGs of the frame's radiance through ``truth`` and their manifest."""
    im = Image.open(frame).convert("RGB").resize((W, H), Image.LANCZOS)
    xx = np.mgrid[0:H, 0:W][1]
    lum = srgb_decode(np.asarray(im, np.float64)) * np.exp(np.log(8.0) * xx / (W - 1))[..., None]
    lum *= 0.3 / np.quantile(lum, 0.5)
    folder = out / f"cam{cam}"
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, rel in enumerate(RELATIVE):
        x = lum * rel
        x = np.clip(x + rng.normal(size=x.shape) * np.sqrt(2e-4 * x + 0.001 ** 2), 0.0, 1.0)
        v = np.stack([truth[c].forward(x[..., c]) for c in range(3)], axis=-1)
        path = folder / f"{i}.png"
        Image.fromarray(np.clip(np.round(v * 255), 0, 255).astype(np.uint8)).save(path)
        entries.append({"path": str(path), "exposure": rel})
    manifest = out / f"cam{cam}.json"
    manifest.write_text(json.dumps({"kind": "exposure-series", "images": entries}, indent=1))
    return manifest


def calibrate(manifest: Path, out: Path, models: list[str]) -> Path:
    if not out.exists():
        cmd = [sys.executable, "-m", "clblur.cli", "calibrate", str(manifest), "-o", str(out),
               "--quiet", *(["--model", *models] if models else [])]
        subprocess.run(cmd, check=True, capture_output=True)
    return out


def family(path: Path) -> str:
    doc = json.loads(path.read_text())
    first = doc.get("channels", [doc])[0]
    return first.get("params", {}).get("meta", {}).get("family", first.get("kind", "?"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="folder for the brackets, curves and rows.json")
    ap.add_argument("--cameras", type=int, default=10)
    args = ap.parse_args()
    data = Path(os.environ.get("CLBLUR_DATA", Path(__file__).resolve().parents[3]
                               / "shared" / "data"))
    frames = sorted((data / "gopro240" / "frames").glob("*.png"))
    if not frames or not (data / "crf" / "emor.txt").is_file():
        raise SystemExit(f"no GoPro frames or EMoR basis under {data}: set CLBLUR_DATA")
    basis = EmorBasis.load(data / "crf")
    rng = np.random.default_rng(7)
    rows = []
    for cam in range(args.cameras):
        c0, _ = draw_curve(basis, rng)
        truth = [Table(basis.grid, draw_curve(basis, rng, c0)[1]) for _ in range(3)]
        manifest = bracket(args.out, cam, frames[(cam * 7) % len(frames)], truth, rng)
        best = calibrate(manifest, args.out / f"cam{cam}_best.json", [])
        paper = calibrate(manifest, args.out / f"cam{cam}_exp.json", ["exp"])
        photo = np.asarray(Image.open(args.out / f"cam{cam}" / f"{PHOTO}.png"))
        ref = clblur.blur(photo, MOTION, truth, backend="numpy")
        row = {"camera": cam, "family": family(best)}
        for label, spec in SPECS:
            spec = {"calibrated": str(best), "Eq. 3 calibrated": str(paper)}.get(label, spec)
            row[label] = round(psnr(clblur.blur(photo, MOTION, spec, backend="numpy"), ref), 2)
        rows.append(row)
        print(row, flush=True)
    (args.out / "rows.json").write_text(json.dumps(rows, indent=1) + "\n")
    labels = [label for label, _ in SPECS]
    print("\n| camera | chosen family | " + " | ".join(labels) + " |")
    print("|---|---|" + "---|" * len(labels))
    for row in rows:
        print(f"| {row['camera']} | {row['family']} | "
              + " | ".join(f"{row[k]:.2f}" for k in labels) + " |")
    print("| median | | " + " | ".join(f"{np.median([r[k] for r in rows]):.2f}"
                                       for k in labels) + " |")


if __name__ == "__main__":
    main()
