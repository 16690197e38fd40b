"""Study speed on a 1-megapixel blur pair, and detection limits per effect.

    python bench/bench_study.py speed  [--results bench/results_study.md]
    python bench/bench_study.py limits [--seeds 3] [--noise A] [--effects E ...] [--results FILE]
    python bench/bench_study.py series [--data DIR] [--results FILE]
    python bench/bench_study.py null   [--seeds 40] [--results bench/results_study_null.md]
    python bench/bench_study.py memory [--trees BEFORE .] [--results FILE]
    python bench/bench_study.py pedestal [--seeds 4] [--results bench/results_study_pedestal.md]
    python bench/bench_study.py handover [--seeds 2] [--results bench/results_study_handover.md]

``speed``: renders a 1000 x 1000 RGB pair with the virtual camera (uniform motion (14, 5) px,
a 15 % exposure-gain mismatch, then a 1000 x 1000 PSF pair), writes PNGs and a manifest in a
temporary folder and times ``clblur.study.study`` end to end (reading, histograms, all tests,
report and figures).  ``limits``: for each effect, the fraction of seeds on which the study
ranks the hidden effect first and significant, at magnitudes below and inside the realistic
range of ``clblur.study.synthetic.RANGES`` (48 x 64 scenes, as in the tests).  ``series``:
the 7 JPEGs of ``$CLBLUR_DATA/canon400d_road`` downscaled to 0.3 MP, timing ``calibrate``
(every model) and ``study`` end to end (target: study under 2 minutes).  ``memory``: peak
resident memory and time of ``clblur calibrate`` on the full-size bracket (7 x 10 MP JPEGs,
models exp and spline), each tree of ``--trees`` in a process of its own, interleaved.
``null``: false findings on null data, the seeds cycling through a vector pair, a PSF pair,
a frame stack and an exposure series without and with sensor noise.
``handover``: how long fold 1 takes to reach its worker process
(``clblur.study.fold_worker``) on the ``speed`` uniform pair: a worker started and asked for
a gain-only fit, the fold sent through the pipe and through a memory-mapped file in turn,
``--seeds`` rounds.
``pedestal``: whether a black level is named beside a camera curve that is not Eq. 3 (the
free response shape can absorb a pedestal), on exposure series of linear, gamma-2.2, sRGB
and Eq. 3 cameras, and false black levels on the first two without one.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from clblur.camera import Camera, random_scene
from clblur.io import write_image
from clblur.manifest import write_manifest
from clblur.study import study, study_groups
from clblur.study.synthetic import RANGES, scenario

# magnitudes tried per effect (units of RANGES), smallest first
LIMIT_GRID = {
    "black_level": (0.0002, 0.0005, 0.001, 0.002, 0.005, 0.02),
    "response_shape": (1.005, 1.01, 1.02, 1.05, 1.1, 1.6),
    "saturation": (1.1, 1.2, 1.3, 1.6, 2.0),
    "noise": (2e-7, 5e-7, 1e-6, 2e-6, 5e-6, 2e-5, 2e-4),
    "vignetting": (0.002, 0.005, 0.01, 0.02, 0.05, 0.3),
    "nonuniform_motion": (1.05, 1.1, 1.25, 1.5, 2.0),
    "channel_gain": (0.001, 0.002, 0.003, 0.006, 0.01, 0.05),
    "exposure_gain": (0.001, 0.002, 0.003, 0.006, 0.01, 0.08),
    "channel_shape": (0.002, 0.005, 0.01, 0.02, 0.05, 0.1),
    "exposure_times": (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.04),
    "white_balance": (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.04),
    "optical_blur": (0.05, 0.1, 0.2, 0.3, 0.5),
}


def _speed_pairs(tmp: Path) -> None:
    """The speed mode's images in ``tmp``: the static ``s.png``, ``b.png`` blurred by the
    uniform motion, the kernel ``k.png`` and ``bk.png`` blurred by it."""
    rng = np.random.default_rng(1)
    scene = random_scene(rng, (1000, 1000), 3, high=0.35)
    cam = Camera(noise_a=5e-4, noise_b=5e-6)
    kernel = np.zeros((15, 15))
    kernel[7, 2:13] = np.linspace(1.0, 2.0, 11)
    kernel[3:8, 12] = 1.0
    write_image(tmp / "s.png", cam.capture(scene, rng=rng))
    write_image(tmp / "b.png", cam.capture(scene, motion=(14.0, 5.0), gain=1.15, rng=rng))
    write_image(tmp / "k.png", np.rint(kernel / kernel.max() * 255).astype(np.uint8))
    write_image(tmp / "bk.png", cam.capture(scene, motion=kernel / kernel.sum(),
                                            gain=1.15, rng=rng))


def speed(results: Path) -> None:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        _speed_pairs(tmp)
        for name, entry in (("uniform (14, 5)", {"motion": [14.0, 5.0]}),
                            ("PSF 15 x 15", {"psf": "k.png"})):
            blurred = "b.png" if "motion" in entry else "bk.png"
            write_manifest(tmp / "m.json", {"kind": "blur-pair", "pairs": [
                {"static": "s.png", "blurred": blurred, **entry}]})
            t0, c0 = time.perf_counter(), _cpu()
            r = study(tmp / "m.json", report=tmp / "r.json", figures_dir=tmp / "fig",
                      progress=True).report
            rows.append((name, time.perf_counter() - t0, _cpu() - c0,
                         ", ".join(r["extended"]["effects"]), r["baseline"]["heldout_rmse"],
                         r["extended"]["heldout_rmse"]))
    lines = [_header("speed"),
             "| 1000 x 1000 RGB pair, motion | wall (s) | CPU (s) | effects found "
             "| held-out RMSE paper -> extended |", "|---|---:|---:|---|---|"]
    lines += [f"| {n} | {w:.1f} | {c:.1f} | {e} | {b:.2f} -> {x:.2f} |"
              for n, w, c, e, b, x in rows]
    _write(results, lines)


def handover(results: Path, rounds: int) -> None:
    """Fold 1's hand-over to its worker, through the pipe and through a file, alternately."""
    from clblur.manifest import load_manifest
    from clblur.study import fold_worker
    from clblur.study.crossfit import Folds, assign_blocks
    from clblur.study.model import null_params
    from clblur.study.run import groups_from_manifest

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        _speed_pairs(tmp)
        write_manifest(tmp / "m.json", {"kind": "blur-pair", "pairs": [
            {"static": "s.png", "blurred": "b.png", "motion": [14.0, 5.0]}]})
        groups = groups_from_manifest(load_manifest(tmp / "m.json"))
    folds = Folds(groups, assign_blocks(groups))
    part, nvalid = folds.part[1], folds.nvalid[1]
    default = fold_worker.OUT_OF_BAND_BYTES
    rows = []
    try:
        for _ in range(rounds):
            for route, limit in (("pipe", 1 << 62), ("file", default)):
                fold_worker.OUT_OF_BAND_BYTES = limit
                t0 = time.perf_counter()
                worker = fold_worker.FoldWorker(part, nvalid, folds.bounds)
                t1 = time.perf_counter()
                worker.submit(["gain"], null_params(), None, False, False)
                worker.result()
                rows.append((route, t1 - t0, time.perf_counter() - t0))
                worker.close()
    finally:
        fold_worker.OUT_OF_BAND_BYTES = default
    lines = [_header("handover"),
             f"Fold 1 of the `speed` uniform pair ({nvalid} valid values), a worker started "
             "and asked for a gain-only fit.", "",
             "| route | parent's part (s) | to the first answer (s) |", "|---|---:|---:|"]
    lines += [f"| {r} | {a:.2f} | {b:.2f} |" for r, a, b in rows]
    _write(results, lines)


