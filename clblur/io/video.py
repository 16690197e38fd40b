"""Video and image-sequence input/output for ``clblur video``.

Conventions
-----------
* Frames are H x W x 3 RGB arrays (H x W for grey image files).  Video files decode to uint8
  (``rgb24``), turned upright as their display matrix says (phones' portrait videos); image
  folders keep the dtype and layout of their files (uint8, uint16, float32 TIFF; alpha is
  dropped), and an image-folder output keeps them too (PNG, or TIFF for
  floats).  Encoding to video converts to 8-bit RGB.
* A path is an image sequence when it is a folder (or, for output, has no suffix or ends with
  a path separator); otherwise it is a video file and its suffix picks the container.
* Audio is copied packet for packet (no re-encoding), so the output container must accept the
  input's audio codec; image-sequence outputs cannot hold audio and report it as dropped.
* Bad input raises ``VideoReadError`` (a ``ValueError``) carrying ``frames_read``, the number of
  frames decoded before the problem, so a caller can keep and report what it already wrote.
  A stream that ends early without a decoder error (a cut-off file) is detected by comparing the
  decoded frames with the frame count or the duration the file declares for the video stream
  (MP4 and MOV store a count, Matroska a duration).  Formats that declare neither (raw streams,
  some AVI) can only report decoder errors.  An MP4 whose edit list hides frames would decode
  fewer frames than it declares and be reported as truncated (not seen in testing).
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.io.atomic import tmp_beside
from clblur.io.images import read_image, write_image
from clblur.io.paths import resolve_inside
from clblur.pixels import quantise

__all__ = ["CRF_RANGES", "DEFAULT_CRF", "IMAGE_SUFFIXES", "VIDEO_CODECS", "Frame",
           "ImageSequenceSink", "ImageSequenceSource", "VideoFileSink", "VideoFileSource",
           "VideoReadError", "check_crf", "is_image_sequence", "open_sink", "open_source"]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
# Default encoder per output container; libx264 at CRF 17 is visually lossless for most content.
VIDEO_CODECS = {".mp4": "libx264", ".mov": "libx264", ".mkv": "libx264", ".avi": "mpeg4",
                ".webm": "libvpx-vp9"}
DEFAULT_CRF = 17
# the encoders' constant-quality scales: x264 and x265 (8-bit) take 0 - 51, libvpx-vp9 0 - 63;
# out of range, FFmpeg refuses only when the first frame is encoded, after the first blur
CRF_RANGES = {"libx264": (0, 51), "libx265": (0, 51), "libvpx-vp9": (0, 63)}


class VideoReadError(ValueError):
    """The input could not be read (at all, or after ``frames_read`` frames)."""

    def __init__(self, message: str, frames_read: int = 0):
        super().__init__(message)
        self.frames_read = frames_read


@dataclass(frozen=True)
class Frame:
    index: int
    image: np.ndarray
    pts: int | None = None  # presentation time in ``time_base`` units (video files only)
    time_base: Fraction | None = None
    name: str | None = None  # file stem (image sequences only)


def is_image_sequence(path: str | os.PathLike, for_output: bool = False) -> bool:
    """A folder; for output also a new path with no suffix or a trailing separator."""
    p = Path(path)
    if p.is_dir():
        return True
    return for_output and (p.suffix == "" or str(path).endswith(("/", os.sep)))


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _warn_of_gaps(stems: list[str], folder: Path) -> None:
    """Warn when frames named alike (``frame_000170``, ...) skip numbers: the flow between two
    neighbours then spans more than one frame interval, and the blur is too long there."""
    parts = [re.fullmatch(r"(.*?)(\d+)(\D*)", s) for s in stems]
    if len(stems) < 3 or not all(parts) or len({(m[1], m[3]) for m in parts}) != 1:
        return
    numbers = [int(m[2]) for m in parts]
    steps = np.diff(numbers)
    usual = int(np.median(steps))
    jumps = np.flatnonzero(steps != usual)
    if usual > 0 and jumps.size:
        j = int(jumps[0])
        warnings.warn(f"{folder}: frame numbers jump from {numbers[j]} to {numbers[j + 1]}"
                      + (f" (and {jumps.size - 1} more)" if jumps.size > 1 else "")
                      + f" where the others step by {usual}: frames missing? The motion "
                      "between those neighbours spans more than one frame interval",
                      stacklevel=3)


class ImageSequenceSource:
    """Frames from the image files of a folder, in natural name order."""

    def __init__(self, folder: str | os.PathLike, fps: float | Fraction = 30):
        self.path = Path(folder)
        self.files = sorted((f for f in self.path.iterdir()
                             if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES),
                            key=lambda f: _natural_key(f.name))
        if not self.files:
            raise VideoReadError(f"no image files ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
        for f in self.files:  # a frame symlink must not lead out of the folder
            resolve_inside(self.path, f.name, f"image sequence {folder}: frame")
        self.fps = Fraction(fps).limit_denominator(1001000)
        self.declared_frames: int | None = len(self.files)
        self.audio_stream = None
        _warn_of_gaps([f.stem for f in self.files], self.path)

    def frames(self, on_audio: Callable | None = None) -> Iterator[Frame]:
        shape = dtype = None
        for i, f in enumerate(self.files):
            try:
                img = read_image(f)
            except ValueError as e:
                raise VideoReadError(f"frame {i} ({f.name}): {e}", frames_read=i) from None
            if img.ndim == 3 and img.shape[2] == 4:
                img = img[..., :3]  # video frames carry no alpha
            if shape is not None and img.shape != shape:
                raise VideoReadError(f"frame {i} ({f.name}) has shape {img.shape}, earlier "
                                     f"frames {shape}", frames_read=i)
            if dtype is not None and img.dtype != dtype:
                raise VideoReadError(f"frame {i} ({f.name}) is {img.dtype}, earlier frames "
                                     f"{dtype}: one bit depth per sequence", frames_read=i)
            shape, dtype = img.shape, img.dtype
            yield Frame(i, img, name=f.stem)

    def close(self) -> None:
        pass


class VideoFileSource:
    """Frames (and audio packets) of a video file, decoded with PyAV."""

    def __init__(self, path: str | os.PathLike):
        import av

        self.path = Path(path)
        if not self.path.is_file():
            raise VideoReadError(f"video file not found: {path}")
        try:
            self.container = av.open(str(self.path))
        except av.FFmpegError as e:
            raise VideoReadError(f"cannot read video {path}: {e}") from None
        if not self.container.streams.video:
            self.container.close()
            raise VideoReadError(f"{path} has no video stream")
        form = self.container.format.name
        if form == "image2" or form.endswith("_pipe"):
            # FFmpeg reads a still image as a one-frame video, which would come out as it went
            # in (no neighbour, no flow): say so rather than write an unblurred copy
            self.container.close()
            raise VideoReadError(f"{path} is a single image, not a video: give a video file "
                                 "or a folder of frames (clblur blur IN OUT --motion/--flow "
                                 "blurs one image)")
        self.video_stream = self.container.streams.video[0]
        self.video_stream.thread_type = "AUTO"
        self.audio_stream = (self.container.streams.audio[0]
                             if self.container.streams.audio else None)
        rate = self.video_stream.average_rate or self.video_stream.guessed_rate
        if not rate:
            self.container.close()
            raise VideoReadError(f"{path}: the video stream declares no frame rate")
        self.fps = Fraction(rate)
        self.declared_end: float | None = None  # set from a Matroska duration tag
        self.declared_frames = self._declared_frames()

    def _declared_end(self) -> float | None:
        """End time (s) of the video stream as the file declares it, if it does."""
        # Only Matroska's per-stream tag (HH:MM:SS.fffffffff, the end of the last packet) is
        # trusted: FFmpeg fills ``stream.duration`` from the container when it has to guess,
        # which would flag a video with a longer audio track as cut off.
        tag = self.video_stream.metadata.get("DURATION")
        if tag:
            try:
                h, m, sec = tag.split(":")
                return int(h) * 3600 + int(m) * 60 + float(sec)
            except ValueError:
                return None
        return None

    def _declared_frames(self) -> int | None:
        """Frame count from the stream header, else estimated from its duration."""
        if self.video_stream.frames:
            return int(self.video_stream.frames)
        self.declared_end = self._declared_end()
        if self.declared_end is None:
            return None
        start = self.video_stream.start_time
        start = float(start * self.video_stream.time_base) if start else 0.0
        return max(1, int(round((self.declared_end - start) * float(self.fps))))

    def frames(self, on_audio: Callable | None = None) -> Iterator[Frame]:
        """Decode the video; audio packets go to ``on_audio`` as they are demuxed."""
        import av

        streams = [self.video_stream] + ([self.audio_stream] if self.audio_stream else [])
        n, last_end = 0, None
        try:
            for packet in self.container.demux(*streams):
                if packet.stream.type == "audio":
                    if on_audio is not None and packet.dts is not None:
                        on_audio(packet)
                    continue
                for vf in packet.decode():
                    if vf.time is not None:
                        last_end = vf.time + 1 / float(self.fps)
                    yield Frame(n, _upright(vf), pts=vf.pts, time_base=vf.time_base)
                    n += 1
        except av.FFmpegError as e:
            raise VideoReadError(f"{self.path}: decoding failed after {n} frame(s): {e}",
                                 frames_read=n) from None
        if n == 0:
            raise VideoReadError(f"{self.path}: no frame could be decoded")
        declared = self.video_stream.frames
        if declared and n < declared:
            raise VideoReadError(f"{self.path} is truncated: it declares {declared} frames "
                                 f"but only {n} could be decoded", frames_read=n)
        # Without a frame count, a cut-off file ends before its declared duration; half a
        # frame interval absorbs timestamp rounding (Matroska stores milliseconds).
        if (not declared and self.declared_end is not None and last_end is not None
                and last_end < self.declared_end - 0.5 / float(self.fps)):
            raise VideoReadError(f"{self.path} is truncated: its video stream should last "
                                 f"until {self.declared_end:.3f} s but the last decodable "
                                 f"frame ends at {last_end:.3f} s ({n} frames)", frames_read=n)

    def close(self) -> None:
        self.container.close()


def _upright(vf) -> np.ndarray:
    """A decoded frame as RGB, turned as its display matrix says.

    Phones store a portrait video's frames sideways and add a display matrix that players
    apply; without it the blurred output (written without one) would play sideways.  PyAV's
    ``rotation`` is the matrix's counter-clockwise turn in degrees (ffmpeg's autorotate
    applies the same); turns that are not quarter turns are left alone, as is an older PyAV
    without the attribute."""
    image = vf.to_ndarray(format="rgb24")
    turn = getattr(vf, "rotation", 0) or 0
    quarters = round(turn / 90)
    if quarters % 4 and abs(turn - 90 * quarters) < 1:
        image = np.ascontiguousarray(np.rot90(image, quarters))
    return image


def open_source(path: str | os.PathLike, fps: float | None = None):
    """An image-sequence or video-file source.  ``fps`` sets an image sequence's rate."""
    if is_image_sequence(path):
        return ImageSequenceSource(path, fps if fps is not None else 30)
    if not Path(path).exists():
        raise VideoReadError(f"input not found: {path}")
    return VideoFileSource(path)


