"""Occlusion study: gather, speed layers and depth layers against sub-frame ground truth.

Part 1 renders the scenes of ``clblur.scenes.example_scenes`` at ``--samples`` shutter
instants with exact occlusion (``clblur.scenes.render``), blurs the sharp centre frame with each
method along the renderer's own motion vectors (straight exposure chords, anchor ``center``)
and scores PSNR against the true exposure over the swept region (whole-frame PSNR hides the
error in the static background), over its part whose light the sharp frame shows, and over
the whole frame.

Part 2 repeats the GoPro 240 fps comparison of ``docs/studies/video.md`` (same truth, same
DIS flows, same bent path) with a depth proxy for the depth layers.

Methods: ``gather`` is ``clblur.blur``; ``speed layers`` is ``clblur.blur(..., depth="speed")``,
what ``clblur video --layers`` runs; ``depth layers`` is ``clblur.blur(..., depth=depth)`` and
``depth layers + clean plate`` adds ``background=plate``; ``render layers`` blurs the
scene's multi-layer render (every object alone, then the background: ``clblur.blur_layers``).
The two-layer speed exposure that ``clblur video --layers`` ran before the layered
integrator (``clblur/video_layers.py``) was scored by this script at commit fdb19ad:
``figures/occlusion/results_video_layers.json``.

Run:  python docs/studies/occlusion_study.py [--backend numpy] [--samples 128] [--no-gopro]
Writes docs/studies/figures/occlusion/{results.json,*.png} and prints the tables.
"""

from __future__ import annotations

import argparse
import inspect
import json
import time
from pathlib import Path

import numpy as np

import clblur
from clblur import scenes, vectors

FIG = Path(__file__).resolve().parent / "figures" / "occlusion"
RESPONSE = "srgb"
GENTLE = 0.15  # background contrast of the second scene set (the main set: 0.6)
# 1 px per shutter half, the moving-pixel margin of the former clblur/video_layers.py, fixed
# before looking at these frames
FOREGROUND_PX = 2.0
HIDDEN_MAX = 0.01  # a pixel is "visible" when < 1 % of its light comes from hidden surfaces


def depth_supported() -> bool:
    return "depth" in inspect.signature(clblur.blur).parameters


def plate_supported() -> bool:
    return "background" in inspect.signature(clblur.blur).parameters


