"""Manifests for the shared measured data (``clblur.io.data_dir()``), written outside it.

``python -m clblur.study.shared OUTDIR`` writes ``memorial.json``, ``levin2009.json`` and
the GoPro frame-stack manifests into ``OUTDIR``; image paths point into the data folder,
which is never written to.  The GoPro set has no real long exposure, so the 30 fps "long"
frames are built here from 8 consecutive 240 fps frames in two ways, each written as PNG into
``OUTDIR``: the code-value mean (what simple dataset generators do) and the mean in the
gamma-2.2 linear domain (Nah et al. 2017's synthesis).
"""

from __future__ import annotations

import sys
from fractions import Fraction
from pathlib import Path

import numpy as np

from clblur.io import data_dir, read_image, write_image
from clblur.manifest import write_manifest

GOPRO_STACK = 8  # 240 fps frames per 30 fps exposure
GOPRO_STEP = 4  # start of consecutive stacks, frames


def memorial(out: Path, data: Path) -> Path:
    times = (data / "memorial" / "shutter_times.txt").read_text().split()
    files = sorted((data / "memorial").glob("memorial*.png"))
    if len(times) != len(files):
        raise ValueError(f"memorial: {len(files)} images but {len(times)} shutter times")
    doc = {"kind": "exposure-series",
           "images": [{"path": str(f), "exposure": float(Fraction(t))}
                      for f, t in zip(files, times, strict=True)]}
    path = out / "memorial.json"
    write_manifest(path, doc)
    return path


def levin(out: Path, data: Path) -> Path:
    base = data / "levin2009"
    pairs = []
    for i in range(1, 5):
        for j in range(1, 9):
            pairs.append({"static": str(base / "gt" / f"im{i}.png"),
                          "blurred": str(base / f"im{i}_kernel{j}_img.png"),
                          "psf": str(base / "gt" / f"kernel{j}.png")})
    path = out / "levin2009.json"
    write_manifest(path, {"kind": "blur-pair", "pairs": pairs})
    return path


def gopro(out: Path, data: Path) -> list[Path]:
    files = sorted((data / "gopro240" / "frames").glob("*.png"))
    frames = [read_image(f) for f in files]
    paths = []
    for how in ("code_mean", "gamma22_mean"):
        stacks = []
        for s in range(0, len(files) - GOPRO_STACK + 1, GOPRO_STEP):
            codes = np.stack(frames[s:s + GOPRO_STACK]).astype(np.float64)
            if how == "code_mean":  # in code units, so exact halves round half to even
                mean = codes.mean(axis=0)
            else:
                mean = 255.0 * ((codes / 255.0) ** 2.2).mean(axis=0) ** (1 / 2.2)
            long = out / f"gopro_{how}_{s:02d}.png"
            write_image(long, np.rint(mean).astype(np.uint8))
            stacks.append({"frames": [str(f) for f in files[s:s + GOPRO_STACK]],
                           "long": long.name})
        path = out / f"gopro240_{how}.json"
        write_manifest(path, {"kind": "frame-stack", "stacks": stacks})
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m clblur.study.shared OUTDIR", file=sys.stderr)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    data = data_dir(required=True)
    for p in [memorial(out, data), levin(out, data), *gopro(out, data)]:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
