"""How well must the light a frame hides be known?  An oracle bound for single-frame methods.

Issue 11 asks depth layers >= 44 dB (swept region) on every scene of ``occlusion.md``. From one
frame and its depth, 6 of 8 scenes reach it (``exposure="continuous"``); the crossing whose far
disc is almost hidden at the frame time and the star leaving the frame stay below (42.3 and
40.8 dB on the curved path), while the scene's own layers (every surface whole, also where the
frame hides it, and beyond the frame) reach 51.7 and 46.4 dB.  This script asks what detail of
the hidden light the 44 dB takes.

It blurs the scene's multi-layer render (``clblur.scenes.object_layers`` with an overscan,
curved path, continuous exposure: the best row of ``occlusion.md``) after replacing, in every
layer, the light that the sharp frame does not show by an oracle's estimate of it:

- ``sigma = 0``: the true light (the render layers themselves: the check that this script
  reproduces ``occlusion.md``'s row);
- ``sigma = s`` px: the true light low-passed by a Gaussian of standard deviation ``s``
  (normalised by the layer's coverage, in linear light): the hidden texture known down to
  about ``s`` px;
- ``mean``: the true mean of the layer's hidden light (its texture unknown, its level known);
- ``fill``: no oracle for the light: the membrane fill of the layer's hidden pixels from its
  pixels that the frame shows (``clblur.layer_planes.harmonic_fill``, the fill the depth
  layers use), on the true shape;
- ``frame only``: every layer exact inside the frame (its hidden parts too) and clamped to
  the frame's edge beyond it, the border rule of every clblur integrator: what lies beyond
  the frame unknown, as in one frame; ``frame only, fill``: the same with ``fill``.

What is hidden in layer ``i``: its pixels outside the frame (the overscan) and those that the
layers in front cover fully (coverage >= 0.999; partly covered pixels keep their light, so the
oracle is generous).  Every estimate keeps the true *shape* of each layer and its vectors; a
single-frame method knows less than any of them (it must also guess the hidden shapes and
vectors).  A texture guessed with the right statistics but not the true phase (texture
synthesis) has about twice the mean's squared error, so below ``mean`` and ``fill`` no guess
of unseen texture is expected to help.

Run:  python docs/studies/hidden_light.py [--samples 128] [--spp 2] [--backend numpy]
[--covered 0.999] (about 70 s on the shared 2-core box with the numpy reference).  Writes
``docs/studies/figures/occlusion/hidden_light.json`` (``hidden_light_covered_X.json`` with
another ``--covered``) and prints a Markdown table;
``occlusion.md`` ("How well the hidden light must be known") holds the numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

import clblur
from clblur import scenes, vectors
from clblur.layer_planes import harmonic_fill
from clblur.pixels import quantise
from clblur.responses import response

sys.path.insert(0, str(Path(__file__).resolve().parent))
from occlusion_study import overscan_for  # noqa: E402  (the scenes study, beside this one)

FIG = Path(__file__).resolve().parent / "figures" / "occlusion"
RESPONSE = "srgb"
TARGET_DB = 44.0  # issue 11's bound for the depth layers
SIGMAS = (0.0, 1.0, 2.0, 4.0, 8.0)  # px
COVERED = 0.999  # a pixel whose nearer layers cover at least this is hidden


def hidden_masks(alphas: list[np.ndarray], margin: int, covered: float = COVERED
                 ) -> list[np.ndarray]:
    """Per layer (nearest first), the pixels the sharp frame does not show: outside the frame
    (``margin`` px of overscan on each side) or covered at least ``covered`` by the layers in
    front."""
    h, w = alphas[0].shape
    outside = np.ones((h, w), bool)
    outside[margin:h - margin, margin:w - margin] = False
    clear = np.ones((h, w))  # transmittance of the layers in front
    out = []
    for a in alphas:
        out.append((outside | (1.0 - clear >= covered)) & (a > 0))
        clear = clear * (1.0 - a)
    return out


def estimate(lin: np.ndarray, alpha: np.ndarray, hidden: np.ndarray, sigma) -> np.ndarray:
    """The oracle's estimate of the layer's straight linear colour at its ``hidden`` pixels:
    the true light low-passed at ``sigma`` px (coverage-normalised), its mean, or the fill
    from the layer's pixels that the frame shows."""
    if sigma == "fill":
        seen = (alpha > 0) & ~hidden
        if not seen.any():
            return estimate(lin, alpha, hidden, "mean")  # nothing shows: nothing to fill from
        return harmonic_fill(lin.astype(np.float32), seen)[hidden]
    if sigma == "mean":
        wts = alpha[hidden]
        return np.broadcast_to((lin[hidden] * wts[:, None]).sum(0) / wts.sum(),
                               (int(hidden.sum()), lin.shape[2]))
    if sigma == 0:
        return lin[hidden]
    cover = gaussian_filter(alpha, sigma, mode="nearest")
    low = np.stack([gaussian_filter(lin[..., c] * alpha, sigma, mode="nearest")
                    for c in range(lin.shape[2])], axis=-1)
    return low[hidden] / cover[hidden][:, None]


