"""Registration of hand-held exposure series: accuracy, speed, and what it does to calibration.

    python bench/bench_registration.py [--data DIR] [--seeds 5] [--results FILE]

Accuracy and speed: ``clblur.registration.align_series`` against OpenCV's median threshold
bitmap alignment (``cv2.AlignMTB``, Ward 2003, the usual tool for brackets; the same chain
of neighbouring exposures, so the two differ only in the pairwise criterion) on the shared
Memorial stack and Canon 400D bracket, as stored and as hand-held copies: every frame a
window of the stored frame at a random whole-pixel offset (up to 20 px on Memorial, 6 px on
the Canon bracket shrunk to 1/4), whose true relative shifts are known.  Calibration: the
paper's ``exp`` family (Eq. 3) fitted to one such Canon copy with and without registration,
to a copy whose full-size frames are turned by up to 1 degree (bicubic) before they are
shrunk, registered with and without turns, and to the tripod frames themselves.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import write_results  # noqa: E402

from clblur.calibration import calibrate, load_series  # noqa: E402
from clblur.calibration.series import ExposureSeries  # noqa: E402
from clblur.io import data_dir  # noqa: E402
from clblur.registration import align_series  # noqa: E402


def mtb_shifts(images: list[np.ndarray], exposures) -> np.ndarray:
    """OpenCV's MTB shift of each image against the middle exposure, chained over
    neighbouring exposures as ``align_series`` chains them ((rows, cols), same sign)."""
    mtb = cv2.createAlignMTB()
    n = len(images)
    order = np.argsort(np.asarray(exposures, np.float64))[::-1]
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in images]
    step = np.zeros((n, 2), np.int64)
    for k in range(1, n):
        # calculateShift(a, b) is the shift that moves b onto a, (x, y): b shows a's (y, x)
        # at (y - sy, x - sx)
        sx, sy = mtb.calculateShift(grey[order[k - 1]], grey[order[k]])
        step[k] = (-sy, -sx)
    chained = np.cumsum(step, axis=0)
    chained -= chained[n // 2]
    shifts = np.zeros((n, 2), np.int64)
    shifts[order] = chained
    return shifts


def handheld(images: list[np.ndarray], margin: int, rng) -> tuple[list[np.ndarray], np.ndarray]:
    """Each image cut to a window at a random offset of up to ``margin`` px: (frames, the
    shift of each against the middle exposure is ``offsets[ref] - offsets``)."""
    h, w = images[0].shape[:2]
    offsets = rng.integers(-margin, margin + 1, (len(images), 2))
    frames = [im[margin + dy:h - margin + dy, margin + dx:w - margin + dx]
              for im, (dy, dx) in zip(images, offsets, strict=True)]
    return frames, offsets


def timed(fn, *args):
    t, c = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - t, time.process_time() - c


def accuracy_rows(name: str, series: ExposureSeries, margin: int, seeds: int,
                  stored_known: bool = True) -> list[str]:
    """Rows of the accuracy table; ``stored_known``: the stored frames are registered (else
    their row lists the shifts found, and no hand-held copy is scored: its truth would hold
    the stored frames' unknown shift)."""
    images, exposures = series.images, series.relative_exposures()
    mp = sum(im.shape[0] * im.shape[1] for im in images) / 1e6
    order = np.argsort(exposures)[::-1]
    ref = order[len(images) // 2]
    cases = [("as stored", images, np.zeros((len(images), 2), np.int64))]
    rng = np.random.default_rng(0)
    for s in range(seeds):
        frames, offsets = handheld(images, margin, rng)
        cases.append((f"hand-held copy {s}", frames, offsets[ref] - offsets))
    rows = []
    for label, frames, truth in cases:
        cells = []
        for method in (lambda f: align_series(f, exposures).shifts,
                       lambda f: mtb_shifts(f, exposures)):
            found, wall, cpu = timed(method, frames)
            if stored_known:
                wrong = int(np.count_nonzero((found != truth).any(axis=1)))
                what = f"{wrong} ({int(np.abs(found - truth).max())} px)"
            else:
                what = "found " + (", ".join(f"{series.names[i]} {tuple(found[i].tolist())}"
                                             for i in np.flatnonzero(found.any(axis=1)))
                                   or "none")
            cells.append(f"{what} | {wall:.2f} / {cpu:.2f} | {mp / cpu:.1f}")
        rows.append(f"| {name}, {label} | {len(frames)} x {mp / len(frames):.2f} MP | "
                    + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    return rows


def turn(image: np.ndarray, degrees: float, margin: int) -> np.ndarray:
    """A full-size frame turned by ``degrees`` about its centre (bicubic: the scene as a
    turned camera samples it), shrunk to 1/4 as the bracket is, the border cut away."""
    h, w = image.shape[:2]
    m = cv2.getRotationMatrix2D((w / 2, h / 2), degrees, 1.0)
    out = cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_CUBIC)
    out = cv2.resize(out, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    return out[margin:-margin, margin:-margin]


def turned_frames(full: ExposureSeries, rng) -> list[np.ndarray]:
    """The turned copy: each full-size frame turned by a random angle of up to 1 degree
    either way (``turn``), with a 16 px border cut (the corners a turn of 1 degree brings in
    come to 10 px at 1/4)."""
    angles = rng.uniform(-1, 1, len(full.images))
    return [turn(im, a, 16) for im, a in zip(full.images, angles, strict=True)]


def calibration_rows(canon: ExposureSeries, margin: int, full: ExposureSeries) -> list[str]:
    rng = np.random.default_rng(0)
    frames, _ = handheld(canon.images, margin, rng)
    shifted = ExposureSeries.create(frames, canon.exposures, canon.f_numbers, canon.names)
    inner = [im[margin:-margin, margin:-margin] for im in canon.images]
    tripod = ExposureSeries.create(inner, canon.exposures, canon.f_numbers, canon.names)
    turned = ExposureSeries.create(turned_frames(full, rng), canon.exposures,
                                   canon.f_numbers, canon.names)
    turned_shifted = turned.aligned(turns=False)
    rows = []
    for label, series in (("tripod frames", tripod), ("hand-held, taken as they are", shifted),
                          ("hand-held, registered", shifted.aligned()),
                          ("tripod frames, 16 px border cut (the turned copy's pixels)",
                           ExposureSeries.create([turn(im, 0.0, 16) for im in full.images],
                                                 canon.exposures, canon.f_numbers,
                                                 canon.names)),
                          ("turned by up to 1 deg, registered as whole-pixel moves",
                           turned_shifted),
                          ("turned by up to 1 deg, registered with turns", turned.aligned())):
        cal = calibrate(series, ["exp"], flat_tolerance=0.03)
        e = cal.evaluations["exp"]
        ks = ", ".join(f"{r.params()['k']:.4f}" for r in cal.responses)
        rows.append(f"| {label} | {ks} | {e['rmse_darker'][1]:.2f} / {e['rmse_darker'][4]:.2f}"
                    f" | {e['flat']['rmse_darker'][1]:.2f} / {e['flat']['rmse_darker'][4]:.2f} |")
        print(rows[-1], flush=True)
    return rows


def study_rows(canon: ExposureSeries, margin: int, full: ExposureSeries) -> list[str]:
    """``clblur study`` of the same hand-held and turned copies as ``calibration_rows``, with
    and without registration, and of the tripod frames (PNG files in a temporary folder)."""
    from clblur.calibration.series import folder_series
    from clblur.io import write_image
    from clblur.study import study

    rng = np.random.default_rng(0)
    frames, _ = handheld(canon.images, margin, rng)
    turned = turned_frames(full, rng)
    inner = [im[margin:-margin, margin:-margin] for im in canon.images]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, images, align in (("tripod frames", inner, True),
                                     ("hand-held, taken as they are", frames, False),
                                     ("hand-held, registered", frames, True),
                                     ("tripod frames, 16 px border cut",
                                      [turn(im, 0.0, 16) for im in full.images], True),
                                     ("turned by up to 1 deg, registered with turns", turned,
                                      True)):
            folder = Path(tmp) / label.replace(" ", "_").replace(",", "")
            folder.mkdir()
            for name, im in zip(canon.names, images, strict=True):
                write_image(folder / (Path(name).stem + ".png"), im)
            times = folder / "times.txt"
            times.write_text("".join(f"{Path(n).stem}.png {float(t)!r}\n"
                                     for n, t in zip(canon.names, canon.exposures,
                                                     strict=True)))
            t0 = time.perf_counter()
            r = study(folder_series(folder, times), align=align).report
            rows.append(f"| {label} | {', '.join(r['extended']['effects']) or 'none'} | "
                        f"{r['baseline']['heldout_rmse']:.3f} -> "
                        f"{r['extended']['heldout_rmse']:.3f} | "
                        f"{time.perf_counter() - t0:.0f} |")
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--results", type=Path,
                    default=Path(__file__).resolve().parent / "results_registration.md")
    args = ap.parse_args()
    data = args.data or data_dir(required=True)
    memorial = load_series(data / "memorial", data / "memorial" / "shutter_times.txt",
                           align=False)
    canon = load_series(data / "canon400d_road", align=False)
    quarter = ExposureSeries.create(
        [cv2.resize(im, (im.shape[1] // 4, im.shape[0] // 4), interpolation=cv2.INTER_AREA)
         for im in canon.images], canon.exposures, canon.f_numbers, canon.names)
    head = ["| series | images | clblur: frames wrong (worst error) | clblur: wall / CPU s "
            "| clblur: MP per CPU-s | MTB: frames wrong (worst error) | MTB: wall / CPU s | "
            "MTB: MP per CPU-s |", "|---|---|---|---|---|---|---|---|"]
    print("\n".join(head), flush=True)
    rows = head + accuracy_rows("Memorial", memorial, 20, args.seeds)
    rows += accuracy_rows("Canon 400D at 1/4", quarter, 6, args.seeds)
    rows += accuracy_rows("Canon 400D, full size", canon, 0, 0, stored_known=False)
    cal_head = ["| Canon 400D at 1/4, 6 px hand-held copy 0 | Eq. 3 `k` (R, G, B) | darker "
                "target, all valid pixels, 1 / 4 stops (DN) | flat pixels, 1 / 4 stops (DN) |",
                "|---|---|---|---|"]
    print("\n".join(cal_head), flush=True)
    cal = cal_head + calibration_rows(quarter, 6, canon)
    study_head = ["| Canon 400D at 1/4, 6 px hand-held copy 0 | `clblur study`: effects (order "
                  "joined) | held-out RMSE paper -> extended (codes) | wall s |",
                  "|---|---|---|---|"]
    print("\n".join(study_head), flush=True)
    studied = study_head + study_rows(quarter, 6, canon)
    load = os.getloadavg()[0]
    text = "\n".join([
        "# Registration of exposure series", "",
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.node()} "
        f"({os.cpu_count()} CPUs, shared; load average {load:.1f} at the end), with", "",
        "    python bench/bench_registration.py", "",
        "Frames whose shift against the middle exposure is not the true one (of the series' "
        "images), the largest error in px, and the time to register the whole series. As "
        "stored, Memorial and the Canon bracket at 1/4 are taken as registered (no shift); "
        "at full size the shifts found are listed (see "
        "docs/studies/memorial-calibration.md).", "", *rows, "",
        "Calibration of the paper's `exp` (leave-one-exposure-out, `clblur.calibration."
        "calibrate`):", "", *cal, "", "The study of the same frames:", "", *studied, ""])
    write_results(args.results, text)
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