def series(results: Path, data: Path | None, megapixels: float = 0.3) -> None:
    """Calibrate and study a 7-JPEG exposure bracket downscaled to ~``megapixels``."""
    import cv2

    from clblur.calibration import calibrate, load_series
    from clblur.calibration.series import exif_exposure
    from clblur.io import data_dir

    root = data or data_dir()
    folder = None if root is None else Path(root) / "canon400d_road"
    if folder is None or not folder.is_dir():
        raise SystemExit("bench_study series: canon400d_road not found (set CLBLUR_DATA)")
    files = sorted(folder.glob("*.JPG"))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        images = []
        for f in files:
            im = cv2.imread(str(f), cv2.IMREAD_COLOR)
            scale = (megapixels * 1e6 / (im.shape[0] * im.shape[1])) ** 0.5
            small = cv2.resize(im, (round(im.shape[1] * scale), round(im.shape[0] * scale)),
                               interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(tmp / f.name), small, [cv2.IMWRITE_JPEG_QUALITY, 95])
            t, fn = exif_exposure(f)
            images.append({"path": f.name, "exposure": t, "f_number": fn})
        write_manifest(tmp / "m.json", {"kind": "exposure-series", "images": images})
        h, w = small.shape[:2]
        t0, c0 = time.perf_counter(), _cpu()
        cal = calibrate(load_series(tmp / "m.json"), progress=True)
        cal_t = (time.perf_counter() - t0, _cpu() - c0)
        e = cal.evaluations[cal.best]
        t0, c0 = time.perf_counter(), _cpu()
        r = study(tmp / "m.json", report=tmp / "r.json", progress=True).report
        st_t = (time.perf_counter() - t0, _cpu() - c0)
    lines = [_header("series"),
             f"{len(files)} JPEGs of `canon400d_road` (EXIF times) downscaled to {w} x {h} "
             f"({w * h / 1e6:.2f} MP), JPEG quality 95.", "",
             "| step | wall (s) | CPU (s) | result |", "|---|---:|---:|---|",
             f"| `clblur calibrate` (all models, leave-one-exposure-out) | {cal_t[0]:.1f} | "
             f"{cal_t[1]:.1f} | best {cal.best}: all valid pixels, darker target "
             f"{_f(e['rmse_darker'].get(1))} / {_f(e['rmse_darker'].get(4))} DN at 1 / 4 stops |",
             f"| `clblur study` | {st_t[0]:.1f} | {st_t[1]:.1f} | effects "
             f"{', '.join(r['extended']['effects']) or 'none'}; held-out RMSE "
             f"{r['baseline']['heldout_rmse']:.2f} -> {r['extended']['heldout_rmse']:.2f} |"]
    _write(results, lines)


