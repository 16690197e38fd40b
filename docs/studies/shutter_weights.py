"""Shutter weights: how much of the error left on the occlusion scenes is the quadrature.

clblur samples a pixel's path at ``N`` instants from one end of the exposure to the other,
``s_j = j / (N - 1)``, and weights them equally (``docs/model.md`` Conventions): the paper's
Eq. 9, which averages ``K`` pixels for a motion of ``K - 1``.  A camera integrates a continuous
exposure, and the vector of a renderer (``clblur.scenes``) is the exposure's chord.  Equal
weights on samples that include both ends are the trapezoid rule plus
``((f_0 + f_{N-1}) / 2 - mean f) / (N - 1)``: the two ends of the shutter count twice as much
as they should, an error of first order in ``1 / N`` wherever the texture at the path's ends
differs from its mean.  The trapezoid weights (``1/2, 1, ..., 1, 1/2``, normalised) remove it
at the same cost.

This script scores both, at the same ``N`` (the longest vector's default count, for every
pixel, given as a time-weight vector), equal weights at ``4 N``, and the library's two
exposures at their default per-pixel counts (``exposure="frames"``, the default, and
``exposure="continuous"``), against the sub-frame truth of ``docs/studies/occlusion.md``
(``K = 128`` instants, 2 x 2 sub-pixel samples, PSNR over the swept region): the plain gather
of the sharp frame, and ``clblur.blur_layers`` on the scene's multi-layer render.

With ``$CLBLUR_DATA/gopro240/frames`` present it also scores both exposures on the GoPro
frames of ``docs/studies/video.md`` (frames 8 - 12, DIS flows to ``c - 8`` and ``c + 8``, a
360-degree bent path, gamma 2.2 truth), the gather and the depth proxy's layers.

Run:  python docs/studies/shutter_weights.py [--backend auto] [--samples 128] [--no-gopro]
Prints Markdown tables (docs/studies/occlusion.md, "Shutter weights").
"""

from __future__ import annotations

import argparse

import numpy as np

import clblur
from clblur import scenes

RESPONSE = "srgb"


def trapezoid(n: int) -> np.ndarray:
    """The trapezoid rule's weights for ``n`` equally spaced samples that include both ends
    of the exposure, normalised to unit sum (one sample: weight 1)."""
    w = np.ones(n)
    if n > 1:
        w[[0, -1]] = 0.5
    return w / w.sum()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--samples", type=int, default=128, help="shutter instants of the truth")
    ap.add_argument("--no-gopro", action="store_true", help="skip the GoPro frames")
    args = ap.parse_args()
    runs = ["equal, N", "trapezoid, N", "equal, 4 N", "frames", "continuous"]
    rows = ["| scene | N | " + " | ".join(f"{m}: {r}" for m in ("gather", "render layers")
                                         for r in runs) + " |",
            "|---|---|" + "---|" * 2 * len(runs)]
    for name, scene in scenes.example_scenes().items():
        truth = scenes.render(scene, RESPONSE, np.uint8, samples=args.samples, spp=2)
        layers = [(image, flow) for image, flow, _, _ in
                  scenes.object_layers(scene, RESPONSE, np.uint8, spp=2)]
        longest = max(float(np.hypot(f[..., 0], f[..., 1]).max()) for _, f in layers)
        n = int(np.ceil(longest)) + 1
        runs = [dict(samples=n), dict(samples=n, weights=trapezoid(n)), dict(samples=4 * n),
                {}, dict(exposure="continuous")]
        gather = [clblur.blur(truth.sharp, truth.flow, RESPONSE, backend=args.backend, **kw)
                  for kw in runs]
        composite = [clblur.blur_layers(layers, RESPONSE, backend=args.backend, **kw)[..., :3]
                     for kw in runs]
        cells = [f"{scenes.psnr(out, truth.image, truth.swept):.2f}"
                 for out in gather + composite]
        rows.append(f"| {name} | {n} | " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    print()
    print("\n".join(rows))
    if not args.no_gopro:
        gopro(args.backend)


def gopro(backend: str) -> None:
    """Both exposures on the GoPro frames of docs/studies/video.md (mean PSNR, frames 8-12)."""
    import importlib.util
    from pathlib import Path

    from clblur import video
    from clblur.flow import FlowEstimator
    from clblur.io import gopro_frames, read_image

    names = gopro_frames()
    if not names:
        print("GoPro frames not found ($CLBLUR_DATA): skipped")
        return
    spec = importlib.util.spec_from_file_location(
        "video_study", Path(__file__).resolve().parent / "video_study.py")
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    frames = [read_image(p) for p in names]
    flow = FlowEstimator("dis")
    methods = {"gather": {}, "depth layers (departure proxy)": dict(layers=True,
                                                                    depth="departure")}
    scores: dict[tuple[str, str], list[float]] = {}
    for c in range(8, 13):
        truth = study.truth_exposure(frames, c, study.PRIMARY_TRUTH)
        backward, forward = flow(frames[c], frames[c - 8]), flow(frames[c], frames[c + 8])
        for name, options in methods.items():
            for exposure in ("frames", "continuous"):
                out = video.blur_frame(frames[c], backward, forward, RESPONSE, shutter=360,
                                       backend=backend, exposure=exposure, **options)
                scores.setdefault((name, exposure), []).append(study.psnr(out, truth))
    print("\n| GoPro, mean PSNR (dB) | frames | continuous |\n|---|---|---|")
    for name in methods:
        print(f"| {name} | {np.mean(scores[(name, 'frames')]):.2f} | "
              f"{np.mean(scores[(name, 'continuous')]):.2f} |")


if __name__ == "__main__":
    main()