def bench_peers():
    """``bench/peers.py`` (the peers of the benchmarks), loaded by path."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "bench" / "peers.py"
    spec = importlib.util.spec_from_file_location("clblur_bench_peers", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def overscan_for(r: scenes.Render) -> int:
    """The overscan (px) of the bent and curved render layers: what can enter the frame
    during the shutter, plus 2.  A bent half anchored at one end reaches its whole length,
    the parabola through the halves' points ``|D| / 2 + |C| / 4`` (``D = f + s``,
    ``C = 2 (s - f)``)."""
    f, s = (a.reshape(-1, 2).astype(np.float64) for a in (r.flow_first, r.flow_second))
    return int(np.ceil(max(np.hypot(*f.T).max(), np.hypot(*s.T).max(),
                           (np.hypot(*(f + s).T) / 2 + np.hypot(*(s - f).T) / 2).max()))) + 2


def methods_for(r: scenes.Render, backend: str, scene: scenes.Scene | None = None,
                spp: int = 2, exposure: str = "frames") -> dict[str, np.ndarray]:
    """Every method's blur of the sharp frame along the renderer's vectors; with ``scene``,
    also of the scene's multi-layer render (``clblur.blur_layers``).  ``exposure``: every
    method's (``clblur.blur``'s; passed only when not the default, so that a tree from
    before the option runs the script too)."""
    backend_opts = {"backend": backend}
    if exposure != "frames":
        backend_opts["exposure"] = exposure
    out = {"sharp frame (no blur)": r.sharp,
           "gather": clblur.blur(r.sharp, r.flow, RESPONSE, anchor="center", **backend_opts)}
    # what clblur video --layers runs: layered exposure ordered by speed (faster = nearer)
    out["speed layers"] = clblur.blur(r.sharp, r.flow, RESPONSE, anchor="center",
                                      **backend_opts, depth="speed")
    if depth_supported():
        out["depth layers"] = clblur.blur(r.sharp, r.flow, RESPONSE, anchor="center",
                                          **backend_opts, depth=r.depth)
    if depth_supported():
        # the same ordering as integer layer IDs (the depth's rank): every object is its own
        # layer whatever the spacing of the depth values (see the doc: a far background makes
        # the float-depth layering merge near objects)
        rank = np.unique(r.depth, return_inverse=True)[1].reshape(r.depth.shape)
        out["depth rank as layer IDs"] = clblur.blur(
            r.sharp, r.flow, RESPONSE, anchor="center", **backend_opts,
            depth=rank.astype(np.int32))
    if depth_supported():
        # the renderer's two halves of the path, as Blender's Vector pass holds them (previous
        # and next): each half integrated as layers, the exposures averaged
        out["depth layers, bent path"] = vectors.blur_bent(
            r.sharp, r.flow_first, r.flow_second, RESPONSE, **backend_opts, layers=True,
            depth=r.depth)
        if "curved" in inspect.signature(vectors.blur_bent).parameters:
            # the parabola through the same halves' three points (a tree from before the
            # option runs the script too)
            out["depth layers, curved path"] = vectors.blur_bent(
                r.sharp, r.flow_first, r.flow_second, RESPONSE, **backend_opts, layers=True,
                depth=r.depth, curved=True)
    if depth_supported() and plate_supported():
        # a multi-layer render also hands over the background alone: the hidden light of the
        # background is then known (hidden parts of far objects still are not)
        out["depth layers + clean plate"] = clblur.blur(
            r.sharp, r.flow, RESPONSE, anchor="center", **backend_opts, depth=r.depth,
            background=r.plate)
    if scene is not None and hasattr(clblur, "blur_layers"):
        # a multi-layer render: every object alone as its own RGBA layer with its vectors,
        # then the background alone (scenes.object_layers), so nothing hidden at the frame
        # time is guessed; uint8 sRGB with straight alpha, as the sharp frame is
        layers = scenes.object_layers(scene, RESPONSE, np.uint8, spp=spp)
        straight = [(image, flow) for image, flow, _, _ in layers]
        out["render layers"] = clblur.blur_layers(straight, RESPONSE, **backend_opts)[..., :3]
        # the compositor's way without per-sample occlusion: each layer blurred alone, then
        # merged with `over` (bench/peers.py)
        out["render layers blurred apart, then over"] = bench_peers().layers_apart_then_over(
            straight, RESPONSE, **backend_opts)[..., :3]
        # the same with the two halves and an overscan that holds whatever can enter the
        # frame during the shutter (overscan_for)
        m = overscan_for(r)
        layers = scenes.object_layers(scene, RESPONSE, np.uint8, spp=spp, overscan=m)
        bent = [(image, (first, second)) for image, _, first, second in layers]
        out["render layers, bent path, overscan"] = clblur.blur_layers(
            bent, RESPONSE, overscan=m, **backend_opts)[..., :3]
        out["render layers, curved path, overscan"] = clblur.blur_layers(
            bent, RESPONSE, overscan=m, curved=True, **backend_opts)[..., :3]
    return out


def scene_part(args, contrast: float = 0.6) -> tuple[dict, dict]:
    table, renders = {}, {}
    for name, scene in scenes.example_scenes(background_contrast=contrast).items():
        t0 = time.perf_counter()
        r = scenes.render(scene, RESPONSE, np.uint8, samples=args.samples, spp=args.spp)
        t1 = time.perf_counter()
        got = methods_for(r, args.backend, scene, args.spp, args.exposure)
        visible = r.swept & (r.hidden < HIDDEN_MAX)
        row = {"description": scene.description, "render_s": round(t1 - t0, 2),
               "swept_fraction": float(r.swept.mean()),
               "hidden_share_of_swept": float((r.hidden[r.swept] >= HIDDEN_MAX).mean()),
               "occlusion": len(scene.objects) > 0,
               "psnr_swept_db": {}, "psnr_visible_db": {}, "psnr_frame_db": {}}
        for m, img in got.items():
            row["psnr_swept_db"][m] = scenes.psnr(img, r.image, r.swept)
            row["psnr_visible_db"][m] = scenes.psnr(img, r.image, visible)
            row["psnr_frame_db"][m] = scenes.psnr(img, r.image)
        table[name] = row
        renders[name] = (r, got)
        print(f"{name} (background contrast {contrast}): rendered in {t1 - t0:.1f} s, methods in "
              f"{time.perf_counter() - t1:.1f} s", flush=True)
    return table, renders


def gopro_part(args) -> dict | None:
    """Interior frames c = 8..12 of docs/studies/video.md: the gamma 2.2 truth over c-4..c+4,
    DIS flows to c-8 and c+8, 360-degree shutter, srgb.  Depth proxy: motion that departs
    from the frame's dominant (median) motion is nearer (see depth_proxy)."""
    from clblur import video
    from clblur.flow import FlowEstimator
    from clblur.io import gopro_frames, read_image

    names = gopro_frames()
    if not names:
        print("GoPro frames not found ($CLBLUR_DATA); part 2 skipped")
        return None
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "video_study", Path(__file__).resolve().parent / "video_study.py")
    vs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(vs)
    frames = [read_image(p) for p in names]
    est = FlowEstimator("dis")
    rows: dict[str, dict[str, float]] = {}
    for c in range(8, 13):
        truth = vs.truth_exposure(frames, c, vs.PRIMARY_TRUTH)
        bwd = est(frames[c], frames[c - 8])
        fwd = est(frames[c], frames[c + 8])
        got = {"gather": video.blur_frame(frames[c], bwd, fwd, RESPONSE, shutter=360,
                                          backend=args.backend),
               "speed layers": video.blur_frame(frames[c], bwd, fwd, RESPONSE, shutter=360,
                                                backend=args.backend, layers=True)}
        if depth_supported():
            got["depth layers (proxy)"] = depth_blur_frame(frames[c], bwd, fwd, args.backend)
            got["depth layers (two-layer proxy IDs)"] = depth_blur_frame(
                frames[c], bwd, fwd, args.backend, ids=True)
        if "curved" in inspect.signature(video.blur_frame).parameters:
            # the parabola through the three positions (clblur video --curved): one surface
            # read along the curve, then with the depth proxy's layers
            got["curved path"] = video.blur_frame(frames[c], bwd, fwd, RESPONSE, shutter=360,
                                                  backend=args.backend, curved=True)
            got["curved path, depth layers (proxy)"] = video.blur_frame(
                frames[c], bwd, fwd, RESPONSE, shutter=360, backend=args.backend, layers=True,
                depth="departure", curved=True)
            # what of its gain is the curve: the same with equal halves (no curvature), i.e.
            # the straight chord, one surface read along its inverse motion
            first, second = video.half_paths(bwd, fwd, 360, frames[c].shape[:2])
            mean = (first + second) / 2
            got["chord along the inverse motion (curved path, equal halves)"] = \
                video.blur_curved(frames[c], mean, mean, RESPONSE, backend=args.backend)
        for m, img in got.items():
            rows.setdefault(m, {})[str(c)] = vs.psnr(img, truth)
        print(f"GoPro frame {c}: " + ", ".join(f"{m} {rows[m][str(c)]:.2f}" for m in rows),
              flush=True)
    return {m: {"per_frame": v, "mean": float(np.mean(list(v.values())))}
            for m, v in rows.items()}