_MEMORY_RUN = """
import resource, sys, time
from clblur.calibration import calibrate, load_series
t, c = time.perf_counter(), _cpu()
series = load_series(sys.argv[1])
own = sum(im.nbytes for im in series.images)
cal = calibrate(series, ["exp", "spline"])
e = cal.evaluations[cal.best]["rmse_darker"]
print(own, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
      time.perf_counter() - t, _cpu() - c, cal.best, e.get(1), e.get(4))
"""


def memory(results: Path, data: Path | None, trees: list[str], rounds: int = 2) -> None:
    """Peak memory of calibrating the full-size Canon bracket, per tree (a process each)."""
    import subprocess
    import sys

    from clblur.io import data_dir

    root = data or data_dir()
    folder = None if root is None else Path(root) / "canon400d_road"
    if folder is None or not folder.is_dir():
        raise SystemExit("bench_study memory: canon400d_road not found (set CLBLUR_DATA)")
    rows = {tree: [] for tree in trees}
    with tempfile.TemporaryDirectory() as neutral:  # `python -c` puts its cwd first on the path
        for _ in range(rounds):
            for tree in trees:
                env = {**os.environ, "PYTHONPATH": str(Path(tree).resolve())}
                out = subprocess.run([sys.executable, "-c", _MEMORY_RUN, str(folder)],
                                     env=env, cwd=neutral, capture_output=True, text=True,
                                     check=True).stdout.split()
                rows[tree].append(out)
                print(tree, out, flush=True)
    count = len(list(folder.glob("*.JPG")))
    lines = [_header("memory --trees " + " ".join(trees)),
             f"`clblur.calibration.calibrate` (models exp, spline) on the {count} "
             f"full-size JPEGs of `canon400d_road`, read with EXIF times; best of {rounds} "
             "interleaved runs per tree, each in a process of its own.", "",
             "| tree | images (MiB) | peak resident (MiB) | peak / images | wall (s) "
             "| CPU (s) | best model: darker target, 1 / 4 stops (DN) |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for tree, runs in rows.items():
        own = int(runs[0][0])
        peak = min(int(r[1]) for r in runs)
        wall = min(float(r[2]) for r in runs)
        cpu = min(float(r[3]) for r in runs)
        best, d1, d4 = runs[0][4], float(runs[0][5]), float(runs[0][6])
        lines.append(f"| `{tree}` | {own / 2**20:.0f} | {peak / 2**20:.0f} | {peak / own:.1f} "
                     f"| {wall:.1f} | {cpu:.1f} | {best}: {d1:.2f} / {d4:.2f} |")
    _write(results, lines)


def _f(v) -> str:
    return "n/a" if v is None or v != v else f"{v:.2f}"


def limits(results: Path, seeds: int, noise: float, effects: list[str] | None = None) -> None:
    cmd = (f"limits --seeds {seeds}" + (f" --noise {noise:g}" if noise else "")
           + (f" --effects {' '.join(effects)}" if effects else ""))
    rule = ("the hidden effect is ranked first and significant" if not noise else
            f"the hidden effect is significant; camera noise a = {noise:g}, b = a / 100 "
            "(found as well)")
    lines = [_header(cmd), f"Detection = {rule}.  48 x 64 scenes.",
             "", "| effect | magnitude | detected | seconds |", "|---|---:|---:|---:|"]
    for effect, grid in LIMIT_GRID.items():
        if (noise and effect == "noise") or (effects and effect not in effects):
            continue
        for m in grid:
            t0 = time.perf_counter()
            hits = 0
            for s in range(seeds):
                hidden = {effect: m, **({"noise": noise} if noise else {})}
                sc = scenario(hidden, np.random.default_rng(9000 + s))
                r = study_groups(sc.kind, sc.groups).report
                top = r["findings"][0]
                hits += (effect in r["extended"]["effects"] if noise else
                         top["effect"] == effect and top["significant"])
            lines.append(f"| {effect} | {m:g} | {hits}/{seeds} | "
                         f"{time.perf_counter() - t0:.0f} |")
            print(lines[-1], flush=True)
            if hits == seeds:  # larger magnitudes are found too (checked by the tests)
                break
    lines += ["", "Realistic ranges used by the tests: " + "; ".join(
        f"{e} {lo:g} to {hi:g}" for e, (lo, hi) in RANGES.items())]
    _write(results, lines)


def null(results: Path, seeds: int) -> None:
    """False findings on null data (the paper's model exactly true), every effect tested.

    Seeds cycle through seven data kinds so every effect of the vocabulary is tested:
    a blur pair with a vector motion, a blur pair with a random asymmetric PSF (where
    ``psf_orientation`` is testable), a frame stack, an exposure series, and a vector
    pair, a PSF pair and an exposure series with sensor noise (``a = 5e-4``: there
    ``noise`` is true and not counted as false; on a pair, noise is what an effect that
    smooths the prediction, ``optical_blur`` or ``psf_scale``, could be mistaken for)."""
    from clblur.study.synthetic import null_series, null_stack

    kinds = ("vector pair", "PSF pair", "frame stack", "exposure series",
             "noisy exposure series", "noisy vector pair", "noisy PSF pair")
    lines = [_header(f"null --seeds {seeds}"),
             "| seed | data | significant findings | structure left | seconds |",
             "|---:|---|---|---|---:|"]
    false = left = 0
    for s in range(seeds):
        rng = np.random.default_rng(7000 + s)
        t0 = time.perf_counter()
        kind = kinds[s % len(kinds)]
        if kind == "frame stack":
            sc = null_stack(rng)
        elif kind.endswith("exposure series"):
            sc = null_series(rng, noise=5e-4 if kind.startswith("noisy") else 0.0)
        else:
            sc = scenario({"noise": 5e-4} if kind.startswith("noisy") else {}, rng,
                          psf=kind.endswith("PSF pair"))
        r = study_groups(sc.kind, sc.groups).report
        found = [f["effect"] for f in r["findings"] if f["significant"]]
        false += bool(set(found) - set(sc.truth))
        lo = r["leftover"]
        left += lo["structure"]
        lines.append(f"| {7000 + s} | {kind} | {', '.join(found) or '-'} | "
                     f"{_leftover_cell(lo)} | {time.perf_counter() - t0:.0f} |")
        print(lines[-1], flush=True)
    lines += ["", f"Seeds with any false finding: {false} of {seeds} "
              f"({100.0 * false / seeds:.1f} %; the design bound is 5 %).",
              "", f"Seeds where the model is said to leave structure (`clblur.study.leftover`; "
              f"the largest t of its two alternatives in the column): {left} of {seeds}."]
    _write(results, lines)


def _leftover_cell(lo: dict) -> str:
    """``yes``/``no`` and the larger statistic of the leftover test's two alternatives."""
    t = max(lo["by_code"]["statistic"], lo["by_group"]["statistic"])
    return f"{'yes' if lo['structure'] else 'no'} (t = {t:.1f})"


# camera curve, black level (normalised), sensor noise a (b = a / 100)
PEDESTAL_CASES = (("linear", 0.03, 5e-4), ("gamma:2.2", 0.04, 0.0), ("srgb", 0.06, 0.0),
                  ("exp", 0.04, 5e-4), ("linear", 0.0, 5e-4), ("gamma:2.2", 0.0, 5e-4))


def pedestal(results: Path, seeds: int) -> None:
    """A black level beside a camera curve the paper's Eq. 3 is not: 48 x 64 exposure
    series one stop apart (4, 2, 1, 1/2), seeds 1.. per case (``PEDESTAL_CASES``)."""
    from clblur.study.series import series_groups

    lines = [_header(f"pedestal --seeds {seeds}"),
             "| camera | black level (codes) | noise a | seed | selected | black level "
             "estimate (codes) | seconds |", "|---|---:|---:|---:|---|---:|---:|"]
    named = {}
    for curve, level, noise in PEDESTAL_CASES:
        for seed in range(1, seeds + 1):
            rng = np.random.default_rng(seed)
            cam = Camera(black_level=level, noise_a=noise, noise_b=noise / 100,
                         **({} if curve == "exp" else {"response": curve}))
            scene = random_scene(rng, (48, 64), 3, low=0.03,
                                 high=0.35 if curve == "exp" else 0.8)
            times = [4.0, 2.0, 1.0, 0.5]
            t0 = time.perf_counter()
            groups = series_groups([cam.capture(scene * 0.25, t, rng=rng) for t in times],
                                   times)
            sel = study_groups("exposure-series", groups).selection
            est = next(f for f in sel.findings if f.effect == "black_level").estimate
            key = (curve, level, noise)
            named[key] = named.get(key, 0) + ("black_level" in sel.effects)
            lines.append(f"| {curve} | {255 * level:.1f} | {noise:g} | {seed} | "
                         f"{', '.join(sel.effects) or '-'} | "
                         f"{est.get('black_level_codes', 0.0):.2f} | "
                         f"{time.perf_counter() - t0:.0f} |")
            print(lines[-1], flush=True)
    lines += ["", "`black_level` selected: " + "; ".join(
        f"{c} {255 * b:.1f} codes, a = {n:g}: {k} of {seeds}"
        for (c, b, n), k in named.items()) + "."]
    _write(results, lines)


def _cpu() -> float:
    """CPU seconds of this process and of its children that have ended (the study fits
    one fold in a child process, ``clblur.study.fold_worker``, ended with each study)."""
    import resource

    return sum(resource.getrusage(who).ru_utime + resource.getrusage(who).ru_stime
               for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))


