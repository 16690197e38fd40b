"""Manifests for the shared measured data (``clblur.io.data_dir()``), written outside it.

``python -m clblur.study.shared OUTDIR`` writes ``memorial.json``, ``levin2009.json`` (and
``levin2009_measured.json``: the kernels measured from the pairs), ``canon400d_road.json``
and the GoPro frame-stack manifests into ``OUTDIR``; image paths
point into the data folder, which is never written to.  The GoPro set has no real long
exposure, so the 30 fps "long" frames are built here from 8 consecutive 240 fps frames, as
dataset generators do, in three spaces (code values; gamma-2.2 linear, Nah et al. 2017's
synthesis; sRGB linear) and stored two ways (rounded; truncated), each written as PNG into
``OUTDIR``, one manifest per window and one pooling every fourth window
(``average_frames``, ``gopro``).
"""

from __future__ import annotations

import sys
from fractions import Fraction
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.io import data_dir, gopro_frames, read_image, write_image
from clblur.manifest import ESTIMATE, write_manifest
from clblur.responses import SRGB, Exp, Gamma

__all__ = ["GOPRO_AVERAGES", "GOPRO_STACK", "GOPRO_STEP", "GOPRO_STORAGE", "average_frames",
           "canon", "gopro", "levin", "main", "memorial"]

GOPRO_STACK = 8  # 240 fps frames per 30 fps exposure
GOPRO_STEP = 4  # start of consecutive stacks, frames


def memorial(out: Path, data: Path) -> Path:
    times = (data / "memorial" / "shutter_times.txt").read_text().split()
    files = sorted((data / "memorial").glob("memorial*.png"))
    if len(times) != len(files):
        raise InputError(f"memorial: {len(files)} images but {len(times)} shutter times")
    doc = {"kind": "exposure-series",
           "images": [{"path": str(f), "exposure": float(Fraction(t))}
                      for f, t in zip(files, times, strict=True)]}
    path = out / "memorial.json"
    write_manifest(path, doc)
    return path


def levin(out: Path, data: Path, measured: bool = False) -> Path:
    """The 32 Levin et al. pairs with their stored kernels (``levin2009.json``), or with
    ``measured`` the kernels measured from the pairs (``levin2009_measured.json``,
    ``"psf": "estimate"``)."""
    base = data / "levin2009"
    pairs = []
    for i in range(1, 5):
        for j in range(1, 9):
            pairs.append({"static": str(base / "gt" / f"im{i}.png"),
                          "blurred": str(base / f"im{i}_kernel{j}_img.png"),
                          "psf": ESTIMATE if measured else str(base / "gt" / f"kernel{j}.png")})
    path = out / ("levin2009_measured.json" if measured else "levin2009.json")
    write_manifest(path, {"kind": "blur-pair", "pairs": pairs})
    return path


GOPRO_AVERAGES = ("code", "gamma22", "srgb")  # space the frames are averaged in
GOPRO_STORAGE = ("round", "trunc")  # how the mean is stored as 8 bits


def average_frames(codes: np.ndarray, how: str, storage: str) -> np.ndarray:
    """8-bit long exposure from a stack of 8-bit frames (F x H x W x C), as a dataset
    generator would make it: the mean taken in code values (``code``), in gamma-2.2 linear
    values (``gamma22``, Nah et al. 2017) or in sRGB linear values (``srgb``), stored by
    rounding (half to even) or by truncation (``trunc``, e.g. a C cast of the float mean).
    ``paper``: the paper's own Eq. 3 + Eq. 8 average, rounded: real frames, yet nothing but
    the paper's model is true (null data for the study)."""
    v = codes.astype(np.float64) / 255.0
    if how == "code":  # in code units, so exact halves stay halves (round half to even)
        mean = codes.astype(np.float64).mean(axis=0) / 255.0
    elif how == "gamma22":
        curve = Gamma(2.2)
        mean = curve.forward(curve.inverse(v).mean(axis=0))
    elif how == "srgb":
        curve = SRGB()
        mean = curve.forward(curve.inverse(v).mean(axis=0))
    elif how == "paper":  # Eq. 3 + Eq. 8 exactly (real null data); 255 as clblur.pixels
        top = 1.0 - 1.0 / (4 * 255)
        curve = Exp(1.0)
        mean = curve.forward(curve.inverse(np.minimum(v, top)).mean(axis=0))
    else:
        raise InputError(f"unknown average {how!r}; use code, gamma22, srgb or paper")
    # code values; 1e-9 so exact code-mean halves do not fall a hair under the integer
    x = np.clip(codes.astype(np.float64).mean(axis=0) if how == "code" else mean * 255.0,
                0.0, 255.0)
    if storage == "round":
        return np.rint(x).astype(np.uint8)
    if storage == "trunc":
        return np.floor(x + 1e-9).astype(np.uint8)
    raise InputError(f"unknown storage {storage!r}; use {', '.join(GOPRO_STORAGE)}")