def degraded(layers, margin: int, sigma, frame_only: bool = False,
             covered: float = COVERED) -> list:
    """``object_layers``' uint8 straight-alpha layers with the hidden light replaced.
    ``frame_only``: what lies beyond the frame is unknown, as in one frame: every layer
    beyond the frame's edge repeats its edge, light, coverage and vectors (clamp-to-edge, the
    border rule of every clblur integrator)."""
    resp = response(RESPONSE)
    if frame_only and margin:
        def clamped(a: np.ndarray) -> np.ndarray:
            inner = a[margin:-margin, margin:-margin]
            return np.pad(inner, ((margin, margin), (margin, margin), (0, 0)), mode="edge")

        layers, margin = [tuple(clamped(a) for a in layer) for layer in layers], 0
    alphas = [img[..., 3].astype(np.float64) / 255.0 for img, *_ in layers]
    out = []
    for (img, _flow, first, second), alpha, hidden in zip(
            layers, alphas, hidden_masks(alphas, margin, covered), strict=True):
        img = img.copy()
        if hidden.any():
            lin = resp.inverse(img[..., :3].astype(np.float64) / 255.0)
            img[..., :3][hidden] = quantise(resp.forward(estimate(lin, alpha, hidden, sigma)),
                                            np.uint8)
        out.append((img, (first, second)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=128, help="shutter instants of the truth")
    ap.add_argument("--spp", type=int, default=2, help="sub-pixel samples per axis")
    ap.add_argument("--backend", default="numpy", help="clblur backend (default: the reference)")
    ap.add_argument("--covered", type=float, default=COVERED,
                    help="coverage by nearer layers from which a pixel counts as hidden "
                         f"(default {COVERED}; 0.001: every partly covered pixel too)")
    args = ap.parse_args()
    opts = {"backend": args.backend, "exposure": "continuous"}
    # (key, hidden light, nothing beyond the frame)
    columns = [*((str(s), s, False) for s in SIGMAS), ("mean", "mean", False),
               ("fill", "fill", False), ("frame only", 0.0, True),
               ("frame only, fill", "fill", True)]
    table = {}
    for name, scene in scenes.example_scenes().items():
        if not scene.objects:
            continue  # nothing hidden but what a pan brings in: no occlusion to bound
        t0 = time.perf_counter()
        r = scenes.render(scene, RESPONSE, np.uint8, samples=args.samples, spp=args.spp)
        m = overscan_for(r)
        layers = scenes.object_layers(scene, RESPONSE, np.uint8, spp=args.spp, overscan=m)
        row = {}
        for key, sigma, frame_only in columns:
            got = clblur.blur_layers(degraded(layers, m, sigma, frame_only, args.covered),
                                     RESPONSE, overscan=m, curved=True, **opts)[..., :3]
            row[key] = scenes.psnr(got, r.image, r.swept)
        frame = vectors.blur_bent(r.sharp, r.flow_first, r.flow_second, RESPONSE,
                                  layers=True, depth=r.depth, curved=True, **opts)
        row["one frame"] = scenes.psnr(frame, r.image, r.swept)
        table[name] = row
        print(f"{name}: {time.perf_counter() - t0:.1f} s", flush=True)
    head = [f"sigma {s:g} px" for s in SIGMAS] + [
        "mean", "fill, true shape", "frame only", "frame only, fill", "one frame + depth"]
    print("\nPSNR (dB) over the swept region, curved path, continuous exposure:\n")
    print("| scene | " + " | ".join(head) + " |")
    print("|---|" + "---|" * len(head))
    for name, row in table.items():
        cells = [row[key] for key, *_ in columns] + [row["one frame"]]
        print(f"| {name} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
    FIG.mkdir(parents=True, exist_ok=True)
    out = "hidden_light.json" if args.covered == COVERED else \
        f"hidden_light_covered_{args.covered:g}.json"
    (FIG / out).write_text(json.dumps(
        {"samples": args.samples, "spp": args.spp, "backend": args.backend,
         "covered": args.covered,
         "target_db": TARGET_DB, "psnr_swept_db": table}, indent=1) + "\n")


if __name__ == "__main__":
    main()