def _header(what: str) -> str:
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    return (f"# Study benchmark ({what})\n\nMeasured {when}"
            f" on {platform.node()} ({os.cpu_count()} CPUs, shared; {platform.machine()}), "
            f"numpy backend, with\n\n    python bench/bench_study.py {what}\n")


def _write(path: Path, lines: list[str]) -> None:
    """Print the tables and write them at the top of ``path``, keeping the notes written by
    hand below its marker (``results_file``)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_file import write_results

    text = "\n".join(lines) + "\n"
    print(text)
    write_results(path, text)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mode", choices=("speed", "limits", "series", "null", "memory", "pedestal",
                                    "handover"))
    p.add_argument("--trees", nargs="+", default=["."],
                   help="memory: source trees to compare (PYTHONPATH of each run)")
    p.add_argument("--data", type=Path, help="series: shared data folder (default CLBLUR_DATA)")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--noise", type=float, default=0.0,
                   help="limits: camera noise a (b = a / 100) under every hidden effect")
    p.add_argument("--effects", nargs="+", choices=list(LIMIT_GRID), metavar="E",
                   help="limits: only these effects (default: every one of LIMIT_GRID)")
    p.add_argument("--results", type=Path)
    a = p.parse_args()
    if a.mode == "speed":
        speed(a.results or Path("bench/results_study.md"))
    elif a.mode == "series":
        series(a.results or Path("bench/results_study_series.md"), a.data)
    elif a.mode == "memory":
        memory(a.results or Path("bench/results_calibrate_memory.md"), a.data, a.trees)
    elif a.mode == "null":
        null(a.results or Path("bench/results_study_null.md"), a.seeds)
    elif a.mode == "pedestal":
        pedestal(a.results or Path("bench/results_study_pedestal.md"), a.seeds)
    elif a.mode == "handover":
        handover(a.results or Path("bench/results_study_handover.md"), a.seeds)
    else:
        name = "results_study_limits" + ("_noisy" if a.noise else "") + ".md"
        limits(a.results or Path("bench") / name, a.seeds, a.noise, a.effects)


if __name__ == "__main__":
    main()
