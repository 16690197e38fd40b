"""Local tone mapping, hidden in generated exposure series: does the study say what it is?

    python docs/studies/local_tone.py            # about 10 minutes on a shared 2-core box
    python docs/studies/local_tone.py --seeds 1 --strengths 0.5

Each series is six one-stop captures (48 x 64, the virtual camera ``clblur.camera``:
gamma 2.2, shot and read noise) of one ``random_scene``, each capture's light passed through
``clblur.camera.local_tone`` (a region darker than mid-grey lifted, a brighter one held down,
by up to ``exp(strength)``; the surround blurred by 4 px) before the response.  Strength 0 is
the same series without it.  For each series the script prints the significant effects, and
the leftover test's three alternatives (``clblur.study.leftover``): held-out gain (nats per
value), t and whether it counts.  ``docs/studies/validation.md`` ("Local tone mapping: what
the model leaves, by the surround") and ``tests/test_study.py`` quote it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from clblur.camera import Camera, local_tone, random_scene
from clblur.study import study_groups
from clblur.study.series import series_groups

ALTERNATIVES = ("by_code", "by_group", "by_surround")


def series(seed: int, strength: float, shape=(48, 64)) -> tuple[list[np.ndarray], list]:
    """Six one-stop captures of one scene, tone-mapped locally at ``strength``."""
    rng = np.random.default_rng(seed)
    cam = Camera(response="gamma:2.2", noise_a=2e-4, noise_b=2e-6)
    scene = random_scene(rng, shape, 3, low=0.03, high=0.8)
    times = [2.0 ** -k for k in range(6)]
    frames = [cam.capture(local_tone(scene * t, strength, 4.0) / t if strength else scene,
                          t, rng=rng) for t in times]
    return frames, times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--strengths", type=float, nargs="+", default=[0.5, 0.0])
    args = ap.parse_args()
    print("| strength | seed | significant effects | " + " | ".join(
        f"{a}: gain / t" for a in ALTERNATIVES) + " | structure | s |")
    print("|---|---|---|" + "---|" * len(ALTERNATIVES) + "---|---|")
    for strength in args.strengths:
        for seed in args.seeds:
            start = time.perf_counter()
            frames, times = series(seed, strength)
            r = study_groups("exposure-series", series_groups(frames, times)).report
            left = r["leftover"]
            cells = [f"{left[a]['gain']:.4f} / {left[a]['statistic']:.1f}"
                     + (" **yes**" if left[a]["significant"] else "") for a in ALTERNATIVES]
            found = ", ".join(f["effect"] for f in r["findings"] if f["significant"])
            print(f"| {strength:g} | {seed} | {found} | " + " | ".join(cells)
                  + f" | {left['structure']} | {time.perf_counter() - start:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