class ImageSequenceSink:
    """Writes each frame as its own PNG (or TIFF for float frames), atomically."""

    audio_supported = False

    def __init__(self, folder: str | os.PathLike):
        self.path = Path(folder)
        if not self.path.exists():
            if not self.path.parent.exists():
                raise InputError(f"output folder's parent does not exist: {self.path.parent}")
            self.path.mkdir()
        self.written = 0

    def write(self, frame: Frame, image: np.ndarray) -> None:
        stem = frame.name if frame.name is not None else f"frame_{frame.index:06d}"
        write_image(self.path / f"{stem}{'.tif' if image.dtype.kind == 'f' else '.png'}", image)
        self.written += 1

    def copy_audio(self, packet) -> None:  # pragma: no cover - never called (no audio)
        raise InputError("an image sequence cannot hold audio")

    def close(self, keep: bool = True) -> None:
        pass


def check_crf(crf: int, path: str | os.PathLike, codec: str | None = None) -> None:
    """Refuse a ``crf`` the encoder that ``path`` (or ``codec``) gets would reject; image
    sequences and encoders without a ``crf`` scale take any integer."""
    if isinstance(crf, bool) or not isinstance(crf, (int, np.integer)):
        raise InputError(f"crf must be an integer, got {crf!r}")
    suffix = Path(path).suffix.lower()
    codec = codec or VIDEO_CODECS.get(suffix)
    if suffix in VIDEO_CODECS and codec in CRF_RANGES:
        lo, hi = CRF_RANGES[codec]
        if not lo <= crf <= hi:
            raise InputError(f"crf {crf} is outside {codec}'s quality scale {lo} - {hi} "
                             "(lower is better)")


