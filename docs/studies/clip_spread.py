"""Generated brackets whose clipped pixels do not all read the clip code.

    python docs/studies/clip_spread.py /tmp/clip_spread
    clblur study /tmp/clip_spread/gamma_noise_after \
        --times /tmp/clip_spread/gamma_noise_after/times.txt --report r.json

Each bracket is six 8-bit PNGs one stop apart (240 x 360) of the textured radiance of
``tests/bracket_scenes.py``, with read noise added the way a simple generator adds it: to the
code values, after the clip, then clipped again to 0 .. 255.

``gamma_noise_after``
    A gamma-2.2 camera, 1 code of noise after the clip: clipped pixels read 252 - 255.
``gamma_exact``
    The same camera clipping after its noise (a converter's clip): the control.
``white_balance``
    The gamma-2.2 camera with gains 0.85 / 1 / 0.92 after the clip (piles at 217 / 255 /
    235) and 1.3 codes of noise after them: each pile spread both ways.
``paper_black``
    The paper's camera (Eq. 3, ``k = 2``) above a black level of 0.04 of full scale,
    scaled so that exposure 1 reaches full scale, 1.5 codes of noise after the clip.

For each, the script prints the series' clip level (``ExposureSeries.white_level``), the
model ``clblur calibrate`` picks among gamma-offset and spline, and each model's largest
one-stop transfer error against the true curve (codes 20 up to 3 below the clip level, one
stop down and one up), and the picked model's held-out RMSE (darker target, 1 / 4 stops).
``docs/studies/validation.md`` ("Clipped pixels that read below the pile") quotes it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from bracket_scenes import scene  # noqa: E402

from clblur.calibration import calibrate, load_series  # noqa: E402
from clblur.calibration.fitting import transfer  # noqa: E402
from clblur.io import write_image  # noqa: E402

TIMES = (8.0, 4.0, 2.0, 1.0, 0.5, 0.25)
GAMMA = 2.2
WB = np.array([0.85, 1.0, 0.92])
BLACK, K = 0.04, 2.0


def codes(v: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """Values in [0, 1] plus read noise, rounded and clipped to 8-bit codes."""
    return np.clip(np.rint((v + rng.normal(0.0, noise, v.shape)) * 255), 0, 255).astype(np.uint8)


def bracket(name: str) -> list[np.ndarray]:
    if name == "paper_black":
        rng = np.random.default_rng(3)
        rad = 0.1 * scene(240, 360, 3)
        return [codes(np.minimum(BLACK + (1 - BLACK) * (1 - np.exp(-K * rad * t))
                                 / (1 - np.exp(-K)), 1.0), rng, 0.006) for t in TIMES]
    rng = np.random.default_rng(1)
    rad = 0.25 * scene(240, 360, 1) if name.startswith("gamma") else 0.12 * scene(240, 360, 1)
    frames = []
    for t in TIMES:
        e = np.clip(rad * t, 0, 1)
        if name == "gamma_noise_after":
            frames.append(codes(e ** (1 / GAMMA), rng, 0.004))
        elif name == "gamma_exact":
            v = codes(e ** (1 / GAMMA), rng, 0.004)
            frames.append(np.where(rad * t >= 1, np.uint8(255), v))
        else:  # white_balance
            frames.append(codes(e ** (1 / GAMMA) * WB, rng, 0.005))
    return frames


def true_transfer(name: str, c: int):
    """The true one-stop (or any ratio) transfer of channel ``c``: value -> value."""
    if name == "paper_black":
        scale = (1 - BLACK) / (1 - np.exp(-K))

        def paper(v, r):
            x = -np.log(1 - np.clip((v - BLACK) / scale, 0, 1 - 1e-12)) / K
            return BLACK + scale * (1 - np.exp(-K * x * r))

        return paper
    gain = WB[c] if name == "white_balance" else 1.0
    return lambda v, r: np.clip(v / gain, 0, 1) * r ** (1 / GAMMA) * gain


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path, help="folder for the brackets (created)")
    out = ap.parse_args().out
    print("| bracket | clip level | picked | gamma-offset: worst error | spline: worst error "
          "| held-out darker 1 / 4 stops |")
    print("|---|---|---|---|---|---|")
    for name in ("gamma_noise_after", "gamma_exact", "white_balance", "paper_black"):
        folder = out / name
        folder.mkdir(parents=True, exist_ok=True)
        lines = []
        for i, (frame, t) in enumerate(zip(bracket(name), TIMES, strict=True)):
            write_image(folder / f"im{i}.png", frame)
            lines.append(f"im{i}.png {t}")
        (folder / "times.txt").write_text("\n".join(lines) + "\n")
        series = load_series(folder, folder / "times.txt")
        cal = calibrate(series, ["gamma-offset", "spline"], refit=False)
        top = series.white_level * 255 - 3
        worst = {}
        for model in ("gamma-offset", "spline"):
            errors = []
            for c, curve in enumerate(cal.fits[model].responses):
                v = np.linspace(20, top, 200) / 255
                for r in (0.5, 2.0):
                    want = true_transfer(name, c)(v, r)
                    keep = (want * 255 > 10) & (want * 255 < top)
                    errors.append(np.abs(transfer(curve, v[keep], r) - want[keep]).max())
            worst[model] = 255 * max(errors)
        ev = cal.evaluations[cal.best]
        print(f"| `{name}` | {series.white_level * 255:.0f} | {cal.best} | "
              f"{worst['gamma-offset']:.2f} | {worst['spline']:.2f} | "
              f"{ev['rmse_darker'][1]:.2f} / {ev['rmse_darker'][4]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
