"""``clblur demo``: the paper's Figure 3 and a Figure-4-like scene, rendered from built-in scenes.

Figure 3 (Lin & Chang 2006): an ideal step edge blurred conventionally (Eq. 7, linear) and
photo-consistently (Eq. 9, the exp response): the bright side bleeds into the dark side, so the
profile is asymmetric.  Figure 4: a bright ball with a clipped specular highlight moving 18 px;
in the photo-consistent blur the highlight stays bright and streaks, as in real photographs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clblur.blur import blur
from clblur.errors import InputError
from clblur.io import atomic_write, write_image
from clblur.responses import Gamma

__all__ = ["BALL_MOTION", "STEP_HIGH", "STEP_LOW", "STEP_MOTION", "ball_scene", "render",
           "step_edge", "step_edge_closed_form"]

STEP_LOW, STEP_HIGH = 30, 225  # uint8 levels of the step edge
STEP_MOTION = 48
BALL_MOTION = 18


def step_edge(width: int = 192, height: int = 24) -> np.ndarray:
    """Dark left half, bright right half (uint8, grey)."""
    img = np.full((height, width), STEP_LOW, np.uint8)
    img[:, width // 2:] = STEP_HIGH
    return img


def step_edge_closed_form(x: np.ndarray, edge: float, length: float, low: float,
                          high: float) -> np.ndarray:
    """Eq. 9 with the exp response on a step, centred anchor, continuous path (values in [0,1]).

    A pixel whose path covers a fraction ``t`` of bright scene gets
    ``1 - (1 - low) ** (1 - t) * (1 - high) ** t`` (a geometric mean of ``1 - f``; k cancels).
    """
    t = np.clip((x - edge) / length + 0.5, 0.0, 1.0)
    return 1.0 - (1.0 - low) ** (1.0 - t) * (1.0 - high) ** t


def ball_scene(height: int = 160, width: int = 240) -> np.ndarray:
    """A shaded ball with a clipped specular highlight on a textured background (uint8 RGB)."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    checker = ((xx // 16 + yy // 16) % 2) * 0.08 + 0.12
    bg = np.stack([checker * 0.9, checker, checker * 1.2], axis=-1)
    cy, cx, r = height * 0.5, width * 0.45, height * 0.28
    d2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / r**2
    inside = d2 <= 1.0
    nz = np.sqrt(np.clip(1.0 - d2, 0.0, 1.0))
    nx, ny = (xx - cx) / r, (yy - cy) / r
    light = np.array([-0.45, -0.55, 0.70])
    light /= np.linalg.norm(light)
    lambert = np.clip(nx * light[0] + ny * light[1] + nz * light[2], 0.0, 1.0)
    albedo = np.array([0.75, 0.22, 0.12])
    # Phong highlight with a peak far above full scale: it clips, as a camera would.
    spec = 6.0 * np.clip(nx * light[0] + ny * light[1] + nz * light[2], 0.0, 1.0) ** 60
    ball = albedo * (0.15 + 0.85 * lambert)[..., None] + spec[..., None]
    img = np.where(inside[..., None], ball, bg)
    # Store as an sRGB-like 8-bit photo: the demo's point is the highlight, not the encoding.
    encoded = Gamma(2.2).forward(np.clip(img, 0, 1))
    return np.clip(np.rint(encoded * 255), 0, 255).astype(np.uint8)


def render(out_dir: Path, backend: str = "auto", device: str | None = None) -> list[Path]:
    """Render every demo figure into ``out_dir``; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"demo output {out_dir} exists and is not a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    opts = dict(backend=backend, device=device)

    # Figure 3: step edge.
    step = step_edge()
    eq7 = blur(step, (STEP_MOTION, 0), "linear", **opts)
    eq9 = blur(step, (STEP_MOTION, 0), "exp", **opts)
    row = step.shape[0] // 2
    x = np.arange(step.shape[1])
    closed = step_edge_closed_form(x, step.shape[1] / 2 - 0.5, STEP_MOTION, STEP_LOW / 255,
                                   STEP_HIGH / 255) * 255
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), gridspec_kw={"height_ratios": [1, 2.2]})
    strip = np.vstack([step, eq7, eq9])
    axes[0].imshow(strip, cmap="gray", vmin=0, vmax=255, aspect="auto")
    axes[0].set_yticks([step.shape[0] * (i + 0.5) for i in range(3)],
                       ["ideal", "Eq. 7 (linear)", "Eq. 9 (exp)"])
    axes[0].set_xticks([])
    axes[1].plot(x, step[row], "k:", label="ideal step")
    axes[1].plot(x, eq7[row], label="Eq. 7: conventional box blur")
    axes[1].plot(x, eq9[row], label="Eq. 9: photo-consistent (exp response)")
    axes[1].plot(x, closed, "--", lw=1, label="Eq. 9 closed form")
    axes[1].set_xlabel("x (pixels)")
    axes[1].set_ylabel("code value")
    axes[1].set_title(f"Step edge blurred by {STEP_MOTION} px: the bright side dominates")
    axes[1].legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    written.append(_savefig(fig, out_dir / "figure3_step_edge.png"))
    plt.close(fig)

    # Figure 4: moving ball with a clipped highlight.
    ball = ball_scene()
    results = {
        "static": ball,
        "linear (Eq. 7)": blur(ball, (BALL_MOTION, 0), "linear", **opts),
        "exp (Eq. 9)": blur(ball, (BALL_MOTION, 0), "exp", **opts),
        "exp, saturation 4": blur(ball, (BALL_MOTION, 0), "exp", saturation=4.0, **opts),
    }
    for name, img in zip(("ball_static", "ball_linear", "ball_exp", "ball_exp_sat4"),
                         results.values(), strict=True):
        write_image(out_dir / f"{name}.png", img)
        written.append(out_dir / f"{name}.png")
    fig, axes = plt.subplots(1, len(results), figsize=(4 * len(results), 3.4))
    for ax, (name, img) in zip(axes, results.items(), strict=True):
        ax.imshow(img)
        ax.set_title(name)
        ax.axis("off")
    fig.suptitle(f"A ball with a clipped highlight moving {BALL_MOTION} px to the right")
    fig.tight_layout()
    written.append(_savefig(fig, out_dir / "figure4_ball.png"))
    plt.close(fig)

    # One side-by-side sheet a person can look at.
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    axes[0, 0].imshow(results["linear (Eq. 7)"])
    axes[0, 0].set_title("conventional blur (Eq. 7): highlight smeared grey")
    axes[0, 1].imshow(results["exp (Eq. 9)"])
    axes[0, 1].set_title("photo-consistent blur (Eq. 9): highlight streaks stay bright")
    for ax in axes[0]:
        ax.axis("off")
    yb = int(ball.shape[0] * 0.36)
    for name in ("static", "linear (Eq. 7)", "exp (Eq. 9)"):
        axes[1, 0].plot(results[name][yb, :, 2], label=name)
    axes[1, 0].set_title(f"blue channel along row {yb}: only the highlight is bright")
    axes[1, 0].legend(fontsize=8)
    axes[1, 1].plot(x, eq7[row], label="Eq. 7")
    axes[1, 1].plot(x, eq9[row], label="Eq. 9")
    axes[1, 1].plot(x, step[row], "k:", label="ideal")
    axes[1, 1].set_title("step edge profile (paper's Fig. 3)")
    axes[1, 1].legend(fontsize=8)
    fig.tight_layout()
    written.append(_savefig(fig, out_dir / "side_by_side.png"))
    plt.close(fig)
    return written


def _savefig(fig, path: Path) -> Path:
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    return path