class VideoFileSink:
    """Encodes frames into a temporary file beside ``path``; ``close`` renames it into place."""

    audio_supported = True

    def __init__(self, path: str | os.PathLike, fps: Fraction, width: int, height: int,
                 audio_template=None, codec: str | None = None, crf: int = DEFAULT_CRF):
        import av

        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in VIDEO_CODECS:
            raise InputError(f"unknown video container {suffix!r} for {path}; use one of "
                             f"{', '.join(VIDEO_CODECS)} or a folder for an image sequence")
        if not self.path.parent.exists():
            raise InputError(f"output folder does not exist: {self.path.parent}")
        codec = codec or VIDEO_CODECS[suffix]
        check_crf(crf, self.path, codec)
        self.tmp = tmp_beside(self.path)
        self.container = av.open(str(self.tmp), "w", format=suffix.lstrip(".").replace(
            "mkv", "matroska"))
        self.stream = self.audio = None
        try:
            self._add_streams(codec, fps, width, height, crf, audio_template)
        except BaseException:
            self.close(keep=False)  # no half-made temporary file is left behind
            raise
        self.written = 0

    def _add_streams(self, codec, fps, width, height, crf, audio_template) -> None:
        import av

        try:
            stream = self.container.add_stream(codec, rate=fps)
        except (av.FFmpegError, ValueError) as e:
            raise InputError(f"cannot encode with codec {codec!r}: {e}") from None
        stream.width, stream.height = width, height
        stream.pix_fmt = _pixel_format(codec, width, height)
        if codec in ("libx264", "libx265", "libvpx-vp9"):
            stream.options = {"crf": str(int(crf))}
        self.stream = stream
        if audio_template is not None:
            try:
                self.audio = self.container.add_stream_from_template(audio_template)
            except (av.FFmpegError, ValueError) as e:
                raise InputError(f"cannot copy the input's {audio_template.codec_context.name}"
                                 f" audio into {self.path.suffix}: {e}; pick another "
                                 "container (.mkv takes most codecs)") from None

    def write(self, frame: Frame, image: np.ndarray) -> None:
        import av

        vf = av.VideoFrame.from_ndarray(_to_rgb24(image), format="rgb24")
        if frame.pts is not None:  # keep the input's timing (and so audio sync)
            vf.pts, vf.time_base = frame.pts, frame.time_base
        else:
            vf.pts, vf.time_base = frame.index, 1 / self.stream.codec_context.framerate
        self.container.mux(self.stream.encode(vf))
        self.written += 1

    def copy_audio(self, packet) -> None:
        packet.stream = self.audio
        self.container.mux(packet)

    def close(self, keep: bool = True) -> None:
        """Flush and finalise; ``keep=False`` discards the output."""
        try:
            if keep and self.stream is not None:
                self.container.mux(self.stream.encode(None))
        finally:
            self.container.close()
        if keep and self.written:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)


