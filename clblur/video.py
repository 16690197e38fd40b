"""Flow-driven motion blur for video: ``clblur video IN OUT``.

Conventions
-----------
* Frame ``i`` is the scene at its frame time ``t_i``; the synthetic shutter is open over
  ``[t_i - s T / 2, t_i + s T / 2]`` with ``T`` the frame interval and ``s = shutter / 360``
  (a shutter angle in degrees, 0..360), so the exposure is centred on the frame time.
* Motion vectors follow ``clblur.motion``: how far content travels across the sensor during the
  exposure (or part of it), x right, y down.  Flows follow ``clblur.flow``: the backward flow
  ``B`` of frame ``i`` points to where its content was in frame ``i-1``, the forward flow
  ``F`` to where it will be in frame ``i+1``.
* The path can bend: during the first half of the shutter content travels from ``p + s B / 2``
  to ``p`` (vector ``-s B / 2``, the frame time is the *end* of that half), during the second
  half from ``p`` to ``p + s F / 2`` (vector ``s F / 2``, the frame time is its *start*).
  Each half is a straight blur; both are integrated in the linear domain and averaged (the
  halves last equally long), then the response is re-applied once:
  ``g = I((E_first + E_second) / 2)``, which is the paper's Eq. 8 over the whole bent path.
* At the ends of a sequence one flow is missing; the other one is mirrored (constant velocity).
* ``samples`` counts samples per half of the shutter (default ``ceil(|v|) + 1`` per pixel).
  Each half includes its ends with equal weight (as ``clblur.blur`` does), so the frame-time
  sample, which ends both halves, counts twice.
* ``curved=True`` follows the parabola through the bent path's three points instead (start,
  frame time, end): chord ``D = first + second`` and quadratic term ``C = 2 (second -
  first)``, read at ``p - D t - C t^2`` for ``t`` in ``[-1/2, 1/2]``
  (``clblur.layered_exposure``, curved paths).  It bends where a point accelerates or turns
  (``D t + C t^2`` passes ``p + first`` at the start and ``p - second`` at the end, and
  ``C = 0`` is the straight chord), and its samples follow the curve: ``samples`` then counts
  samples over the whole shutter (default ``ceil(|D| + |C| / 2) + 1``).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from clblur.blur import blur, resolve_backend
from clblur.errors import InputError, InputTypeError
from clblur.flow import FlowEstimator, FlowFolder, save_flows
from clblur.io import refuse_overwrite
from clblur.io.video import (
    DEFAULT_CRF,
    Frame,
    ImageSequenceSource,
    VideoReadError,
    check_crf,
    open_sink,
    open_source,
)
from clblur.layered_exposure import layered_half
from clblur.layering import departure_order, named_order
from clblur.motion import check_exposure, curved_terms
from clblur.pipeline import run_numpy
from clblur.request import check_image, make_plan
from clblur.responses import per_channel

__all__ = ["DEFAULT_RESPONSE", "DEFAULT_SHUTTER", "VideoResult", "bent_path", "blur_curved",
           "blur_frame", "blur_video", "half_paths", "shutter_fraction"]

# Chosen from docs/studies/video.md (GoPro 240 fps ground truth).
DEFAULT_RESPONSE = "srgb"
DEFAULT_SHUTTER = 180.0


def shutter_fraction(shutter: float) -> float:
    """Shutter angle in degrees -> fraction of the frame interval the shutter is open."""
    try:
        s = float(shutter)
    except (TypeError, ValueError):
        raise InputTypeError(f"shutter must be an angle in degrees, got {shutter!r}") from None
    if not np.isfinite(s) or s < 0 or s > 360:
        raise InputError(f"shutter angle must be within 0..360 degrees, got {shutter}")
    return s / 360.0


def _check_flow(flow, shape: tuple[int, int], what: str) -> np.ndarray | None:
    if flow is None:
        return None
    f = np.asarray(flow, dtype=np.float32)
    if f.shape != (*shape, 2):
        raise InputError(f"{what} flow has shape {f.shape}, expected {(*shape, 2)}")
    if not np.isfinite(f).all():
        raise InputError(f"{what} flow contains NaN or infinite values")
    return f


def half_paths(backward: np.ndarray | None, forward: np.ndarray | None, shutter: float,
               shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel motion of the first and second half of the shutter (H x W x 2 float32 each).

    A missing flow mirrors the other; both missing (a single frame) means no motion.
    """
    s = shutter_fraction(shutter)
    b = _check_flow(backward, shape, "backward")
    f = _check_flow(forward, shape, "forward")
    if b is None and f is None:
        b = f = np.zeros((*shape, 2), np.float32)
    elif b is None:
        b = -f
    elif f is None:
        f = -b
    return (np.float32(-s / 2) * b, np.float32(s / 2) * f)