def depth_proxy(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Depth proxy (smaller = nearer) from motion alone: ``clblur.layering.departure_order``
    of the whole-shutter displacement ``first + second``, ``1 / (1 + |v - median v|)``.
    Assumption: the camera tracks a static scene, so the dominant motion is the background's
    and what moves against it is in front.  It is a guess, stated as such; a renderer's Z
    pass or a depth estimator replaces it."""
    from clblur.layering import departure_order

    return departure_order(first.astype(np.float64) + second)


def depth_blur_frame(frame: np.ndarray, bwd: np.ndarray, fwd: np.ndarray,
                     backend: str, ids: bool = False) -> np.ndarray:
    """``clblur.video.blur_frame``'s bent path with layered exposure ordered by the depth
    proxy (``depth="departure"``, what ``clblur video --order departure`` runs: each half
    integrated as layers, the halves' exposures averaged, the response applied once).
    ``ids``: two integer layers instead, foreground (0) where the motion departs from the
    dominant one by more than ``FOREGROUND_PX`` over the shutter."""
    from clblur import video

    order = "departure"
    if ids:
        first, second = video.half_paths(bwd, fwd, 360, frame.shape[:2])
        order = (depth_proxy(first, second) >= 1.0 / (1.0 + FOREGROUND_PX)).astype(np.int32)
    return video.blur_frame(frame, bwd, fwd, RESPONSE, shutter=360, backend=backend,
                            layers=True, depth=order)


def figures(renders: dict, table: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    FIG.mkdir(parents=True, exist_ok=True)
    names = list(renders)
    cols = ["truth"] + [m for m in renders[names[0]][1] if m != "sharp frame (no blur)"]
    cols = ["sharp frame (no blur)"] + cols
    fig, axes = plt.subplots(len(names), len(cols), figsize=(2.9 * len(cols),
                                                             2.2 * len(names)))
    for i, n in enumerate(names):
        r, got = renders[n]
        ys, xs = np.nonzero(r.swept)
        if r.swept.all():
            y0, y1, x0, x1 = 0, r.swept.shape[0], 0, r.swept.shape[1]
        else:
            y0, y1 = max(ys.min() - 6, 0), min(ys.max() + 7, r.swept.shape[0])
            x0, x1 = max(xs.min() - 6, 0), min(xs.max() + 7, r.swept.shape[1])
        for j, m in enumerate(cols):
            ax = axes[i, j]
            img = r.image if m == "truth" else got[m]
            ax.imshow(img[y0:y1, x0:x1], interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            label = m if m == "truth" else f"{m}\n{table[n]['psnr_swept_db'][m]:.1f} dB"
            ax.set_title(label if i == 0 or m == "truth" else
                         f"{table[n]['psnr_swept_db'][m]:.1f} dB", fontsize=8)
            if j == 0:
                ax.set_ylabel(n, fontsize=8)
    fig.tight_layout()
    fig.savefig(FIG / "scenes.png", dpi=80)
    plt.close(fig)

    # error maps of the crossing with the fast disc behind (the hard case)
    n = "crossing_fast_behind"
    r, got = renders[n]
    ms = [m for m in got if m != "sharp frame (no blur)"]
    cols = -(-(len(ms) + 1) // 2)  # two rows
    fig, grid = plt.subplots(2, cols, figsize=(3.6 * cols, 5.6), layout="constrained")
    axes = list(grid.ravel())
    for ax in axes[len(ms) + 1:]:
        ax.axis("off")
    axes = axes[:len(ms)] + [axes[len(ms)]]
    for ax, m in zip(axes, ms, strict=False):
        err = np.abs(got[m].astype(np.int16) - r.image).mean(axis=2)
        im = ax.imshow(err, cmap="magma", vmin=0, vmax=40)
        ax.set_title(f"|{m} - truth|", fontsize=9)
        ax.axis("off")
    axes[-1].imshow(r.hidden, cmap="gray", vmin=0, vmax=1)
    axes[-1].set_title("light the sharp frame hides\n(fraction of the shutter)", fontsize=9)
    axes[-1].axis("off")
    fig.colorbar(im, ax=axes[:-1], shrink=0.6, label="code values (mean over RGB)")
    fig.savefig(FIG / "crossing_error.png", dpi=80)
    plt.close(fig)


def summarise(table: dict, gopro: dict | None, gentle: dict | None = None) -> str:
    ms = ["gather", "speed layers", "depth layers", "depth rank as layer IDs",
          "depth layers, bent path", "depth layers, curved path",
          "depth layers + clean plate",
          "render layers blurred apart, then over", "render layers",
          "render layers, bent path, overscan", "render layers, curved path, overscan",
          "sharp frame (no blur)"]

    def cell(row, key, m):
        v = row[key].get(m)
        return "TODO" if v is None else f"{v:.2f}"

    lines = ["PSNR (dB) over the swept region:", "",
             "| scene | " + " | ".join(ms) + " | hidden share |", "|---|" + "---|" * (len(ms) + 1)]
    for n, row in table.items():
        lines.append(f"| {n} | " + " | ".join(cell(row, "psnr_swept_db", m) for m in ms)
                     + f" | {row['hidden_share_of_swept']:.2f} |")
    for key, title in (("psnr_visible_db", "swept pixels whose light the sharp frame shows"),
                       ("psnr_frame_db", "whole frame")):
        lines += ["", f"PSNR (dB), {title}:", "", "| scene | " + " | ".join(ms) + " |",
                  "|---|" + "---|" * len(ms)]
        for n, row in table.items():
            lines.append(f"| {n} | " + " | ".join(cell(row, key, m) for m in ms) + " |")
    if gentle:
        lines += ["", f"PSNR (dB) over the swept region, gentle background (contrast "
                  f"{GENTLE}):", "", "| scene | " + " | ".join(ms) + " | hidden share |",
                  "|---|" + "---|" * (len(ms) + 1)]
        for n, row in gentle.items():
            lines.append(f"| {n} | " + " | ".join(cell(row, "psnr_swept_db", m) for m in ms)
                         + f" | {row['hidden_share_of_swept']:.2f} |")
    if gopro:
        frames = list(next(iter(gopro.values()))["per_frame"])
        lines += ["", "GoPro, PSNR (dB) over the whole frame, gamma 2.2 truth:", "",
                  "| method | mean | " + " | ".join(frames) + " |",
                  "|---|---|" + "---|" * len(frames)]
        lines += [f"| {m} | {v['mean']:.2f} | " + " | ".join(
            f"{v['per_frame'][f]:.2f}" for f in frames) + " |" for m, v in gopro.items()]
        if "depth layers (proxy)" not in gopro:
            lines.append("| depth layers (proxy) | TODO | " + " | ".join("TODO" for _ in frames)
                         + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="numpy",
                    help="backend for the synthetic scenes (default numpy, the reference)")
    ap.add_argument("--gopro-backend", default="auto",
                    help="backend for the 1280x720 GoPro frames (default auto)")
    ap.add_argument("--samples", type=int, default=128, help="shutter instants (>= 64)")
    ap.add_argument("--spp", type=int, default=2, help="sub-pixel samples per axis")
    ap.add_argument("--no-gopro", action="store_true", help="skip part 2")
    ap.add_argument("--exposure", choices=("frames", "continuous"), default="frames",
                    help="every method's exposure (clblur.blur); continuous writes "
                         "results_continuous.json and no figures (implies --no-gopro)")
    args = ap.parse_args()
    if args.samples < 64:
        ap.error("--samples must be >= 64")
    FIG.mkdir(parents=True, exist_ok=True)
    table, renders = scene_part(args)
    if args.exposure == "frames":
        figures(renders, table)
    gentle, _ = scene_part(args, GENTLE)
    gopro = None
    if not args.no_gopro and args.exposure == "frames":
        gopro = gopro_part(argparse.Namespace(backend=args.gopro_backend))
    doc = {"response": RESPONSE, "samples": args.samples, "spp": args.spp,
           "backend": args.backend, "depth_layers_scored": depth_supported(),
           "hidden_max": HIDDEN_MAX, "scenes": table,
           "scenes_gentle_background": gentle, "gentle_contrast": GENTLE,
           "gopro_gamma22_truth": gopro, "exposure": args.exposure}
    name = "results.json" if args.exposure == "frames" else f"results_{args.exposure}.json"
    (FIG / name).write_text(json.dumps(doc, indent=1) + "\n")
    print(summarise(table, gopro, gentle))


if __name__ == "__main__":
    main()
