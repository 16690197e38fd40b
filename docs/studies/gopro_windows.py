"""Study the GoPro frame-stack windows one manifest at a time and print a markdown table.

    python -m clblur.study.shared /tmp/m
    python docs/studies/gopro_windows.py /tmp/m gamma22_trunc code_round [--windows 1-10]

For each construction (``{how}_{storage}``, see ``clblur.study.shared``) and window ``wNN``
it runs ``clblur.study.study`` on ``gopro240_{how}_{storage}_wNN.json`` with 20 000 target
pixels (validation.md) and prints one row: the verdict, the response estimates with their
intervals, the quantisation offset, and the held-out RMSE of the paper's model and of the
extended one.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from clblur.study import study


def _row(name: str, r: dict, seconds: float) -> str:
    found = {f["effect"]: f for f in r["findings"]}
    effects = ", ".join(r["extended"]["effects"]) or "-"
    resp = "-"
    for e in ("response_shape", "response_imax"):
        f = found.get(e)
        if f and f["significant"]:
            est = f["estimate"]
            resp = f"{e}: gamma {est['gamma']:.3f}"
            if e == "response_imax":
                resp += f", Imax {est['imax_full_scale']:.3g} x full scale"
    q = found.get("quantisation")
    quant = "-"
    if q and q["significant"]:
        lo, hi = q["interval"]["offset_codes"]
        quant = f"{q['estimate']['offset_codes']:.3f} [{lo:.3f}, {hi:.3f}]"
    b, x = r["baseline"]["heldout_rmse"], r["extended"]["heldout_rmse"]
    return (f"| {name} | {effects} | {resp} | {quant} | {b:.3f} | {x:.3f} | "
            f"{100 * (1 - x / b):.0f} % | {seconds:.0f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("manifests", type=Path)
    p.add_argument("constructions", nargs="+")
    p.add_argument("--windows", default="1-10")
    p.add_argument("--max-pixels", type=int, default=20000)
    a = p.parse_args()
    first, last = (int(v) for v in a.windows.split("-"))
    print("| manifest | effects (order joined) | response | quantisation offset (codes) "
          "[95 % CI] | paper RMSE | extended RMSE | cut | s |")
    print("|---|---|---|---|---:|---:|---:|---:|")
    for c in a.constructions:
        for w in range(first, last + 1):
            m = a.manifests / f"gopro240_{c}_w{w:02d}.json"
            t0 = time.perf_counter()
            r = study(m, max_pixels=a.max_pixels).report
            print(_row(m.stem, r, time.perf_counter() - t0), flush=True)


if __name__ == "__main__":
    main()
