"""Four exposure brackets of cameras nobody here calibrated, rendered from real radiance.

    python docs/studies/rendered_brackets.py /tmp/brackets
    clblur calibrate /tmp/brackets/cam_b.json -o cam_b.json
    clblur study /tmp/brackets/cam_b.json --report cam_b-study.json

Four GoPro frames of ``$CLBLUR_DATA/gopro240/frames`` (real scenes, their sRGB codes
linearised) are the radiance, shaped so that part of every bracket clips: an illumination
ramp of 1 - 20x across the frame, or a window 30x brighter.  Each camera then takes five
images one stop apart (960 x 540) with shot and read noise:

``cam_a``
    A JPEG engine: sRGB, a different exponent per channel (1.00 / 1.05 / 0.96) and an
    S-shaped contrast curve of a different strength per channel, JPEG quality 92.  The
    manifest gives the nominal times 1/30 .. 1/500 s (true ratios exactly 2).
``cam_b``
    A linear raw-like sensor: 16-bit PNG, black level 1024 of 65 535.
``cam_c``
    The paper's camera: ``v = 1 - exp(-x)`` (Eq. 3), 8-bit PNG, shot noise only.
``cam_d``
    A video-range camera: gamma 2.2 into codes 16 .. 235 (studio range, as a video frame
    grab stores it), 8-bit PNG; it clips at 235, below full scale.

``validation.md`` (the clipped-sources section and the free curves' toe) reads these: the
truth is known, the radiance is not generated.  The seeds are fixed, so the files are the
same on every run.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from clblur.responses import response

H, W = 540, 960
RELATIVE = np.array([1, 1 / 2, 1 / 4, 1 / 8, 1 / 16])  # true exposures, longest = 1
S_AMP = np.array([0.22, 0.28, 0.18])  # cam_a: S-curve strength per channel
G_EXTRA = np.array([1.00, 1.05, 0.96])  # cam_a: exponent per channel before the encoding
CAM_A_TIMES = [1 / 30, 1 / 60, 1 / 125, 1 / 250, 1 / 500]  # nominal, as a camera reports
CAM_B_BLACK = 1024


def srgb_decode(code: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes to linear light (the library's curve)."""
    return response("srgb").inverse(code / 255.0)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def radiance(frames: Path, name: str, light: np.ndarray, median: float) -> np.ndarray:
    """A GoPro frame linearised, lit by ``light``, scaled to ``median`` at the longest
    exposure."""
    im = Image.open(frames / name).convert("RGB").resize((W, H), Image.LANCZOS)
    lum = srgb_decode(np.asarray(im, np.float64)) * light
    return lum * (median / np.quantile(lum, 0.5))


def curve_a(x: np.ndarray, c: int) -> np.ndarray:
    y = srgb_encode(np.clip(x, 0, 1) ** G_EXTRA[c])
    return y - S_AMP[c] * np.sin(2 * np.pi * y) / (2 * np.pi)  # slope >= 1 - S_AMP > 0


def write_bracket(out: Path, name: str, light: np.ndarray, read_noise: float, encode,
                  save, exposures, rng) -> None:
    """Five images of ``light`` one stop apart: shot noise ``a = 2e-4``, ``read_noise``,
    ``encode`` (linear light to codes), ``save(codes, path)``; a manifest beside them."""
    (out / name).mkdir(parents=True, exist_ok=True)
    entries = []
    for i, rel in enumerate(RELATIVE):
        x = light * rel
        x = x + rng.normal(size=x.shape) * np.sqrt(2e-4 * x + read_noise**2)
        path = out / name / f"{name[-1]}_{i}.{'jpg' if save is _jpeg else 'png'}"
        save(encode(x), path)
        entries.append({"path": str(path), "exposure": float(exposures[i])})
    text = json.dumps({"kind": "exposure-series", "images": entries}, indent=1)
    (out / f"{name}.json").write_text(text)


def _jpeg(codes: np.ndarray, path: Path) -> None:
    Image.fromarray(codes).save(path, quality=92)


def _png(codes: np.ndarray, path: Path) -> None:
    if codes.dtype == np.uint16:  # OpenCV writes 16-bit PNG; it takes BGR
        cv2.imwrite(str(path), codes[..., ::-1].copy())
    else:
        Image.fromarray(codes).save(path)


def _codes(v: np.ndarray, top: float, dtype) -> np.ndarray:
    return np.clip(np.round(v * top), 0, top).astype(dtype)


def render(frames: Path, out: Path) -> None:
    rng = np.random.default_rng(12345)
    yy, xx = np.mgrid[0:H, 0:W]
    ramp = np.exp(np.log(20.0) * xx / (W - 1))[..., None]
    edge = np.minimum.reduce([xx - 600, 880 - xx, yy - 80, 300 - yy]) / 8.0
    window = (1.0 + 29.0 / (1 + np.exp(-edge)))[..., None]

    def jpeg_engine(x):
        return _codes(np.stack([curve_a(x[..., c], c) for c in range(3)], -1), 255, np.uint8)

    def linear_16bit(x):
        black = CAM_B_BLACK / 65535
        return _codes(black + np.clip(x, 0, None) * (1 - black), 65535, np.uint16)

    def video_range(x):
        return _codes((16 + 219 * np.clip(x, 0, 1) ** (1 / 2.2)) / 255, 255, np.uint8)

    def paper_camera(x):
        return _codes(1 - np.exp(-np.clip(x, 0, None)), 255, np.uint8)

    write_bracket(out, "cam_a", radiance(frames, "000166.png", ramp, 0.35), 0.002,
                  jpeg_engine, _jpeg, CAM_A_TIMES, rng)
    write_bracket(out, "cam_b", radiance(frames, "000176.png", window, 0.25), 0.0005,
                  linear_16bit, _png, RELATIVE, rng)
    write_bracket(out, "cam_c", radiance(frames, "000184.png", ramp, 1.2), 0.0,
                  paper_camera, _png, RELATIVE, rng)
    write_bracket(out, "cam_d", radiance(frames, "000180.png", ramp, 0.4), 0.001,
                  video_range, _png, RELATIVE, rng)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path, help="folder to write cam_a .. cam_d and their "
                        "manifests")
    args = parser.parse_args()
    data = Path(os.environ.get("CLBLUR_DATA", Path(__file__).resolve().parents[3]
                               / "shared" / "data"))
    frames = data / "gopro240" / "frames"
    if not frames.is_dir():
        raise SystemExit(f"no GoPro frames at {frames}: set CLBLUR_DATA")
    render(frames, args.out)
    print(f"wrote {args.out}/cam_a.json, cam_b.json, cam_c.json, cam_d.json")


if __name__ == "__main__":
    main()
