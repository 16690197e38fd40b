"""Calibration's check for local tone mapping, on generated brackets: found where it is, not
where it is not.

    python docs/studies/calibration_surround.py            # about 5 minutes on 2 cores
    python docs/studies/calibration_surround.py --seeds 1

Each bracket is ``tests/test_calibration_surround.py``'s: five one-stop exposures (240 x
320) of flat objects on a smooth background, gamma-2.2 codes with read noise; a case adds
local tone mapping (``clblur.camera.local_tone`` at a strength, surround blurred by 10 px,
or by 3 or 40 px, or an edge-aware surround: a bilateral filter of the log light; on the
flat objects or on a fine texture) or one of
the plain brackets' disturbances (high-ISO noise, JPEG storage, half a pixel of
misregistration, an unsharp mask on the codes, a curve that cannot fit).  For each the script
runs ``clblur.calibration.calibrate`` with the model named and prints the surround check
(``clblur.calibration.surround``): t, the root mean square offset beyond the code's own, the
flat values scored, whether it is reported.  ``docs/studies/validation.md`` ("Calibration's
check for local tone mapping") quotes it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))

from test_calibration_surround import bracket  # noqa: E402

from clblur.calibration.compare import calibrate  # noqa: E402

CASES = {
    "plain": ({}, "gamma-offset"),
    "local tone 0.2": ({"strength": 0.2}, "gamma-offset"),
    "local tone 0.3": ({"strength": 0.3}, "gamma-offset"),
    "local tone 0.5": ({"strength": 0.5}, "gamma-offset"),
    "local tone 0.3, JPEG 85": ({"strength": 0.3, "jpeg": 85}, "gamma-offset"),
    "local tone 0.3, surround 3 px": ({"strength": 0.3, "tone_sigma": 3.0}, "gamma-offset"),
    "local tone 0.3, surround 40 px": ({"strength": 0.3, "tone_sigma": 40.0}, "gamma-offset"),
    "local tone 0.3, edge-aware 10 px": ({"strength": 0.3, "edge_aware": True},
                                         "gamma-offset"),
    "local tone 0.3, edge-aware 30 px": ({"strength": 0.3, "edge_aware": True,
                                          "tone_sigma": 30.0}, "gamma-offset"),
    "local tone 0.5, edge-aware 10 px": ({"strength": 0.5, "edge_aware": True},
                                         "gamma-offset"),
    "local tone 0.5, edge-aware 10 px, texture 0.1": ({"strength": 0.5, "edge_aware": True,
                                                       "texture": 0.1}, "gamma-offset"),
    "local tone 0.5, edge-aware 10 px, texture 0.3": ({"strength": 0.5, "edge_aware": True,
                                                       "texture": 0.3}, "gamma-offset"),
    "texture 0.3": ({"texture": 0.3}, "gamma-offset"),
    "noise 4 codes": ({"noise": 0.016}, "gamma-offset"),
    "JPEG 85": ({"jpeg": 85}, "gamma-offset"),
    "shift 0.5 px": ({"shift": 0.5}, "gamma-offset"),
    "sharpened": ({"sharpen": 1.0}, "gamma-offset"),
    "wrong curve (exp)": ({}, "exp"),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = ap.parse_args()
    print("| bracket | model | seed | t | offset (codes, rms) | flat values (in two or more "
          "surrounds) | verdict |")
    print("|---|---|---|---|---|---|---|")
    start = time.time()
    for label, (opts, model) in CASES.items():
        for seed in args.seeds:
            r = calibrate(bracket(seed, **opts), [model]).surround
            verdict = ("not tested" if not r["tested"] else "reported" if r["dependent"]
                       else "trace" if r["p_value"] < r["alpha"] else "none")
            print(f"| {label} | {model} | {seed} | {r['statistic']:.2f} | "
                  f"{r['offset_codes']:.2f} | {r['values']} ({r['contrast_values']}) | "
                  f"{verdict} |", flush=True)
    print(f"\n{time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
