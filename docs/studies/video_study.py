"""GoPro 240 fps study for ``clblur video`` (docs/studies/video.md).

Ground truth: a 360-degree 30 fps exposure centred on frame ``c`` of the 240 fps sequence,
formed in the linear domain under an assumed response ``R``: the mean of the two 8-frame
averages ``c-4..c+3`` and ``c-3..c+4`` (weights 1/16, 1/8 x 7, 1/16 over ``c-4..c+4``), because
an even number of frames cannot be centred on a frame.  A 30 fps clip is every 8th frame
(phases 0..4 give clips {p, p+8, p+16}); ``clblur video`` blurs each clip with --shutter 360.

Run:  python docs/studies/video_study.py [--backend auto] [--work DIR]
Writes docs/studies/figures/video/{results.json,*.png} and prints the tables for video.md.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from clblur import video
from clblur.cli import video as video_cli
from clblur.flow import FlowFolder
from clblur.io import data_dir, gopro_frames, read_image
from clblur.pixels import linearise, normalise, quantise
from clblur.responses import response

SYNTH = ["exp", "linear", "srgb", "gamma:2.2"]  # responses given to clblur video
TRUTHS = ["gamma:2.2", "srgb", "exp", "linear"]  # assumed camera responses for the truth
PRIMARY_TRUTH = "gamma:2.2"  # Nah et al. 2017 built GOPRO_Large's blur with gamma 2.2
STRIDE = 8  # 240 fps -> 30 fps
WEIGHTS = np.array([1, 2, 2, 2, 2, 2, 2, 2, 1]) / 16.0  # frames c-4 .. c+4
FIG = Path(__file__).resolve().parent / "figures" / "video"


def truth_exposure(frames: list[np.ndarray], c: int, resp_spec: str) -> np.ndarray:
    """Linear-domain exposure over frames c-4..c+4, linearised exactly as clblur does (so a
    clipped pixel gets the least saturating exposure, not the infinity of exp's inverse)."""
    r = response(resp_spec)
    acc = sum(w * linearise(normalise(frames[c - 4 + k]), r, np.uint8, 1.0)
              for k, w in enumerate(WEIGHTS))
    return quantise(r.forward(acc), np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / mse))


def run_clblur_video(argv: list[str]) -> None:
    """Parse ``argv`` with the real ``clblur video`` parser and run it."""
    parser = argparse.ArgumentParser(prog="clblur")
    video_cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["video", *argv])
    if args.func(args) != 0:
        raise RuntimeError(f"clblur video {' '.join(argv)} failed")