def blur_frame(frame: np.ndarray, backward: np.ndarray | None, forward: np.ndarray | None,
               response=DEFAULT_RESPONSE, *, shutter: float = DEFAULT_SHUTTER,
               samples: int | None = None, backend: str = "auto", saturation: float = 1.0,
               device: str | None = None, layers: bool = False,
               depth: np.ndarray | str | None = None, exposure: str = "frames",
               curved: bool = False) -> np.ndarray:
    """Blur one frame along the bent path given by its backward and forward flows.

    ``exposure``: how each half's samples are weighted (``clblur.blur``; ``"continuous"``:
    the trapezoid rule, for a real shutter).

    ``layers``: integrate each half as layered exposure (``clblur.layered_exposure``), so
    moving objects smear over what lies behind them, ordered by ``depth``: H x W (smaller =
    nearer), ``"departure"`` (what moves against the frame's dominant motion is nearer,
    ``clblur.layering.departure_order`` of the whole shutter's vectors) or ``"speed"`` /
    None (faster = nearer, each half by its own speed); without ``layers`` every pixel
    gathers along its own vector only.
    ``curved``: the parabola through the path's three points instead of two straight halves
    (module Conventions; :func:`blur_curved`).
    Returns an array with the frame's dtype and shape (see the module Conventions).
    """
    first, second = half_paths(backward, forward, shutter, check_image(frame).shape[:2])
    check_exposure(exposure)
    if curved:
        order = (depth if depth is not None else "speed") if layers else None
        return blur_curved(frame, first, second, response, samples=samples, backend=backend,
                           saturation=saturation, device=device, depth=order,
                           exposure=exposure)
    if isinstance(depth, str):
        named_order(depth)  # checked; speed: each half orders by its own vectors (None)
        depth = departure_order(first.astype(np.float64) + second) \
            if layers and depth == "departure" else None
    # The plan carries the frame, responses and saturation; the motion is the bent path the
    # integrator below closes over (the plan's own motion is not used).
    plan = make_plan(frame, (0.0, 0.0), response, saturation=saturation)
    backend = resolve_backend(backend, device)  # once per frame, not once per half
    if not layers and backend == "opencl":
        # the whole bent path on the device: one upload, one download per frame
        from clblur.opencl.bent_path import blur_bent

        return blur_bent(plan, first, second, samples, device, exposure=exposure)
    integrate = bent_path(first, second, samples=samples, backend=backend, device=device,
                          layers=layers, depth=depth, exposure=exposure)
    return run_numpy(plan, integrate)


