"""clblur video: sign conventions of the bent path, linear-domain halves, I/O, audio, bad input."""

from __future__ import annotations

import argparse
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from clblur import blur
from clblur.cli import video as video_cli
from clblur.errors import InputError
from clblur.flow import FlowEstimator, FlowFolder, save_flows
from clblur.io import gopro_frames, read_image, write_image
from clblur.io.video import VideoReadError
from clblur.pixels import quantise
from clblur.responses import response
from clblur.video import blur_frame, blur_video, half_paths

av = pytest.importorskip("av")

H, W = 40, 56


# --------------------------------------------------------------------------- synthetic scenes

def blob_radiance(cx: float, cy: float, shape=(H, W), sigma: float = 1.6,
                  peak: float = 0.8, floor: float = 0.02) -> np.ndarray:
    """Linear radiance of a Gaussian blob on a dark floor (smooth, so bilinear sampling of a
    rendered frame matches the continuous scene closely)."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    return floor + peak * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma ** 2))


def render(radiance: np.ndarray, spec: str) -> np.ndarray:
    """Scene radiance -> uint8 RGB frame through the response ``spec``."""
    v = response(spec).forward(radiance)
    return quantise(np.repeat(v[..., None], 3, axis=2), np.uint8)


def true_exposure(path, spec: str, shutter: float, n: int = 801) -> np.ndarray:
    """The exposure of a blob moving along ``path(t)`` (t in frame intervals, 0 = frame
    time) over a shutter centred on the frame time, integrated finely in the linear domain."""
    s = shutter / 360
    ts = np.linspace(-s / 2, s / 2, n)
    acc = np.mean([blob_radiance(*path(t)) for t in ts], axis=0)
    return render(acc, spec)


def uniform_flow(dx: float, dy: float) -> np.ndarray:
    f = np.empty((H, W, 2), np.float32)
    f[..., 0], f[..., 1] = dx, dy
    return f


def err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int32) - b.astype(np.int32)).max())


# --------------------------------------------------------------------------- conventions

def test_half_paths_scale_and_sign():
    b, f = uniform_flow(-4, 2), uniform_flow(6, 0)
    first, second = half_paths(b, f, 180, (H, W))
    # first half: content travels from p + sB/2 to p, i.e. by -sB/2; second half by +sF/2
    np.testing.assert_allclose(first[0, 0], [1.0, -0.5])
    np.testing.assert_allclose(second[0, 0], [1.5, 0.0])
    # a missing flow mirrors the other (constant velocity); both missing: no motion
    first, second = half_paths(None, f, 360, (H, W))
    np.testing.assert_allclose(first[0, 0], second[0, 0])
    first, second = half_paths(None, None, 360, (H, W))
    assert not first.any() and not second.any()


@pytest.mark.parametrize("shutter", [-1, 361, float("nan")])
def test_bad_shutter(shutter):
    with pytest.raises(ValueError, match="shutter"):
        half_paths(None, None, shutter, (H, W))


def test_bad_flow_shape_and_values():
    frame = render(blob_radiance(20, 20), "srgb")
    with pytest.raises(ValueError, match="forward flow has shape"):
        blur_frame(frame, None, np.zeros((H, W + 1, 2)), backend="numpy")
    bad = uniform_flow(1, 1)
    bad[3, 3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        blur_frame(frame, bad, None, backend="numpy")


@pytest.mark.parametrize("spec", ["srgb", "exp", "gamma:2.2"])
@pytest.mark.parametrize("shutter", [180, 360])
def test_bent_path_matches_true_exposure(spec, shutter):
    """A blob arrives from the left at 8 px/frame and leaves downwards at 12 px/frame: the
    streak is an L, left arm s*8/2 long, lower arm s*12/2.  Any sign or half mix-up moves an
    arm to the wrong side, which the check below shows would be caught."""
    x0, y0 = 30.0, 14.0

    def path(t):
        return (x0 + 8 * t, y0) if t < 0 else (x0, y0 + 12 * t)

    frame = render(blob_radiance(x0, y0), spec)
    backward, forward = uniform_flow(-8, 0), uniform_flow(0, 12)
    truth = true_exposure(path, spec, shutter)
    opts = dict(shutter=shutter, backend="numpy")
    # dense sampling isolates the geometry; what remains is bilinear interpolation of the blob
    got = blur_frame(frame, backward, forward, spec, samples=33, **opts)
    assert got.shape == frame.shape and got.dtype == np.uint8
    assert err(got, truth) <= 3
    assert np.abs(got.astype(int) - truth).mean() < 0.1
    # the default ceil(|v|)+1 samples per half (equal weights, ends included) add a little
    default = blur_frame(frame, backward, forward, spec, **opts)
    assert err(default, truth) <= 8 and np.abs(default.astype(int) - truth).mean() < 0.25
    # the same test fails for a path turned the wrong way or with its halves swapped
    wrong = blur_frame(frame, -backward, -forward, spec, samples=33, **opts)
    assert err(wrong, truth) > 30
    swapped = blur_frame(frame, -forward, -backward, spec, samples=33, **opts)
    assert err(swapped, truth) > 30


def test_halves_are_summed_as_exposures_not_pictures():
    """For a straight path the bent-path blur equals one straight clblur.blur over the whole
    shutter with the same samples (the frame-time sample ends both halves, so it counts twice);
    averaging two quantised half-blurs in the display domain would not."""
    rng = np.random.default_rng(5)
    frame = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    u = (7.0, -3.0)
    got = blur_frame(frame, uniform_flow(-u[0], -u[1]), uniform_flow(*u), "exp", shutter=360,
                     backend="numpy", samples=33)
    weights = np.ones(65)
    weights[32] = 2
    straight = blur(frame, u, "exp", anchor="center", weights=weights, backend="numpy")
    assert err(got, straight) <= 1  # float32 exposures vs the float64 reference
    halves = [blur(frame, (u[0] / 2, u[1] / 2), "exp", anchor=a, samples=33, backend="numpy")
              for a in ("end", "start")]
    display_mean = quantise((halves[0] / 255.0 + halves[1] / 255.0) / 2, np.uint8)
    assert err(display_mean, straight) > 5


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("channels", [None, 3, 5])
def test_opencl_bent_path_matches_the_reference(opencl, dtype, channels):
    """The device bent path (clblur/opencl/bent_path.py: one upload, both halves on the
    device, the mean finished there) within the tolerance of docs/tolerances.md, for grey,
    RGB and two channel groups, default and fixed sample counts, a missing flow mirrored,
    both exposures."""
    rng = np.random.default_rng(11)
    shape = (H, W) if channels is None else (H, W, channels)
    codes = rng.integers(0, 256, shape)
    frame = (codes / 255.0).astype(dtype) if dtype == np.float32 else \
        (codes * (257 if dtype == np.uint16 else 1)).astype(dtype)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    backward = np.stack([-6 - xx / 9, np.sin(yy / 5) * 3], -1).astype(np.float32)
    forward = np.stack([np.cos(xx / 7) * 5, 4 + yy / 8], -1).astype(np.float32)
    for bwd, fwd, samples, exposure in ((backward, forward, None, "frames"),
                                        (backward, None, 9, "frames"),
                                        (backward, forward, None, "continuous"),
                                        (backward, forward, 9, "continuous")):
        ref = blur_frame(frame, bwd, fwd, "srgb", shutter=270, samples=samples,
                         backend="numpy", exposure=exposure)
        got = blur_frame(frame, bwd, fwd, "srgb", shutter=270, samples=samples,
                         backend="opencl", exposure=exposure)
        assert got.shape == ref.shape and got.dtype == ref.dtype
        if dtype == np.float32:
            np.testing.assert_allclose(got, ref, atol=2e-5, rtol=1e-5)
        else:
            d = np.abs(got.astype(np.int64) - ref)
            assert d.max() <= 1 and (d > 0).mean() <= 0.02


@pytest.mark.parametrize("spec", ["srgb", "exp", "linear", "gamma:2.2"])
def test_no_motion_returns_the_frame(spec):
    frame = np.arange(256, dtype=np.uint8).reshape(16, 16)
    frame = np.stack([frame, frame.T, 255 - frame], axis=2)
    out = blur_frame(frame, None, None, spec, backend="numpy")
    np.testing.assert_array_equal(out, frame)


def test_flow_estimator_sign_convention():
    """content at p in src is at p + flow(p) in dst"""
    rng = np.random.default_rng(1)
    tex = rng.integers(0, 256, (96, 160), dtype=np.uint8)
    import cv2

    tex = cv2.GaussianBlur(tex, (0, 0), 1.5)
    src, dst = tex[20:84, 20:140], np.roll(tex, (2, 5), axis=(0, 1))[20:84, 20:140]
    for method in ("dis", "farneback"):
        flow = FlowEstimator(method)(src, dst)
        centre = flow[16:48, 30:90]
        np.testing.assert_allclose(np.median(centre.reshape(-1, 2), axis=0), [5, 2], atol=0.3)
    with pytest.raises(ValueError, match="unknown flow method"):
        FlowEstimator("lucas")


def test_dis_flow_of_small_frames():
    """OpenCV's DIS crashes the process on frames 8 - 15 px high and 48 px or more wide
    (12 x 64 here, opencv/opencv#14554) and raises on smaller ones: such frames are padded
    with their edge pixels, and the flow of a strip still finds its motion."""
    import cv2

    rng = np.random.default_rng(1)
    tex = cv2.GaussianBlur(rng.integers(0, 256, (40, 120), dtype=np.uint8), (0, 0), 2)
    for h in (12, 9, 5):
        src, dst = tex[:h, 10:74], tex[:h, 7:71]  # the content moves 3 px right
        flow = FlowEstimator("dis")(src, dst)
        assert flow.shape == (h, 64, 2) and np.isfinite(flow).all()
        np.testing.assert_allclose(np.median(flow.reshape(-1, 2), axis=0), [3, 0], atol=0.2)
    assert FlowEstimator("dis")(tex[:1, :1], tex[:1, :1]).shape == (1, 1, 2)


# --------------------------------------------------------------------------- files

def moving_frames(n: int, h: int = H, w: int = W, step: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(2)
    tex = rng.integers(0, 256, (h, w + step * n, 3), dtype=np.uint8)
    return [np.ascontiguousarray(tex[:, step * i: step * i + w]) for i in range(n)]


def write_video(path: Path, frames, fps: int = 24, audio: bool = False,
                codec: str = "libx264") -> None:
    c = av.open(str(path), "w")
    vs = c.add_stream(codec, rate=fps)
    vs.height, vs.width = frames[0].shape[:2]
    vs.pix_fmt = "yuv444p" if codec == "libx264" else "yuv420p"
    if audio:
        a = c.add_stream("aac", rate=8000)
        a.layout = "mono"
    for i, img in enumerate(frames):
        f = av.VideoFrame.from_ndarray(img, format="rgb24")
        f.pts, f.time_base = i, Fraction(1, fps)
        c.mux(vs.encode(f))
    c.mux(vs.encode(None))
    if audio:
        t = np.arange(int(8000 * len(frames) / fps)) / 8000
        af = av.AudioFrame.from_ndarray((0.3 * np.sin(2 * np.pi * 440 * t))[None].astype(
            np.float32), format="fltp", layout="mono")
        af.sample_rate, af.pts = 8000, 0
        c.mux(a.encode(af))
        c.mux(a.encode(None))
    c.close()


def probe(path: Path) -> dict:
    with av.open(str(path)) as c:
        v = c.streams.video[0]
        info = {"fps": v.average_rate, "size": (v.height, v.width),
                "audio": [(s.codec_context.name, s.sample_rate) for s in c.streams.audio]}
        info["audio_packets"] = sum(1 for p in c.demux(audio=0) if p.size) if info["audio"] \
            else 0
    with av.open(str(path)) as c:
        decoded = list(c.decode(video=0))
        info["frames"] = [f.to_ndarray(format="rgb24") for f in decoded]
        info["times"] = [round(f.time, 4) for f in decoded]
    return info


def test_video_with_audio_keeps_rate_timing_and_audio(tmp_path):
    src, dst = tmp_path / "in.mp4", tmp_path / "out.mp4"
    write_video(src, moving_frames(6), fps=24, audio=True)
    result = blur_video(src, dst, response="srgb", backend="numpy")
    assert (result.frames, result.audio, result.fps) == (6, "copied", 24)
    a, b = probe(src), probe(dst)
    assert b["fps"] == 24 and b["size"] == (H, W) and len(b["frames"]) == 6
    assert b["times"] == a["times"]
    assert b["audio"] == a["audio"] and b["audio_packets"] == a["audio_packets"] > 0
    # the content moves 3 px/frame, so the output is visibly blurred (smoother)
    assert np.abs(np.diff(b["frames"][3].astype(int), axis=1)).mean() < \
        0.8 * np.abs(np.diff(a["frames"][3].astype(int), axis=1)).mean()
    assert not list(tmp_path.glob(".*part*")), "temporary file left behind"


def test_progress_bar_counts_frames(tmp_path, capsys):
    src = tmp_path / "in.mp4"
    write_video(src, moving_frames(3))
    blur_video(src, tmp_path / "out", backend="numpy", progress=True)
    assert "3/3" in capsys.readouterr().err


def test_video_to_image_folder_reports_dropped_audio(tmp_path):
    src = tmp_path / "in.mkv"
    write_video(src, moving_frames(3), audio=True)
    result = blur_video(src, tmp_path / "frames", backend="numpy")
    assert result.audio == "dropped"
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == [
        "frame_000000.png", "frame_000001.png", "frame_000002.png"]


def test_image_folder_with_flow_folder_is_exact(tmp_path):
    """Frames in a folder, flows from a folder: each frame gets its own backward/forward flow
    (checked against blur_frame), output names follow the input names."""
    frames = moving_frames(4)
    (tmp_path / "in").mkdir()
    (tmp_path / "flows").mkdir()
    for i, f in enumerate(frames):
        write_image(tmp_path / "in" / f"shot_{i + 8}.png", f)  # natural order: 8, 9, 10, 11
    rng = np.random.default_rng(3)
    flows = {(d, i): rng.uniform(-3, 3, (H, W, 2)).astype(np.float32)
             for d in ("backward", "forward") for i in range(4)}
    del flows[("backward", 0)], flows[("forward", 3)]  # the sequence ends
    for (d, i), f in flows.items():
        save_flows(tmp_path / "flows", i, f if d == "backward" else None,
                   f if d == "forward" else None)
    blur_video(tmp_path / "in", tmp_path / "out/", flow=str(tmp_path / "flows"),
               response="exp", shutter=270, backend="numpy")
    for i, f in enumerate(frames):
        expected = blur_frame(f, flows.get(("backward", i)), flows.get(("forward", i)), "exp",
                              shutter=270, backend="numpy")
        np.testing.assert_array_equal(read_image(tmp_path / "out" / f"shot_{i + 8}.png"),
                                      expected)


def test_saved_flows_reproduce_the_run(tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "flows").mkdir()
    for i, f in enumerate(moving_frames(3)):
        write_image(tmp_path / "in" / f"{i:03d}.png", f)
    blur_video(tmp_path / "in", tmp_path / "a", save_flows_to=tmp_path / "flows",
               backend="numpy")
    assert FlowFolder(tmp_path / "flows").get("backward", 0, (H, W)) is None
    assert FlowFolder(tmp_path / "flows").get("forward", 1, (H, W)) is not None
    blur_video(tmp_path / "in", tmp_path / "b", flow=str(tmp_path / "flows"), backend="numpy")
    for p in (tmp_path / "a").iterdir():
        np.testing.assert_array_equal(read_image(p), read_image(tmp_path / "b" / p.name))


def test_saved_flows_never_rewrite_the_flows_read_or_join_the_input_frames(tmp_path):
    (tmp_path / "in").mkdir()
    for i, f in enumerate(moving_frames(3)):
        write_image(tmp_path / "in" / f"{i:03d}.png", f)
    blur_video(tmp_path / "in", tmp_path / "a", save_flows_to=tmp_path / "flows",
               backend="numpy")
    before = {p.name: p.stat().st_ino for p in (tmp_path / "flows").iterdir()}
    for save in ("flows", "in"):
        with pytest.raises(InputError, match=f"--save-flows .*{save}"):
            blur_video(tmp_path / "in", tmp_path / "b", flow=str(tmp_path / "flows"),
                       save_flows_to=tmp_path / save, backend="numpy")
    assert {p.name: p.stat().st_ino for p in (tmp_path / "flows").iterdir()} == before
    assert not (tmp_path / "b").exists() and len(list((tmp_path / "in").iterdir())) == 3


def test_odd_frame_size_and_single_frame(tmp_path):
    src = tmp_path / "odd.mkv"
    write_video(src, [moving_frames(1, h=15, w=21)[0]])
    result = blur_video(src, tmp_path / "out.mkv", backend="numpy")
    assert result.frames == 1 and probe(tmp_path / "out.mkv")["size"] == (15, 21)


@pytest.mark.parametrize("turn", [90, -90, 180])
def test_a_phone_video_with_a_display_matrix_is_blurred_upright(tmp_path, turn):
    # phones store portrait video sideways with a display matrix; the output has none, so
    # the frames are turned upright as they are read (as ffmpeg's autorotate does)
    from clblur.io.video import VideoFileSource

    frames = moving_frames(3, h=16, w=24)
    src = tmp_path / "phone.mp4"
    c = av.open(str(src), "w")
    vs = c.add_stream("libx264", rate=24)
    vs.height, vs.width, vs.pix_fmt = 16, 24, "yuv444p"
    if not hasattr(vs, "set_display_rotation"):
        pytest.skip("this PyAV cannot write a display matrix")
    vs.set_display_rotation(turn)
    for i, img in enumerate(frames):
        f = av.VideoFrame.from_ndarray(img, format="rgb24")
        f.pts, f.time_base = i, Fraction(1, 24)
        c.mux(vs.encode(f))
    c.mux(vs.encode(None))
    c.close()
    source = VideoFileSource(src)
    got = [f.image for f in source.frames()]
    source.close()
    plain = probe(src)["frames"]  # as stored, sideways
    for stored, upright in zip(plain, got, strict=True):
        np.testing.assert_array_equal(upright, np.rot90(stored, turn // 90))
    result = blur_video(src, tmp_path / "out.mkv", backend="numpy")
    assert result.frames == 3
    assert probe(tmp_path / "out.mkv")["size"] == got[0].shape[:2]


def test_truncated_video_keeps_frames_written(tmp_path):
    src = tmp_path / "in.mkv"
    write_video(src, moving_frames(12), audio=True)
    data = src.read_bytes()
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(data[: int(len(data) * 0.75)])
    dst = tmp_path / "out.mkv"
    with pytest.raises(VideoReadError, match="truncated.*kept the") as info:
        blur_video(cut, dst, backend="numpy")
    n = info.value.frames_read
    assert 0 < n < 12
    assert f"{n} frame(s) written to {dst}" in str(info.value)
    assert len(probe(dst)["frames"]) == n


def test_truncated_faststart_mp4_declares_its_frame_count(tmp_path):
    src = tmp_path / "in.mp4"
    c = av.open(str(src), "w", options={"movflags": "faststart"})
    vs = c.add_stream("mpeg4", rate=24)
    vs.height, vs.width, vs.pix_fmt = H, W, "yuv420p"
    for i, img in enumerate(moving_frames(10)):
        f = av.VideoFrame.from_ndarray(img, format="rgb24")
        f.pts, f.time_base = i, Fraction(1, 24)
        c.mux(vs.encode(f))
    c.mux(vs.encode(None))
    c.close()
    data = src.read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(VideoReadError, match="declares 10 frames") as info:
        blur_video(tmp_path / "cut.mp4", tmp_path / "frames", backend="numpy")
    assert len(list((tmp_path / "frames").iterdir())) == info.value.frames_read > 0


def test_unreadable_inputs(tmp_path):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video" * 50)
    with pytest.raises(VideoReadError, match="cannot read video"):
        blur_video(junk, tmp_path / "out.mp4", backend="numpy")
    assert not (tmp_path / "out.mp4").exists()
    with pytest.raises(VideoReadError, match="not found"):
        blur_video(tmp_path / "missing.mp4", tmp_path / "out.mp4")
    (tmp_path / "empty").mkdir()
    with pytest.raises(VideoReadError, match="no image files"):
        blur_video(tmp_path / "empty", tmp_path / "out2")


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif"])
def test_a_single_image_is_refused_as_a_video(tmp_path, suffix):
    # FFmpeg reads a still image as a one-frame video, which came out unblurred (no
    # neighbour, no flow) at FFmpeg's 25 fps: a user who meant ``clblur blur`` is told so
    still = tmp_path / f"still{suffix}"
    write_image(still, np.full((24, 32, 3), 128, np.uint8))
    with pytest.raises(VideoReadError, match="single image, not a video.*clblur blur"):
        blur_video(still, tmp_path / "out.mp4", backend="numpy")
    assert not (tmp_path / "out.mp4").exists()
    r = subprocess.run([sys.executable, "-m", "clblur.cli", "video", str(still),
                        str(tmp_path / "out.mp4")], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "single image" in r.stderr


def test_bad_frame_in_folder_keeps_earlier_frames(tmp_path):
    (tmp_path / "in").mkdir()
    for i, f in enumerate(moving_frames(3)):
        write_image(tmp_path / "in" / f"{i:03d}.png", f)
    (tmp_path / "in" / "003.png").write_bytes(b"broken")
    with pytest.raises(VideoReadError, match="003.png.*kept the 3 frame") as info:
        blur_video(tmp_path / "in", tmp_path / "out", backend="numpy")
    assert info.value.frames_read == 3
    assert len(list((tmp_path / "out").iterdir())) == 3


def test_a_folder_of_mixed_bit_depths_stops_at_the_first_odd_frame(tmp_path):
    # each output frame kept its own depth, so the sequence came out mixed as well
    (tmp_path / "in").mkdir()
    frames = moving_frames(3)
    for i, f in enumerate(frames):
        write_image(tmp_path / "in" / f"{i:03d}.png", f if i < 2 else f.astype(np.uint16) * 257)
    with pytest.raises(VideoReadError, match="002.png.*uint16, earlier frames uint8"):
        blur_video(tmp_path / "in", tmp_path / "out", backend="numpy")


def test_a_gap_in_the_frame_numbers_is_named(tmp_path, capsys):
    from clblur.cli import main

    (tmp_path / "in").mkdir()
    for i, f in zip((10, 11, 12, 14, 15), moving_frames(5), strict=True):
        write_image(tmp_path / "in" / f"frame_{i:04d}.png", f)
    assert main(["video", str(tmp_path / "in"), str(tmp_path / "out"), "--backend", "numpy",
                 "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frame numbers jump from 12 to 14" in err[0], err
    (tmp_path / "in" / "frame_0010.png").rename(tmp_path / "in" / "frame_0013.png")
    assert main(["video", str(tmp_path / "in"), str(tmp_path / "out2"), "--backend", "numpy",
                 "--quiet"]) == 0
    assert "jump" not in capsys.readouterr().err


def test_refuses_to_overwrite_input_and_bad_options(tmp_path):
    src = tmp_path / "in.mp4"
    write_video(src, moving_frames(2))
    with pytest.raises(ValueError, match="refusing to overwrite"):
        blur_video(src, src)
    with pytest.raises(ValueError, match="unknown video container"):
        blur_video(src, tmp_path / "out.xyz", backend="numpy")
    with pytest.raises(ValueError, match="unknown response"):
        blur_video(src, tmp_path / "o.mp4", response="sepia")
    with pytest.raises(ValueError, match="flow folder|unknown flow method"):
        blur_video(src, tmp_path / "o.mp4", flow="nonsense")
    with pytest.raises(ValueError, match="fps only applies"):
        blur_video(src, tmp_path / "o.mp4", fps=25)
    (tmp_path / "flows").mkdir()
    save_flows(tmp_path / "flows", 5, None, uniform_flow(1, 0))  # nothing for frames 0 and 1
    with pytest.raises(ValueError, match="neither forward_000000 nor backward_000001"):
        blur_video(src, tmp_path / "o.mp4", flow=str(tmp_path / "flows"), backend="numpy")
    assert not list(tmp_path.glob("*o.mp4*"))


def test_audio_the_container_cannot_hold_is_a_clear_error(tmp_path):
    src = tmp_path / "in.mkv"
    c = av.open(str(src), "w")
    vs = c.add_stream("libx264", rate=24)
    vs.height, vs.width, vs.pix_fmt = H, W, "yuv420p"
    a = c.add_stream("pcm_s16le", rate=8000)
    a.layout = "mono"
    for i, img in enumerate(moving_frames(2)):
        f = av.VideoFrame.from_ndarray(img, format="rgb24")
        f.pts, f.time_base = i, Fraction(1, 24)
        c.mux(vs.encode(f))
    c.mux(vs.encode(None))
    af = av.AudioFrame.from_ndarray(np.zeros((1, 800), np.int16), format="s16", layout="mono")
    af.sample_rate, af.pts = 8000, 0
    c.mux(a.encode(af))
    c.mux(a.encode(None))
    c.close()
    with pytest.raises(ValueError, match="cannot copy the input's pcm_s16le audio into .webm"):
        blur_video(src, tmp_path / "out.webm", backend="numpy")
    assert list(tmp_path.iterdir()) == [src], "no output or temporary file may be left"
    assert blur_video(src, tmp_path / "out.mkv", backend="numpy").audio == "copied"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="clblur")
    video_cli.register(p.add_subparsers(dest="command", required=True))
    return p


def test_command_line(tmp_path, capsys):
    src = tmp_path / "in.mp4"
    write_video(src, moving_frames(3), audio=True)
    args = parser().parse_args(["video", str(src), str(tmp_path / "o.mkv"), "--shutter", "90",
                                "--flow", "farneback", "--response", "gamma:2.2", "--samples",
                                "4", "--backend", "numpy", "--crf", "10", "--quiet"])
    assert args.func(args) == 0
    assert "wrote 3 frame(s) at 24 fps" in capsys.readouterr().out
    assert probe(tmp_path / "o.mkv")["audio"]
    args = parser().parse_args(["video", str(src), str(tmp_path / "p.mp4"), "--fps", "0"])
    with pytest.raises(ValueError, match="--fps"):
        args.func(args)


@pytest.mark.parametrize("out, crf, ok", [("o.mp4", -5, False), ("o.mp4", 52, False),
                                           ("o.webm", 63, True), ("o.webm", 64, False),
                                           ("o.avi", 99, True), ("frames", -1, True)])
def test_a_crf_outside_the_encoder_s_scale_is_refused_before_any_frame(tmp_path, out, crf,
                                                                       ok):
    # FFmpeg refused crf -5 only when the first frame was encoded (a traceback, after the
    # first blur); mpeg4 and image sequences have no crf scale
    from clblur.io.video import check_crf

    if ok:
        check_crf(crf, tmp_path / out)
        return
    src = tmp_path / "in.mp4"
    write_video(src, moving_frames(2))
    with pytest.raises(InputError, match=f"crf {crf} is outside"):
        blur_video(src, tmp_path / out, backend="numpy", crf=crf)
    assert sorted(tmp_path.iterdir()) == [src], "nothing may be written"


def test_gopro_frames_blur_towards_the_long_exposure(shared_data):
    """Real 240 fps frames: blurring frame 10 along DIS flows from frames 2 and 18 must come
    closer to the 8-frame linear-domain exposure than the sharp frame itself."""
    names = gopro_frames(shared_data)
    crop = (slice(300, 400), slice(560, 720))
    f = [read_image(names[i])[crop] for i in range(21)]
    r = response("gamma:2.2")
    w = np.array([1, 2, 2, 2, 2, 2, 2, 2, 1]) / 16
    truth = quantise(r.forward(sum(wk * r.inverse(f[6 + k] / 255) for k, wk in enumerate(w))),
                     np.uint8)
    full = [read_image(names[i]) for i in (2, 10, 18)]
    est = FlowEstimator("dis")
    fwd, bwd = est(full[1], full[2])[crop], est(full[1], full[0])[crop]
    got = blur_frame(f[10], bwd, fwd, "gamma:2.2", shutter=360, backend="numpy")
    mse = np.mean((got.astype(float) - truth) ** 2)
    mse_sharp = np.mean((f[10].astype(float) - truth) ** 2)
    assert mse < 0.5 * mse_sharp


def test_departure_order_of_a_bent_path():
    """``depth="departure"``: the departure of the whole shutter's vectors, computed once for
    both halves; ``clblur video --order departure`` runs it (and implies --layers)."""
    from clblur.layering import departure_order

    lin, ball = ball_over_stripes(40.0)
    frame = quantise(np.repeat(response("srgb").forward(lin)[..., None], 3, axis=2), np.uint8)
    back = np.zeros((*lin.shape, 2), np.float32) + np.float32([-6.0, 0.0])  # the camera pans
    fwd = -back
    back[ball], fwd[ball] = (-1.0, 0.0), (1.0, 0.0)  # a tracked subject
    first, second = half_paths(back, fwd, 360, lin.shape)
    opts = dict(shutter=360, backend="numpy", layers=True)
    np.testing.assert_array_equal(
        blur_frame(frame, back, fwd, "srgb", depth="departure", **opts),
        blur_frame(frame, back, fwd, "srgb",
                   depth=departure_order(first.astype(np.float64) + second), **opts))
    np.testing.assert_array_equal(blur_frame(frame, back, fwd, "srgb", depth="speed", **opts),
                                  blur_frame(frame, back, fwd, "srgb", **opts))
    with pytest.raises(ValueError, match="unknown depth ordering"):
        blur_frame(frame, back, fwd, "srgb", depth="nearest", **opts)


def test_command_line_video_order_departure(tmp_path):
    from clblur.cli import main

    src = tmp_path / "seq"
    src.mkdir()
    for i, f in enumerate(moving_frames(4)):
        write_image(src / f"{i:03d}.png", f)
    assert main(["video", str(src), str(tmp_path / "v"), "--order", "departure",
                 "--backend", "numpy", "--quiet"]) == 0
    assert len(list((tmp_path / "v").glob("*.png"))) == 4
    assert main(["video", str(src), str(tmp_path / "w"), "--order", "nearest"]) == 2


def test_command_line_video_curved(tmp_path):
    """``clblur video --curved`` blurs each frame along the parabola through its three
    positions (``blur_frame(..., curved=True)``), with the same flows as the bent path."""
    from clblur.cli import main
    from clblur.video import DEFAULT_RESPONSE, DEFAULT_SHUTTER

    src = tmp_path / "seq"
    src.mkdir()
    frames = moving_frames(3)
    for i, f in enumerate(frames):
        write_image(src / f"{i:03d}.png", f)
    assert main(["video", str(src), str(tmp_path / "bent"), "--backend", "numpy", "--quiet",
                 "--save-flows", str(tmp_path / "flows")]) == 0
    assert main(["video", str(src), str(tmp_path / "curved"), "--flow", str(tmp_path / "flows"),
                 "--curved", "--layers", "--backend", "numpy", "--quiet"]) == 0
    flows = FlowFolder(tmp_path / "flows")
    bwd, fwd = (flows.get(d, 1, frames[1].shape[:2]) for d in ("backward", "forward"))
    got = read_image(sorted((tmp_path / "curved").glob("*.png"))[1])
    np.testing.assert_array_equal(got, blur_frame(
        frames[1], bwd, fwd, DEFAULT_RESPONSE, shutter=DEFAULT_SHUTTER, backend="numpy",
        layers=True, curved=True))
    assert not np.array_equal(got, read_image(sorted((tmp_path / "bent").glob("*.png"))[1]))


def test_clblur_main_reports_bad_video_with_exit_code_2(tmp_path, capsys):
    from clblur.cli import main

    src = tmp_path / "in.mkv"
    write_video(src, moving_frames(12))
    (tmp_path / "cut.mkv").write_bytes(src.read_bytes()[: int(src.stat().st_size * 0.75)])
    code = main(["video", str(tmp_path / "cut.mkv"), str(tmp_path / "out"), "--backend",
                 "numpy", "--quiet"])
    err_line = capsys.readouterr().err.strip()
    assert code == 2 and err_line.startswith("clblur video: error:") and "kept the" in err_line
    assert main(["video", str(src), str(tmp_path / "o.mp4"), "--shutter", "400"]) == 2


def test_dis_pipeline_bends_with_the_real_motion(tmp_path):
    """End to end with estimated flow: content moves 4 px, then 12 px per frame, so the middle
    frame's streak reaches 4s/2 px back and 12s/2 px ahead.  Swapping which flow drives which
    half of the shutter would change the interior by far more than the tolerance."""
    import cv2

    rng = np.random.default_rng(4)
    tex = cv2.GaussianBlur(rng.integers(0, 256, (72, 160, 3), dtype=np.uint8), (0, 0), 2.0)
    frames = [np.ascontiguousarray(tex[:, 40 - x: 40 - x + 96]) for x in (0, 4, 16)]
    (tmp_path / "in").mkdir()
    for i, f in enumerate(frames):
        write_image(tmp_path / "in" / f"{i}.png", f)
    blur_video(tmp_path / "in", tmp_path / "out", shutter=360, response="srgb",
               backend="numpy")
    got = read_image(tmp_path / "out" / "1.png")
    inner = (slice(16, 56), slice(24, 72))
    expected = blur_frame(frames[1], uniform_flow_like(frames[1], -4, 0),
                          uniform_flow_like(frames[1], 12, 0), "srgb", shutter=360,
                          backend="numpy")
    swapped = blur_frame(frames[1], uniform_flow_like(frames[1], -12, 0),
                         uniform_flow_like(frames[1], 4, 0), "srgb", shutter=360,
                         backend="numpy")
    d_ok = np.abs(got[inner].astype(int) - expected[inner]).mean()
    d_swapped = np.abs(got[inner].astype(int) - swapped[inner]).mean()
    assert d_ok < 0.25 and d_swapped > 1.5  # measured: 0.0003 and 2.3


def uniform_flow_like(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    f = np.empty((*image.shape[:2], 2), np.float32)
    f[..., 0], f[..., 1] = dx, dy
    return f


def test_grey_sequence_to_folder_and_video(tmp_path):
    (tmp_path / "in").mkdir()
    for i, f in enumerate(moving_frames(2)):
        write_image(tmp_path / "in" / f"{i}.png", np.ascontiguousarray(f[..., 1]))
    blur_video(tmp_path / "in", tmp_path / "out", backend="numpy")
    assert read_image(tmp_path / "out" / "1.png").shape == (H, W)
    blur_video(tmp_path / "in", tmp_path / "v.mp4", backend="numpy")
    assert probe(tmp_path / "v.mp4")["frames"][0].shape == (H, W, 3)


def test_float_tiff_sequence_round_trip(tmp_path):
    (tmp_path / "in").mkdir()
    for i, f in enumerate(moving_frames(2)):
        write_image(tmp_path / "in" / f"{i}.tif", (f / 255.0).astype(np.float32))
    blur_video(tmp_path / "in", tmp_path / "out", backend="numpy")
    out = read_image(tmp_path / "out" / "0.tif")
    assert out.dtype == np.float32 and out.shape == (H, W, 3)
    assert blur_video(tmp_path / "in", tmp_path / "v.mkv", fps=25, backend="numpy").frames == 2
    info = probe(tmp_path / "v.mkv")
    assert info["fps"] == 25 and info["times"] == [0.0, 0.04]


# --------------------------------------------------------------------------- --layers

def ball_over_stripes(x, h=48, w=96, y=24.0):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    ball = np.hypot(xx - x, yy - y) < 6
    return np.where(ball, 1.0, 0.12 + 0.1 * (np.sin(xx / 3.0) > 0)), ball


def test_layers_smear_a_moving_object_over_a_static_background():
    """Exact flow on the ball, zero elsewhere: --layers reproduces the true exposure; the plain
    gather cannot (its streak ends at the ball's silhouette)."""
    r = response("srgb")

    def picture(lin):
        return quantise(np.repeat(r.forward(lin)[..., None], 3, axis=2), np.uint8)

    x0, speed = 40.0, 16.0
    truth = picture(np.mean([ball_over_stripes(x0 + speed * t)[0]
                             for t in np.linspace(-0.5, 0.5, 321)], axis=0))
    lin, ball = ball_over_stripes(x0)
    frame = picture(lin)
    flow = np.zeros((*lin.shape, 2), np.float32)
    flow[ball, 0] = speed
    opts = dict(shutter=360, backend="numpy", samples=33)
    layered = blur_frame(frame, -flow, flow, "srgb", layers=True, **opts)
    gathered = blur_frame(frame, -flow, flow, "srgb", **opts)
    # measured: mean 0.21, max 10 (on the ball, where the hidden background is guessed)
    assert np.abs(layered.astype(int) - truth).mean() < 0.35 and err(layered, truth) <= 16
    assert np.abs(gathered.astype(int) - truth).mean() > 1.5 and err(gathered, truth) > 60


def test_layers_change_nothing_without_a_moving_layer(rng):
    frame = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    b, f = uniform_flow(-5, 1), uniform_flow(6, 2)
    np.testing.assert_array_equal(
        blur_frame(frame, b, f, "exp", layers=True, backend="numpy"),
        blur_frame(frame, b, f, "exp", backend="numpy"))
