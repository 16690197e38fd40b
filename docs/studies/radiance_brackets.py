"""Exposure brackets of a measured radiance map through an sRGB camera: PNG and JPEG copies.

Data nobody here prepared, with a known truth: Memorial's radiance map
(``memorial/radiance_debevec_qhan1028.hdr`` in the shared data), shrunk, scaled so that its
99th percentile is 1, exposed at six times a stop apart (1/16 .. 2), with shot noise (4000
electrons at that percentile) and read noise (0.0005 of full scale), through the sRGB curve,
rounded to 8 bits.  Each frame is written three ways: PNG (lossless), JPEG quality 90 with
4:2:0 chroma and with 4:4:4.  The frames have their nominal times, one white balance, no
black level and the sRGB curve, so a study should find ``response_shape`` (sRGB is not the
paper's Eq. 3) and ``noise``, nothing else.

Run: ``python docs/studies/radiance_brackets.py OUT [--scale 0.5] [--range full|inner]
[--noise on|off]``, then ``clblur study OUT/png --times OUT/times.txt --report r.json`` (or
``OUT/q90_420``, ``OUT/q90_444``).  ``--range inner`` compresses the radiance so that no
value reaches code 0 or 255 (a control).  Measured: docs/studies/validation.md,
"Values at either end censored" and "A JPEG's clipped blocks left out as sources".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from clblur.io import data_dir

TIMES = [2.0**k for k in range(-4, 2)]
ELECTRONS = 4000.0  # at the radiance's 99th percentile, exposure 1
READ_NOISE = 0.0005  # of full scale


def srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB encoding (IEC 61966-2-1) of linear values, clipped to [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--scale", type=float, default=0.5, help="shrink factor (default 0.5)")
    ap.add_argument("--range", choices=("full", "inner"), default="full")
    ap.add_argument("--noise", choices=("on", "off"), default="on")
    args = ap.parse_args(argv)
    root = data_dir()
    hdr = None if root is None else root / "memorial" / "radiance_debevec_qhan1028.hdr"
    if hdr is None or not hdr.is_file():
        print("radiance_brackets: Memorial's radiance map not found; set CLBLUR_DATA",
              file=sys.stderr)
        return 2
    rad = cv2.imread(str(hdr), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64)
    rad = cv2.resize(rad, None, fx=args.scale, fy=args.scale, interpolation=cv2.INTER_AREA)
    rad /= np.percentile(rad, 99)
    if args.range == "inner":
        rad = np.clip(rad, 0.05, 0.45)
    kinds = {"png": ("PNG", {}), "q90_420": ("JPEG", {"quality": 90, "subsampling": 2}),
             "q90_444": ("JPEG", {"quality": 90, "subsampling": 0})}
    for kind in kinds:
        (args.out / kind).mkdir(parents=True, exist_ok=True)
    lines = []
    for i, t in enumerate(TIMES):
        rng = np.random.default_rng(i)
        e = rad * t
        if args.noise == "on":
            e = rng.poisson(e * ELECTRONS) / ELECTRONS + rng.normal(0, READ_NOISE, e.shape)
        codes = np.round(255 * srgb(e)).astype(np.uint8)
        for kind, (fmt, opts) in kinds.items():
            ext = "png" if fmt == "PNG" else "jpg"
            Image.fromarray(codes).save(args.out / kind / f"img{i}.{ext}", fmt, **opts)
        lines.append(f"img{i} {t}\n")
    (args.out / "times.txt").write_text("".join(lines))
    print(f"wrote {len(TIMES)} frames x {len(kinds)} kinds to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