def blur_curved(image: np.ndarray, first: np.ndarray, second: np.ndarray,
                response=DEFAULT_RESPONSE, *, depth: np.ndarray | str | None = None,
                samples: int | None = None, backend: str = "auto", saturation: float = 1.0,
                device: str | None = None, exposure: str = "frames") -> np.ndarray:
    """Blur ``image`` along the parabola through a bent path's three points (module
    Conventions): ``first`` (H x W x 2) ends at the frame time, ``second`` starts there.

    ``depth``: an occlusion ordering as ``clblur.blur`` takes it (an H x W depth or layer IDs,
    ``"speed"`` or ``"departure"`` of the chord): layered exposure along the curve
    (``clblur.layered_exposure``).  None: one surface, blurred along the curve.  Either way
    only the pixels that the curve or an occlusion concerns take the layered integrator
    (``clblur.layered_exposure.curved_region``); the others are the gather along the chord,
    which is the curve where ``C`` is nil.  Returns the image's dtype and shape.
    """
    from clblur.blur import stages
    from clblur.layered_exposure import integrator
    from clblur.pipeline import run

    shape = check_image(image).shape[:2]
    chord, bend = curved_terms(_check_flow(first, shape, "first half"),
                               _check_flow(second, shape, "second half"))
    if depth is None:  # one surface: layer IDs all 0, read along the curve
        depth = np.zeros(shape, np.int32)
    plan = make_plan(image, chord, response, anchor="center", samples=samples,
                     saturation=saturation, depth=depth, exposure=exposure, check_flow=True)
    ran = resolve_backend(backend, device)
    return run(plan, stages(ran, device), integrator(ran, device, curvature=bend))


def bent_path(first: np.ndarray, second: np.ndarray, *, samples: int | None = None,
              backend: str = "auto", device: str | None = None, layers: bool = False,
              depth: np.ndarray | None = None, exposure: str = "frames"):
    """Integrator (``clblur.pipeline``) of the bent path: the mean of the two halves' exposures.

    Each half is a straight blur of the linearised frame with the identity response (the
    halves are exposures, not pictures, so nothing is quantised before they are summed);
    ``layers`` integrates each half as layered exposure (``clblur.layered_exposure``) ordered
    by ``depth``, or by speed when ``depth`` is None.
    """
    opts = dict(samples=samples, backend=backend, device=device, exposure=exposure)

    def integrate(lin: np.ndarray, plan) -> np.ndarray:
        lin32 = lin.astype(np.float32)
        if layers:
            e_first = layered_half(lin32, first, "end", depth=depth, **opts)
            e_second = layered_half(lin32, second, "start", depth=depth, **opts)
        else:
            e_first = blur(lin32, first, "linear", anchor="end", **opts)
            e_second = blur(lin32, second, "linear", anchor="start", **opts)
        return 0.5 * (e_first.astype(np.float64) + e_second)
    return integrate


@dataclass
class VideoResult:
    output: Path
    frames: int
    fps: Fraction
    audio: str  # "copied", "none" or "dropped" (image-sequence output)
    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(
        ("decode", "flow", "blur", "encode"), 0.0))