def _pixel_format(codec: str, width: int, height: int) -> str:
    even = width % 2 == 0 and height % 2 == 0
    if even:
        return "yuv420p"
    if codec in ("libx264", "libx265", "libvpx-vp9"):
        return "yuv444p"  # 4:2:0 needs even sizes; these codecs also take full chroma
    raise InputError(f"codec {codec} needs an even frame size, got {width} x {height}; "
                     "write .mp4/.mkv (libx264) or an image folder instead")


def _to_rgb24(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:  # grey image sequences
        image = np.repeat(image[..., None], 3, axis=2)
    if image.dtype == np.uint8:
        return np.ascontiguousarray(image)
    if image.dtype == np.uint16:  # 16-bit image sequences into an 8-bit codec
        return np.rint(image / 257.0).astype(np.uint8)
    if image.dtype.kind == "f":  # normalised float frames (TIFF sequences)
        return quantise(image, np.uint8)
    raise InputTypeError(f"cannot encode {image.dtype} frames as video")


def open_sink(path: str | os.PathLike, fps: Fraction, width: int, height: int,
              audio_template=None, codec: str | None = None, crf: int = DEFAULT_CRF):
    if is_image_sequence(path, for_output=True):
        return ImageSequenceSink(path)
    return VideoFileSink(path, fps, width, height, audio_template, codec, crf)