def synthesise(names: list[Path], work: Path, backend: str, reuse: bool) -> dict:
    """Blur every 30 fps clip with every response; returns {(phase, spec): {index: image}}."""
    out = {}
    for phase in range(STRIDE // 2 + 1):
        idx = list(range(phase, len(names), STRIDE))
        clip = work / f"clip{phase}"
        clip.mkdir(exist_ok=True)
        for i in idx:
            link = clip / names[i].name
            if not link.exists():
                link.symlink_to(names[i])
        flows = work / f"flows{phase}"
        flows.mkdir(exist_ok=True)
        for spec in SYNTH:
            dst = work / f"out{phase}_{spec.replace(':', '').replace('.', '_')}"
            flow_args = (["--flow", str(flows)] if any(flows.iterdir())
                         else ["--save-flows", str(flows)])
            if not (reuse and all((dst / names[i].name).exists() for i in idx)):
                run_clblur_video([str(clip), str(dst), "--shutter", "360", "--response", spec,
                                  "--backend", backend, "--quiet", *flow_args])
            out[(phase, spec)] = {i: read_image(dst / names[i].name) for i in idx}
        # the same default response with OpenCV's other flow, to compare flow methods
        dst = work / f"out{phase}_srgb_farneback"
        if not (reuse and all((dst / names[i].name).exists() for i in idx)):
            run_clblur_video([str(clip), str(dst), "--shutter", "360", "--response", "srgb",
                              "--flow", "farneback", "--backend", backend, "--quiet"])
        out[(phase, "srgb, Farneback flow")] = {i: read_image(dst / names[i].name) for i in idx}
        dst = work / f"out{phase}_srgb_layers"  # two-layer exposure (--layers)
        if not (reuse and all((dst / names[i].name).exists() for i in idx)):
            run_clblur_video([str(clip), str(dst), "--shutter", "360", "--response", "srgb",
                              "--flow", str(flows), "--layers", "--backend", backend,
                              "--quiet"])
        out[(phase, "srgb, --layers")] = {i: read_image(dst / names[i].name) for i in idx}
    return out


def straight_path(frames, work: Path, backend: str) -> dict:
    """Ablation: interior frames blurred along a straight path (backward flow ignored and the
    forward flow mirrored), with the same saved flows, to see what bending buys."""
    out = {}
    for phase in range(STRIDE // 2 + 1):
        c = phase + STRIDE
        fwd = FlowFolder(work / f"flows{phase}").get("forward", 1, frames[c].shape[:2])
        out[c] = video.blur_frame(frames[c], None, fwd, "srgb", shutter=360, backend=backend)
    return out


def one_sided_truth(frames, synth) -> dict:
    """Sensitivity to centring: PSNR of flow srgb against the plain 8-frame average c-4..c+3
    (centred half a 240 fps frame early) instead of the symmetric 9-tap truth."""
    r = response(PRIMARY_TRUTH)
    vals = []
    for phase in range(STRIDE // 2 + 1):
        c = phase + STRIDE
        acc = np.mean([linearise(normalise(frames[k]), r, np.uint8, 1.0)
                       for k in range(c - 4, c + 4)], axis=0)
        vals.append(psnr(synth[(phase, "srgb")][c], quantise(r.forward(acc), np.uint8)))
    return {"flow srgb vs 8-frame c-4..c+3, truth " + PRIMARY_TRUTH: float(np.mean(vals))}


def evaluate(frames, synth, straight=None) -> dict:
    rows = {}
    for (_phase, spec), imgs in synth.items():
        idx = sorted(imgs)
        for j, c in enumerate(idx):
            if c < 4 or c + 4 >= len(frames):
                continue
            interior = 0 < j < len(idx) - 1
            key = (c, interior)
            rows.setdefault(key, {})[f"flow {spec}"] = imgs[c]
            rows[key]["sharp frame"] = frames[c]
            if interior:
                rows[key]["30 fps frame average"] = quantise(
                    np.mean([frames[c - STRIDE], frames[c], frames[c + STRIDE]], axis=0) / 255,
                    np.uint8)
    table = {}
    for (c, interior), methods in sorted(rows.items()):
        if interior and straight is not None:
            methods["flow srgb, straight (forward only)"] = straight[c]
        for t in TRUTHS:
            truth = truth_exposure(frames, c, t)
            for m, img in methods.items():
                table.setdefault(m, {}).setdefault(t, {})[f"{c}{'' if interior else 'e'}"] = \
                    psnr(img, truth)
    return table, rows


def summarise(table: dict) -> str:
    lines = ["| method | " + " | ".join(f"truth {t}" for t in TRUTHS) + " |",
             "|---|" + "---|" * len(TRUTHS)]
    for m in table:
        cells = []
        for t in TRUTHS:
            vals = [v for k, v in table[m][t].items() if not k.endswith("e")]
            cells.append(f"{np.mean(vals):.2f}" if vals else "-")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    frames = sorted({k for m in table for k in table[m][PRIMARY_TRUTH]},
                    key=lambda k: (k.endswith("e"), int(k.rstrip("e"))))
    lines += ["", f"Per frame, truth {PRIMARY_TRUTH} (e: first/last frame of its clip):", "",
              "| method | " + " | ".join(frames) + " |", "|---|" + "---|" * len(frames)]
    for m in table:
        lines.append(f"| {m} | " + " | ".join(
            f"{table[m][PRIMARY_TRUTH][k]:.2f}" if k in table[m][PRIMARY_TRUTH] else "-"
            for k in frames) + " |")
    return "\n".join(lines)


def figures(frames, rows, c: int = 10) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = rows[(c, True)]
    truth = truth_exposure(frames, c, PRIMARY_TRUTH)
    panels = [("truth (8-frame linear mean, gamma 2.2)", truth)] + [
        (m, methods[m]) for m in ("sharp frame", "30 fps frame average", "flow exp",
                                  "flow linear", "flow srgb", "flow gamma:2.2")]
    for name, (y0, x0, h, w) in {"crop_legs": (300, 560, 240, 360),
                                 "crop_shirt": (0, 520, 240, 360),
                                 "full": (0, 0, 720, 1280)}.items():
        cols = 2 if name == "full" else 4
        rows_n = -(-len(panels) // cols)
        fig, axes = plt.subplots(rows_n, cols, figsize=(4.2 * cols, 4.2 * rows_n * h / w + 0.4))
        for ax in axes.flat:
            ax.axis("off")
        for ax, (title, img) in zip(axes.flat, panels, strict=False):
            ax.imshow(img[y0:y0 + h, x0:x0 + w])
            label = title if img is truth else \
                f"{title}\nPSNR {psnr(img, truth):.2f} dB (whole frame)"
            ax.set_title(label, fontsize=9)
        fig.tight_layout()
        fig.savefig(FIG / f"gopro_{name}_frame{c}.png", dpi=80 if name == "full" else 90)
        plt.close(fig)
    # Where the responses disagree: |error| of exp and linear against the truth.
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.4), layout="constrained")
    for ax, m in zip(axes, ("flow exp", "flow srgb", "flow linear"), strict=True):
        err = np.abs(methods[m].astype(np.int16) - truth).mean(axis=2)
        im = ax.imshow(err, cmap="magma", vmin=0, vmax=30)
        ax.set_title(f"|{m} - truth| (mean over RGB, code values)", fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.9)
    fig.savefig(FIG / f"gopro_error_frame{c}.png", dpi=90)
    plt.close(fig)


def bent_path_figure() -> None:
    """Synthetic illustration: a ball arrives from the left (backward flow) and leaves
    downwards (forward flow); 360-degree shutter, srgb response.  The flow is uniform, so the
    whole picture moves with the ball (gathering needs the flow where the streak lands)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w, x0, y0 = 96, 128, 72.0, 36.0
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)

    def scene(cx, cy):  # linear radiance: a bright ball on a mid-grey floor
        return 0.18 + 2.0 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 3.0 ** 2))

    r = response("srgb")

    def picture(lin):
        return quantise(np.repeat(r.forward(lin)[..., None], 3, axis=2), np.uint8)

    def pos(t):  # t in frame intervals; 24 px/frame from the left, then 32 px/frame down
        return (x0 + 24 * t, y0) if t < 0 else (x0, y0 + 32 * t)

    ts = np.linspace(-0.5, 0.5, 401)
    truth = picture(np.mean([scene(*pos(t)) for t in ts], axis=0))
    frame = picture(scene(x0, y0))
    bwd = np.broadcast_to(np.float32([-24, 0]), (h, w, 2))
    fwd = np.broadcast_to(np.float32([0, 32]), (h, w, 2))
    panels = [("sharp frame", frame),
              ("straight path (forward flow mirrored)",
               video.blur_frame(frame, None, fwd, "srgb", shutter=360, backend="numpy")),
              ("bent path: backward then forward flow",
               video.blur_frame(frame, bwd, fwd, "srgb", shutter=360, backend="numpy")),
              ("true exposure (401 instants, linear mean)", truth)]
    fig, axes = plt.subplots(1, 4, figsize=(13, 2.9), layout="constrained")
    for ax, (title, img) in zip(axes, panels, strict=True):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.savefig(FIG / "bent_path.png", dpi=90)
    plt.close(fig)


def gather_limit_figure() -> dict:
    """Synthetic: a ball moves right at 24 px/frame over a static striped floor; the flow is
    exact (the ball's velocity on the ball, zero elsewhere).  Shows the gather limitation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w, x0, y0, speed = 96, 160, 80.0, 48.0, 24.0
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    floor = 0.12 + 0.1 * (np.sin(xx / 3.0) > 0)
    r = response("srgb")

    def scene(cx):
        ball = np.hypot(xx - cx, yy - y0) < 10
        return np.where(ball, 1.0, floor), ball

    def picture(lin):
        return quantise(np.repeat(r.forward(lin)[..., None], 3, axis=2), np.uint8)

    ts = np.linspace(-0.5, 0.5, 401)
    truth = picture(np.mean([scene(x0 + speed * t)[0] for t in ts], axis=0))
    lin, ball = scene(x0)
    frame = picture(lin)
    flow = np.zeros((h, w, 2), np.float32)
    flow[ball, 0] = speed
    got = video.blur_frame(frame, -flow, flow, "srgb", shutter=360, backend="numpy")
    layered = video.blur_frame(frame, -flow, flow, "srgb", shutter=360, backend="numpy",
                               layers=True)
    scores = {"gather (default)": psnr(got, truth), "--layers": psnr(layered, truth),
              "sharp frame": psnr(frame, truth)}
    panels = [("sharp frame; flow = 24 px/frame on the ball only", frame),
              (f"clblur video (gather): PSNR {scores['gather (default)']:.1f} dB", got),
              (f"clblur video --layers: PSNR {scores['--layers']:.1f} dB", layered),
              ("true exposure (401 instants)", truth)]
    fig, axes = plt.subplots(1, 4, figsize=(16, 2.8), layout="constrained")
    for ax, (title, img) in zip(axes, panels, strict=True):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.savefig(FIG / "gather_limit.png", dpi=90)
    plt.close(fig)
    return scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--work", default=None, help="keep intermediate clips here")
    ap.add_argument("--reuse", action="store_true",
                    help="with --work: keep blurred clips already there (re-evaluate only)")
    args = ap.parse_args()
    names = gopro_frames(data_dir(required=True))
    frames = [read_image(p) for p in names]
    FIG.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(exist_ok=True)
        synth = synthesise(names, work, args.backend, args.reuse)
        straight = straight_path(frames, work, args.backend)
        table, rows = evaluate(frames, synth, straight)
        sensitivity = one_sided_truth(frames, synth)
        figures(frames, rows)
    bent_path_figure()
    limit = gather_limit_figure()
    doc = {"truth_weights_c-4..c+4": WEIGHTS.tolist(), "psnr_db": table,
           "sensitivity_psnr_db": sensitivity, "gather_limit_psnr_db": limit,
           "backend": args.backend}
    (FIG / "results.json").write_text(json.dumps(doc, indent=1) + "\n")
    print(summarise(table))
    print("\n".join(f"\n{k}: {v:.2f} dB (mean of interior frames)"
                    for k, v in sensitivity.items()))
    print(f"\nstatic background, exact flow on the ball only: {limit}")


if __name__ == "__main__":
    main()
