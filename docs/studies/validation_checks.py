"""Independent checks of the study's verdicts on the shared data, in plain numpy/scipy.

    CLBLUR_DATA=../shared/data python docs/studies/validation_checks.py

Nothing from ``clblur`` is imported: each check rebuilds the prediction under the cause the
study named, directly from the files, so a bug in the study's model cannot confirm itself.
Printed numbers are quoted in ``docs/studies/validation.md``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.signal import convolve2d, correlate2d


def load(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path)).astype(np.float64)


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


def gopro(data: Path) -> None:
    """Long exposure = gamma-2.2 mean of 8 frames, truncated.  Predict it three ways."""
    files = sorted((data / "gopro240" / "frames").glob("*.png"))
    print("GoPro window | Eq.3 (paper) | gamma 2.2 rounded | gamma 2.2 - 0.5 | code mean")
    for s in range(1, 11):
        f = np.stack([load(p) for p in files[s:s + 8]]) / 255.0
        lin = (f ** 2.2).mean(axis=0)
        long = np.floor(np.clip(255.0 * lin ** (1 / 2.2), 0, 255) + 1e-9)  # the stored data
        ok = (long > 0) & (long < 255) & (f.max(axis=0) < 1.0)
        exp3 = 255.0 * (1.0 - np.exp(np.log1p(-np.minimum(f, 1 - 1 / 1020)).mean(axis=0)))
        gam = 255.0 * lin ** (1 / 2.2)
        code = 255.0 * f.mean(axis=0)
        print(f"w{s:02d} | {rmse(long[ok], exp3[ok]):.3f} | {rmse(long[ok], gam[ok]):.3f} | "
              f"{rmse(long[ok], gam[ok] - 0.5):.3f} | {rmse(long[ok], code[ok]):.3f}")


def levin(data: Path) -> None:
    """Blurred = gt (*) kernel, linear in the stored values; per kernel, which orientation?"""
    base = data / "levin2009"
    print("kernel | convolution RMSE | correlation RMSE (flipped) | better")
    lin_conv, lin_best = [], []
    for k in range(1, 9):
        ker = load(base / "gt" / f"kernel{k}.png")
        ker = ker / ker.sum()
        r = max(ker.shape)
        e_conv, e_corr = [], []
        for i in range(1, 5):
            gt = load(base / "gt" / f"im{i}.png")
            bl = load(base / f"im{i}_kernel{k}_img.png")
            best = []
            for op in (convolve2d, correlate2d):
                pred = op(gt, ker, mode="same", boundary="symm")
                # the kernels are crops of unknown origin: best integer shift within 4 px
                errs = [rmse(np.roll(pred, (dy, dx), (0, 1))[r:-r, r:-r], bl[r:-r, r:-r])
                        for dy in range(-4, 5) for dx in range(-4, 5)]
                best.append(min(errs))
            e_conv.append(best[0])
            e_corr.append(best[1])
        c = float(np.sqrt(np.mean(np.square(e_conv))))
        f = float(np.sqrt(np.mean(np.square(e_corr))))
        lin_conv.append(c)
        lin_best.append(min(c, f))
        print(f"{k} | {c:.2f} | {f:.2f} | {'convolution' if c < f else 'correlation'}")
    conv = np.sqrt(np.mean(np.square(lin_conv)))
    best = np.sqrt(np.mean(np.square(lin_best)))
    print(f"all 32 pairs, linear blur: convolution for all {conv:.2f} DN, "
          f"orientation chosen per kernel {best:.2f} DN")


def main() -> None:
    data = Path(os.environ.get("CLBLUR_DATA", "../shared/data"))
    gopro(data)
    levin(data)


if __name__ == "__main__":
    main()
