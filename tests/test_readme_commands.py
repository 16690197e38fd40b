"""Every ``clblur`` command in README.md's code blocks, run as written (issue 10).

The commands run in README order in one sandbox working directory, where every input the
README names exists as a tiny file (``photo.png``, ``huge.tif``, ``photos/``, ``in.mp4``,
``../shared/data/memorial``, ``../shared/data/levin2009``, ...), so outputs of one command
feed the next exactly as a reader would chain them.  ``[...]`` marks optional arguments: the
command runs without them and with each one.  Commands that name absolute paths (a
cluster's ``/shared``, ``/tmp/manifests``) or a running Dask scheduler cannot run in a
sandbox; they are parsed by the real argument parser,
so an option the README shows must still exist.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from clblur.cli import build_parser, main
from clblur.io import write_flow, write_image

README = Path(__file__).parents[1] / "README.md"


def readme_commands() -> list[str]:
    """The clblur commands of README.md's ```bash blocks, in order, comments removed."""
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S)
    commands = []
    for block in blocks:
        text = block.replace("\\\n", " ")
        for line in text.splitlines():
            line = re.sub(r"\s#.*$", "", line).strip()
            for part in line.split("&&"):
                part = part.strip()
                if part.startswith("clblur ") or part.startswith("python -m clblur"):
                    commands.append(part)
    return commands


def expand_optional(command: str) -> list[list[str]]:
    """``a [--x X] [--y Y]`` -> argv lists: without the brackets, then with each one."""
    optional = re.findall(r"\[([^\]]+)\]", command)
    base = shlex.split(re.sub(r"\s*\[[^\]]+\]", "", command))
    return [base] + [base + shlex.split(o) for o in optional]


def runnable(argv: list[str]) -> bool:
    return not any(a.startswith("/") for a in argv) and "--scheduler" not in argv


def make_inputs(root: Path) -> Path:
    """The sandbox: ``root/work`` (the working directory) and ``root/shared/data``."""
    rng = np.random.default_rng(5)
    work = root / "work"
    work.mkdir()
    img = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    write_image(work / "photo.png", img)
    write_image(work / "huge.tif", img)
    write_flow(work / "huge_flow.npy", rng.normal(0, 3, (24, 32, 2)))
    try:  # the EXR / render-pass commands
        from clblur.io import exr
    except ImportError:
        exr = None
    if exr is not None:
        lin = (img / 255.0).astype(np.float32)
        exr.write_image(work / "beauty.exr", lin)
        exr.write_image(work / "plate.exr", lin)
        cover = np.zeros((24, 32, 1), np.float32)
        cover[6:18, 8:20] = 1.0  # an opaque box, premultiplied
        exr.write_image(work / "ball.exr", np.concatenate([lin * cover, cover], axis=2))
        v = rng.normal(0, 2, (24, 32)).astype(np.float32)
        exr.write_channels(work / "vectors.exr", {f"Vector.{c}": v for c in "XYZW"})
        exr.write_channels(work / "depth.exr", {"Z": np.where(cover[..., 0] > 0, 1.0, 10.0)
                                                 .astype(np.float32)})
        exr.write_channels(work / "motion.exr", {f"{layer}.{c}": v for layer in
                                                 ("forward", "backward") for c in "uv"})
        views = {}  # a Blender multilayer EXR with two view layers
        for name, alpha in (("Ball", cover[..., 0]), ("Background", np.ones((24, 32)))):
            for i, c in enumerate("RGB"):
                views[f"{name}.Combined.{c}"] = lin[..., i] * alpha
            views[f"{name}.Combined.A"] = alpha.astype(np.float32)
            views.update({f"{name}.Vector.{c}": v for c in "XYZW"})
        exr.write_channels(work / "render.exr", views)
    (work / "photos").mkdir()
    for i in range(2):
        write_image(work / "photos" / f"p{i}.png", img[:, i:])
    (work / "jobs.csv").write_text("image,dx,dy\np0.png,4,1\n")
    (work / "frames").mkdir()
    frames = [np.ascontiguousarray(np.roll(img, 2 * i, axis=1)) for i in range(3)]
    for i, f in enumerate(frames):
        write_image(work / "frames" / f"f{i:03d}.png", f)
    try:
        import av
    except ImportError:
        av = None
    if av is not None:
        for name in ("in.mp4", "static_cam.mp4"):
            c = av.open(str(work / name), "w")
            s = c.add_stream("mpeg4", rate=24)
            s.width, s.height, s.pix_fmt = 32, 24, "yuv420p"
            for f in frames:
                for pkt in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                    c.mux(pkt)
            for pkt in s.encode():
                c.mux(pkt)
            c.close()
    # an exposure series shaped like ../shared/data/memorial: flat patches, 5 exposures
    series = root / "shared" / "data" / "memorial"
    series.mkdir(parents=True)
    radiance = np.kron(np.exp(rng.uniform(-4, 1, (5, 8, 1))), np.ones((8, 8, 1)))
    times = [1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2]
    for i, t in enumerate(times):
        v = np.clip((radiance * [1.0, 0.9, 0.8] * t * 4) ** (1 / 2.2), 0, 1)
        write_image(series / f"memorial{i:04d}.png", np.rint(v * 255).astype(np.uint8))
    (series / "shutter_times.txt").write_text("".join(f"{t}\n" for t in times))
    # a blur pair shaped like ../shared/data/levin2009: grey rectangles, a 5 px blur
    levin = root / "shared" / "data" / "levin2009"
    (levin / "gt").mkdir(parents=True)
    sharp = np.full((128, 128), 0.2)
    for _ in range(40):
        y, x, a, b = rng.integers(0, 120, 4)
        sharp[y:y + a // 4 + 3, x:x + b // 4 + 3] = rng.uniform(0.0, 1.0)
    from scipy.ndimage import uniform_filter1d

    blurred = uniform_filter1d(sharp, 5, axis=1)
    write_image(levin / "gt" / "im1.png", np.rint(sharp * 255).astype(np.uint8))
    write_image(levin / "im1_kernel4_img.png", np.rint(blurred * 255).astype(np.uint8))
    return work


def test_readme_has_commands_for_every_command_group():
    names = {shlex.split(c)[1] for c in readme_commands() if c.startswith("clblur ")}
    assert {"demo", "calibrate", "blur", "study", "psf", "batch", "video"} <= names


def test_every_readme_command_runs_as_written(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CLBLUR_QUIET", "1")
    work = make_inputs(tmp_path)
    monkeypatch.chdir(work)
    ran, parsed = [], []
    for command in readme_commands():
        for argv in expand_optional(command):
            if argv[:3] == ["python", "-m", "clblur.cli"]:
                argv = ["clblur", *argv[3:]]
            if argv[0] != "clblur":  # python -m clblur.study.shared: needs the real data
                parsed.append(argv)
                continue
            if argv[1] == "video":
                pytest.importorskip("av")
            if runnable(argv):
                code = main(argv[1:])
                err = capsys.readouterr().err
                assert code == 0, f"README command failed: {' '.join(argv)}\n{err}"
                assert "Traceback" not in err
                ran.append(argv)
            else:
                build_parser().parse_args(argv[1:])  # the options must exist
                parsed.append(argv)
    assert len(ran) >= 9, ran
    # what the commands should have left behind
    for path in ("demo/side_by_side.png", "memorial.json", "memorial-report/report.md",
                 "blurred.png", "huge_blurred.tif", "blurred/p0.png", "out.mp4",
                 "blurred/f000.png", "flows/forward_000000.npy", "kernel.png", "photo_shaken.png"):
        assert (work / path).exists(), path