class _Flows:
    """Backward/forward flow of each frame, estimated or read from a folder."""

    def __init__(self, flow: str, save_dir: str | os.PathLike | None):
        self.folder = FlowFolder(flow) if Path(flow).is_dir() else None
        self.estimate = None if self.folder else FlowEstimator(flow)
        self.save_dir = save_dir
        if save_dir is not None and Path(save_dir).exists() and not Path(save_dir).is_dir():
            raise InputError(f"--save-flows {save_dir} exists and is not a folder")
        # a missing folder is created by save_flows when the first flow is written

    def between(self, a: Frame, b: Frame) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(forward flow of ``a``, backward flow of ``b``) for neighbours ``a``, ``b``."""
        if self.folder is not None:
            shape = a.image.shape[:2]
            fwd = self.folder.get("forward", a.index, shape)
            bwd = self.folder.get("backward", b.index, shape)
            if fwd is None and bwd is None:  # one may be mirrored, but not both missing
                raise InputError(f"{self.folder.path} has neither forward_{a.index:06d} nor "
                                 f"backward_{b.index:06d}: no motion known between frames "
                                 f"{a.index} and {b.index}")
            return fwd, bwd
        return self.estimate(a.image, b.image), self.estimate(b.image, a.image)


def blur_video(src: str | os.PathLike, dst: str | os.PathLike, *,
               response=DEFAULT_RESPONSE, shutter: float = DEFAULT_SHUTTER,
               flow: str = "dis", samples: int | None = None, backend: str = "auto",
               saturation: float = 1.0, device: str | None = None, fps: float | None = None,
               codec: str | None = None, crf: int = DEFAULT_CRF,
               save_flows_to: str | os.PathLike | None = None, layers: bool = False,
               order: str = "speed", progress: bool = False,
               exposure: str = "frames", curved: bool = False) -> VideoResult:
    """Blur every frame of a video file or image folder ``src`` into ``dst``.

    The output keeps the input's frame rate and timestamps (``fps`` sets it for an image
    sequence) and copies the audio.  On unreadable or truncated input the frames decoded so
    far are blurred, written and finalised, then ``VideoReadError`` says how many.
    ``layers``: layered exposure, ordered by ``order`` (``"speed"`` or ``"departure"``,
    :func:`blur_frame`'s ``depth``); ``exposure`` and ``curved``: :func:`blur_frame`'s.
    """
    from tqdm import tqdm

    refuse_overwrite(dst, src)
    shutter_fraction(shutter)
    per_channel(response, 1)  # fail on a bad response before decoding anything
    named_order(order)  # and on a bad layer order
    check_exposure(exposure)
    check_crf(crf, dst, codec)
    if save_flows_to is not None:  # its files would replace or join the inputs
        for given, what in ((flow, "the --flow folder"), (src, "the input frames' folder")):
            if Path(given).is_dir() and Path(save_flows_to).resolve() == Path(given).resolve():
                raise InputError(f"--save-flows {save_flows_to} is {what}; name a new folder")
    flows = _Flows(flow, save_flows_to)
    source = open_source(src, fps)
    if fps is not None and not isinstance(source, ImageSequenceSource):
        source.close()
        raise InputError("fps only applies to image-sequence input; a video keeps its own rate")
    result = VideoResult(Path(dst), 0, source.fps, "none")
    sink, pending_audio = None, []
    timer = result.seconds

    def on_audio(packet):
        if sink is None:
            pending_audio.append(packet)
        elif sink.audio_supported:
            sink.copy_audio(packet)

    def emit(frame: Frame, backward, forward) -> None:
        t0 = time.perf_counter()
        out = blur_frame(frame.image, backward, forward, response, shutter=shutter,
                         samples=samples, backend=backend, saturation=saturation, device=device,
                         layers=layers, depth=order, exposure=exposure, curved=curved)
        t1 = time.perf_counter()
        sink.write(frame, out)
        timer["blur"] += t1 - t0
        timer["encode"] += time.perf_counter() - t1
        result.frames += 1
        bar.update()
        if save_flows_to is not None:
            save_flows(save_flows_to, frame.index, backward, forward)

    bar = tqdm(total=source.declared_frames, unit="frame", disable=not progress,
               desc=Path(src).name)
    frames = source.frames(on_audio)
    current, backward, finished = None, None, False
    try:
        while True:
            t0 = time.perf_counter()
            nxt = next(frames, None)
            timer["decode"] += time.perf_counter() - t0
            if nxt is None:
                break
            if sink is None:
                h, w = nxt.image.shape[:2]
                sink = open_sink(dst, source.fps, w, h, source.audio_stream, codec, crf)
                result.audio = ("none" if source.audio_stream is None else
                                "copied" if sink.audio_supported else "dropped")
                for packet in pending_audio:
                    on_audio(packet)
            if current is not None:
                if nxt.image.shape != current.image.shape:
                    raise VideoReadError(f"frame {nxt.index} changes size from "
                                         f"{current.image.shape} to {nxt.image.shape}",
                                         frames_read=nxt.index)
                t0 = time.perf_counter()
                forward, next_backward = flows.between(current, nxt)
                timer["flow"] += time.perf_counter() - t0
                emit(current, backward, forward)
                backward = next_backward
            current = nxt
        if current is not None:
            emit(current, backward, None)
        finished = True
    except VideoReadError as e:
        if current is not None:
            emit(current, backward, None)  # the last good frame, extrapolating its motion
            finished = True
        if sink is not None:
            sink.close(keep=True)
            sink = None
        kept = f"; kept the {result.frames} frame(s) written to {dst}" if result.frames else \
            "; nothing was written"
        raise VideoReadError(f"{e}{kept}", frames_read=result.frames) from None
    finally:
        bar.close()
        source.close()
        if sink is not None:
            sink.close(keep=finished)
    return result