def gopro(out: Path, data: Path) -> list[Path]:
    """Frame-stack manifests from the 240 fps GoPro frames: for every average and storage,
    one manifest per 8-frame window (``gopro240_{how}_{storage}_wNN.json``, window start NN)
    and one pooling the windows that start every ``GOPRO_STEP`` frames
    (``gopro240_{how}_{storage}.json``), plus real null data: ``gopro240_paper_round_wNN``
    (the paper's own average, every ``GOPRO_STEP`` frames).  Long exposures are written as
    PNG into ``out``."""
    files = gopro_frames(data)
    if len(files) < GOPRO_STACK:
        raise InputError(f"gopro240: {len(files)} frames, need at least {GOPRO_STACK}")
    frames = np.stack([read_image(f) for f in files])
    paths = []
    starts = range(0, len(files) - GOPRO_STACK + 1)
    for how in GOPRO_AVERAGES:
        for storage in GOPRO_STORAGE:
            stacks = {}
            for s in starts:
                long = out / f"gopro_{how}_{storage}_{s:02d}.png"
                write_image(long, average_frames(frames[s:s + GOPRO_STACK], how, storage))
                stacks[s] = {"frames": [str(f) for f in files[s:s + GOPRO_STACK]],
                             "long": long.name}
                path = out / f"gopro240_{how}_{storage}_w{s:02d}.json"
                write_manifest(path, {"kind": "frame-stack", "stacks": [stacks[s]]})
                paths.append(path)
            path = out / f"gopro240_{how}_{storage}.json"
            write_manifest(path, {"kind": "frame-stack",
                                  "stacks": [stacks[s] for s in starts[::GOPRO_STEP]]})
            paths.append(path)
    for s in starts[::GOPRO_STEP]:  # real null data: the paper's model built the long frame
        long = out / f"gopro_paper_round_{s:02d}.png"
        write_image(long, average_frames(frames[s:s + GOPRO_STACK], "paper", "round"))
        path = out / f"gopro240_paper_round_w{s:02d}.json"
        write_manifest(path, {"kind": "frame-stack", "stacks": [
            {"frames": [str(f) for f in files[s:s + GOPRO_STACK]], "long": long.name}]})
        paths.append(path)
    return paths


def canon(out: Path, data: Path) -> Path | None:
    """The Canon 400D JPEG bracket (exposure = the file name, in seconds)."""
    base = data / "canon400d_road"
    files = sorted(base.glob("*.JPG"), key=lambda f: float(f.stem)) if base.is_dir() else []
    if not files:
        return None
    path = out / "canon400d_road.json"
    write_manifest(path, {"kind": "exposure-series",
                          "images": [{"path": str(f), "exposure": float(f.stem)}
                                     for f in files]})
    return path


def main(argv: list[str] | None = None) -> int:
    """Write the manifests into OUTDIR; 0 when done, 2 on bad arguments (``--help``: 0)."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m clblur.study.shared",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("outdir", metavar="OUTDIR",
                        help="folder for the manifests and the GoPro long exposures")
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    except SystemExit as e:  # --help (0), or a usage error already printed (2)
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    out = Path(args.outdir)
    out.mkdir(parents=True, exist_ok=True)
    data = data_dir(required=True)
    made = [memorial(out, data), levin(out, data), levin(out, data, measured=True),
            canon(out, data), *gopro(out, data)]
    for p in made:
        if p is not None:
            print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
