"""PSF estimation from a sharp / blurred pair: accuracy, speed and memory against a peer.

Run:  python bench/bench_psf.py [--repeat 3]
Prints Markdown tables and writes ``bench/results_psf.md``.

``clblur.psf_estimation.fit_psf`` (non-negative least squares on gradients by FISTA, the
window grown from 15 px, linear and sRGB light tried) against the strongest simple peer we
could write: the closed-form Fourier-domain least squares on the same gradients in the same
linear light (Tikhonov-regularised division of spectra, the fast kernel step of Cho and Lee
2009), negative weights clipped, the same 5 % floor, told the true window (an advantage
clblur does not get).

* Synthetic pairs: a scene of rectangles over smooth noise in linear light, blurred by a
  camera-shake-like path kernel, sRGB-encoded with 1 DN read noise, 8-bit; accuracy is the
  normalised correlation with the true kernel (1 = exact; ``kernel_agreement``, no shift).
* Levin et al. 2009's 32 real pairs (when ``$CLBLUR_DATA`` has them): each kernel fitted on
  the left half, scored on the right half (``docs/studies/levin_kernels.py``'s RMSE), with
  Levin's own kernels as the reference.
* Wall and process CPU time are medians of ``--repeat`` runs; MP per CPU-s counts the
  pair's pixels; peak memory is the largest traced allocation of one run (``tracemalloc``,
  a separate run).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import tracemalloc
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "docs" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from psf_pairs import pair, path_kernel  # noqa: E402
from results_file import write_results  # noqa: E402

from clblur.io import data_dir, read_image, read_psf  # noqa: E402
from clblur.psf_estimation import fit_psf, kernel_agreement  # noqa: E402
from clblur.responses import response  # noqa: E402


def fourier_psf(static: np.ndarray, blurred: np.ndarray, size: int,
                spec: str = "srgb", lam: float = 1e-3) -> np.ndarray:
    """The peer: closed-form least squares on gradients in the Fourier domain."""
    curve = response(spec)
    x = curve.inverse(np.atleast_3d(static).astype(np.float64) / 255.0)
    y = curve.inverse(np.atleast_3d(blurred).astype(np.float64) / 255.0)
    num = 0.0
    den = 0.0
    for axis in (0, 1):
        # forward differences, zero on the last row / column (one grid for both axes)
        gx = np.diff(x, axis=axis, append=np.take(x, [-1], axis=axis))
        gy = np.diff(y, axis=axis, append=np.take(y, [-1], axis=axis))
        for c in range(x.shape[2]):
            fx, fy = np.fft.rfft2(gx[..., c]), np.fft.rfft2(gy[..., c])
            num = num + np.conj(fx) * fy
            den = den + fx.real ** 2 + fx.imag ** 2
    shape = x.shape[:2]
    k = np.fft.irfft2(num / (den + lam * den.mean()), shape)
    k = np.fft.fftshift(k)
    c0, c1, r = shape[0] // 2, shape[1] // 2, size // 2
    k = np.maximum(k[c0 - r:c0 + r + 1, c1 - r:c1 + r + 1], 0.0)
    k[k < 0.05 * k.max()] = 0.0
    return k / k.sum()


def timed(fn, repeat: int):
    walls, cpus = [], []
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return out, float(np.median(walls)), float(np.median(cpus)), peak / 2**20


def synthetic_rows(repeat: int) -> list[str]:
    rng = np.random.default_rng(7)
    cases = [(512, 512, 15, [(-3, -5), (2, 0), (3, 5)]),
             (1024, 1024, 31, [(-10, -8), (0, 4), (9, 13)]),
             (1440, 1440, 31, [(-10, -8), (0, 4), (9, 13)]),
             (2592, 3888, 31, [(-10, -8), (0, 4), (9, 13)])]
    rows = ["| pair | true kernel | method | agreement | wall / CPU s | MP per CPU-s | "
            "peak traced MB |", "|---|---|---|---:|---|---:|---:|"]
    print("\n".join(rows), flush=True)
    for h, w, n, pts in cases:
        truth = path_kernel(n, pts)
        sharp, blurred = pair(rng, truth, shape=(h, w))
        mp = h * w / 1e6
        methods = [("clblur fit_psf (default)", partial(fit_psf, sharp, blurred)),
                   ("clblur fit_psf, response srgb",
                    partial(fit_psf, sharp, blurred, response="srgb")),
                   ("peer: Fourier least squares, told the window",
                    partial(fourier_psf, sharp, blurred, n))]
        for name, fn in methods:
            k, wall, cpu, peak = timed(fn, repeat)
            k = getattr(k, "kernel", k)
            rows.append(f"| {h} x {w} RGB ({mp:.2f} MP) | {n} px path | {name} | "
                        f"{kernel_agreement(truth, k, 0):.3f} | {wall:.2f} / {cpu:.2f} | "
                        f"{mp / cpu:.2f} | {peak:.0f} |")
            print(rows[-1], flush=True)
    return rows


def levin_rows(data: Path) -> list[str]:
    from levin_kernels import heldout

    base = data / "levin2009"
    scores = {"Levin's kernels (measured from dots beside the print)": [],
              "clblur fit_psf (default)": [], "peer: Fourier least squares, 31 px window": []}
    for j in range(1, 9):
        given = read_psf(base / "gt" / f"kernel{j}.png")
        for i in range(1, 5):
            sharp = read_image(base / "gt" / f"im{i}.png")
            blurred = read_image(base / f"im{i}_kernel{j}_img.png")
            half = (sharp[:, :128], blurred[:, :128])
            b = blurred.astype(float)
            for name, k in zip(scores, (given, fit_psf(*half).kernel,
                                        fourier_psf(*half, 31, "linear")), strict=True):
                scores[name].append(heldout(sharp, b, k))
    levin = "Levin's kernels (measured from dots beside the print)"
    ref = np.array(scores[levin])
    rows = ["| kernels | right-half RMSE, mean of 32 (codes) | pairs better than Levin's |",
            "|---|---:|---:|"]
    for name, s in scores.items():
        s = np.array(s)
        better = "" if name == levin else f"{int((s < ref).sum())} of 32"
        rows.append(f"| {name} | {s.mean():.2f} | {better} |")
    print("\n".join(rows), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--results", type=Path,
                    default=Path(__file__).resolve().parent / "results_psf.md")
    args = ap.parse_args()
    synth = synthetic_rows(args.repeat)
    data = data_dir()
    levin = levin_rows(data) if data is not None and (data / "levin2009").is_dir() else \
        ["(Levin et al.'s pairs not found: set CLBLUR_DATA)"]
    load = os.getloadavg()[0]
    text = "\n".join([
        "# PSF estimation from a sharp / blurred pair", "",
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.node()} "
        f"({os.cpu_count()} CPUs, shared; load average {load:.1f} at the end), with", "",
        f"    python bench/bench_psf.py --repeat {args.repeat}", "",
        "Synthetic pairs (known kernel, sRGB, 1 DN noise; agreement = normalised correlation "
        "with the true kernel; pairs over 2 MP are fitted on their central 2 MP):", "",
        *synth, "",
        "Levin et al. 2009, 32 real pairs: fitted on the left half, scored on the right half "
        "(a linear blur of the stored values, each kernel at its best orientation and shift):",
        "", *levin, ""])
    write_results(args.results, text)
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
