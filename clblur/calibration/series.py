"""Exposure series: the images of one static scene taken at several known exposures.

Conventions
-----------
* ``exposures`` are exposure *times* in seconds (any consistent unit), ``f_numbers`` the
  aperture of each image or None when unknown.  The photometric exposure of image ``i`` is
  ``t_i / N_i**2`` (``relative_exposures``); with no F-numbers it is just ``t_i``.
* Images keep their file dtype (uint8 / uint16 / float32) and are H x W x C (a grey image gets
  C = 1).  Values are normalised by the dtype's full scale (``clblur.pixels.imax``).
* Sources, in order of precedence: a manifest of kind ``exposure-series``; a folder of images
  plus a times file or sequence; EXIF ``ExposureTime`` / ``FNumber`` of the images.
* Clipping below full scale: a camera whose highlights stop at a code under full scale (a
  JPEG engine that clips at 230, video-range levels, raw data in a wider container) would
  have its clipped pixels taken for light.  ``ExposureSeries.white_level`` finds such a
  level (``clblur.pixels.series_clip_level``) and the valid ranges of sampling, fitting and
  evaluation scale with it; a series that clips at full scale is untouched.
* Registration: ``load_series`` registers the images (``clblur.registration``: the
  whole-pixel translation between hand-held exposures) and crops them to the window all of
  them cover; ``ExposureSeries.registration`` records it.  A series built from arrays is
  taken as it is; ``aligned()`` registers it.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from dataclasses import dataclass
from fractions import Fraction
from functools import cached_property
from pathlib import Path
from typing import NamedTuple

import numpy as np

from clblur.errors import InputError, InputTypeError
from clblur.io import codec_block, light_channels, read_image, require_file, resolve_inside
from clblur.manifest import Exposure, Manifest, load_manifest
from clblur.pixels import clip_level, code_step, imax, near_clip, series_clip_level
from clblur.registration import Registration, align_series

__all__ = ["IMAGE_SUFFIXES", "ExposureSeries", "check_brightening", "exif_exposure", "exif_iso",
           "folder_series", "load_series", "parse_time", "photometric_exposure",
           "read_times_file", "series_files", "TimeRow"]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".ppm", ".pgm", ".pnm")
# check_brightening: a pixel at least this bright (fraction of full scale) in the shorter of
# two exposures lies above any black level's noise (dark frames of a pedestal brighten and
# darken at random: Memorial's darkest steps, 1 stop apart, brighten only 22 - 53 % of their
# pixels above 2 % of full scale, and 86 - 100 % of those above 25 %); steps closer than
# BRIGHTEN_RATIO are not judged (noise could outweigh them)
BRIGHTEN_FROM = 0.25
BRIGHTEN_RATIO = 1.2
_EXIF_IFD, _EXPOSURE_TIME, _F_NUMBER, _ISO = 0x8769, 0x829A, 0x829D, 0x8827


def check_brightening(images: list[np.ndarray], exposures, names: list[str],
                      white_level: float = 1.0) -> None:
    """Refuse a series whose images do not brighten with their exposures: times in the wrong
    order, a frame repeated under another time, a file given the wrong time.

    For each step between neighbouring exposures (photometric, ``exposures``) at least
    ``BRIGHTEN_RATIO`` apart, over the pixels that the shorter one exposes at ``BRIGHTEN_FROM``
    of full scale or more and that neither clips (below ``0.98 white_level``), a longer
    exposure brightens nearly every one: at worst 86 % on the shared real series (Memorial,
    Canon 400D).  Fewer than half (a swapped pair: none; a repeated frame: about half, by
    noise) raises ValueError naming the two images.  Every 4th row is read (a check, not a
    fit); a step with fewer than 100 such pixels is not judged.
    """
    x = np.asarray(exposures, dtype=np.float64)
    order = np.argsort(x, kind="stable")
    for a, b in zip(order[:-1], order[1:], strict=True):
        if x[b] < BRIGHTEN_RATIO * x[a]:
            continue
        full = imax(images[a].dtype)
        lo, hi = BRIGHTEN_FROM * full, 0.98 * white_level * full
        short, long_ = images[a][::4], images[b][::4]
        both = (short >= lo) & (short < hi) & (long_ < hi)
        n = int(np.count_nonzero(both))
        if n < 100:
            continue
        up = np.count_nonzero(both & (long_ > short)) / n
        if up < 0.5:
            raise InputError(
                f"{names[b]} is not brighter than {names[a]} although its exposure is "
                f"{x[b] / x[a]:.3g}x as long: only {100 * up:.0f} % of the pixels both expose "
                "well brighten; check the times (their order, a repeated frame)")


def photometric_exposure(times, f_numbers=None) -> np.ndarray:
    """The light each exposure gathers, up to one constant: ``t / N**2`` (exposure time over
    the F-number squared), or the times themselves where no F-number is given (``f_numbers``
    None, or None for every image).  Float64, one per image.  Raises ValueError when only
    some images have an F-number (times and ``t / N**2`` are not one unit)."""
    t = np.asarray(times, dtype=np.float64)
    if f_numbers is None or all(f is None for f in f_numbers):
        return t
    if any(f is None for f in f_numbers) or len(f_numbers) != t.size:
        raise InputError("give an F-number for every image or for none")
    return t / np.asarray(f_numbers, dtype=np.float64) ** 2


# px beyond a JPEG's clipped region left out of calibration: the ringing's first lobes and the
# subsampled chroma value a decoder's upsampling reads across.  On the Memorial radiance-map
# bracket (JPEG q90 4:2:0) the nonparametric and EMoR curves came within 2 % of the truth
# above 0.8 of full scale with 2 or 4 (50 % and 98 % off in blue with none; 8 - 20 % with a
# whole block every way, which leaves the top few samples; docs/studies/validation.md)
CODEC_MARGIN = 2


@dataclass(frozen=True, eq=False)  # holds arrays: compare series by identity
class ExposureSeries:
    """A validated stack; construct it with ``load_series`` or ``ExposureSeries.create``."""

    images: list[np.ndarray]
    exposures: np.ndarray
    f_numbers: np.ndarray | None
    names: list[str]
    registration: Registration | None = None  # set by aligned(): how the images were cut
    # the side of the blocks a lossy codec coded the images in (a JPEG's 8 or 16 pixels,
    # ``clblur.io.images.codec_block``); 1 for lossless storage (``coded_near_clip``)
    block: int = 1

    @classmethod
    def create(cls, images, exposures, f_numbers=None, names=None,
               block: int = 1) -> ExposureSeries:
        """Validate arrays already in memory (shapes, dtypes, times) and build a series;
        ``block``: the side of the blocks a lossy codec coded them in (1: lossless)."""
        images = [_as_hwc(np.asarray(im), i) for i, im in enumerate(images)]
        if len(images) < 2:
            raise InputError(f"an exposure series needs at least 2 images, got {len(images)}")
        t = _check_times(exposures, len(images))
        fn = None
        if f_numbers is not None and any(f is not None for f in f_numbers):
            photometric_exposure(t, f_numbers)  # every image has one, or it raises
            fn = np.asarray(f_numbers, dtype=np.float64)
            if not np.all(np.isfinite(fn)) or np.any(fn <= 0):
                raise InputError(f"F-numbers must be positive and finite, got {fn.tolist()}")
        names = list(names) if names is not None else [f"image{i}" for i in range(len(images))]
        first = images[0]
        for name, im in zip(names, images, strict=True):
            if im.shape != first.shape:
                raise InputError(f"images of different sizes: {names[0]} is {first.shape}, "
                                 f"{name} is {im.shape}")
            if im.dtype != first.dtype:
                raise InputError(f"images of different dtypes: {names[0]} is {first.dtype}, "
                                 f"{name} is {im.dtype}")
        key = t if fn is None else t / fn**2
        order = np.argsort(key)
        dup = np.flatnonzero(np.isclose(np.diff(key[order]), 0.0, rtol=1e-9, atol=0.0))
        if dup.size:
            a, b = order[dup[0]], order[dup[0] + 1]
            raise InputError(f"duplicate exposures: {names[a]} and {names[b]} both have "
                             f"exposure {t[a]:g}" + ("" if fn is None else f" at f/{fn[a]:g}"))
        return cls(images, t, fn, names, block=max(1, int(block)))

    @property
    def dtype(self) -> np.dtype:
        return self.images[0].dtype

    @property
    def full_scale(self) -> float:
        return imax(self.dtype)

    @property
    def channels(self) -> int:
        return self.images[0].shape[2]

    @property
    def shape(self) -> tuple[int, int]:
        return self.images[0].shape[:2]

    @cached_property
    def white_level(self) -> float:
        """The value (fraction of full scale) at which the series clips
        (``clblur.pixels.series_clip_level``): 1.0 for clipping at full scale; lower for a
        camera that piles its highlights up below it, or, stored lossless, whose clipped
        pixels read below the pile (noise added after the clip, ``pile_floor``)."""
        return series_clip_level(self.images, self.relative_exposures(),
                                 lossless=self.block <= 1)

    @cached_property
    def moving(self) -> np.ndarray:
        """H x W bool: pixels that do not show one static scene across the series (a moving
        object, a border one frame lacks; ``clblur.calibration.ghosts``), left out of the
        calibration's samples and of its held-out scores."""
        from clblur.calibration.ghosts import moving_pixels

        return moving_pixels(self.images, self.relative_exposures(), self.full_scale)

    def moving_note(self) -> str | None:
        """A line saying how much of the frame is left out as moving, or None."""
        share = float(self.moving.mean())
        if share == 0.0:
            return None
        return (f"left out as not static: {100 * share:.1f} % of the pixels (inconsistent "
                "between neighbouring exposures: something moved, or a border differs)")

    def clipping_note(self) -> str | None:
        """A line saying that the series clips below full scale, or None."""
        if self.white_level >= 1.0:
            return None
        code = f"{self.white_level * self.full_scale:g} of {self.full_scale:g}"
        order = np.argsort(self.relative_exposures())[::-1]
        pile = clip_level(self.images[order[0]],
                          self.images[order[1]] if len(order) > 1 else None)
        if pile <= self.white_level:
            return (f"clips below full scale: the longest exposure piles up at code {code}; "
                    "the valid ranges of sampling and evaluation end below it")
        return (f"clips at code {code}: noise added after the clip spreads its pile at "
                f"{pile * self.full_scale:g} down to there; the valid ranges of sampling and "
                "evaluation end below it")

    def coded_near_clip(self, index: int, reach: int = 0) -> np.ndarray | None:
        """H x W bool for images coded in blocks (``block`` > 1, a JPEG): image ``index``'s
        clipped region as the codec left it (at the series' ``white_level``, any channel,
        gaps narrower than a block closed; ``clblur.pixels.near_clip``) and
        ``CODEC_MARGIN + reach`` pixels around it, left out of the samples and the held-out
        scores; None for lossless storage."""
        if self.block <= 1:
            return None
        top = (self.white_level - 0.5 * code_step(self.dtype)) * self.full_scale
        return near_clip(self.images[index], top, self.block, CODEC_MARGIN + reach)

    def relative_exposures(self) -> np.ndarray:
        """Photometric exposure ``t / N**2`` divided by its maximum (the longest is 1)."""
        x = photometric_exposure(self.exposures, self.f_numbers)
        return x / x.max()

    def values(self) -> np.ndarray:
        """All images normalised to [0, 1], float32, shape (n, H, W, C)."""
        return np.stack([im.astype(np.float32) for im in self.images]) / np.float32(
            self.full_scale)

    def aligned(self, turns: bool = True) -> ExposureSeries:
        """The series registered and cropped to the window every image covers (views of the
        images where they moved by whole pixels; the same images when nothing moved), with
        ``registration`` set; ``turns``: also find turns between the frames
        (``clblur.registration.align_series``)."""
        reg = align_series(self.images, self.relative_exposures(), turns=turns)
        images = ([reg.crop(im, i) for i, im in enumerate(self.images)] if reg.moved
                  else self.images)
        return ExposureSeries(images, self.exposures, self.f_numbers, self.names, reg,
                              self.block)

    def subset(self, keep) -> ExposureSeries:
        """The series restricted to the images whose indices are in ``keep`` (order kept); it
        keeps the series' ``white_level`` (the camera clips where it clips, whichever images
        are left to show it)."""
        keep = [int(i) for i in keep]
        fn = None if self.f_numbers is None else self.f_numbers[keep]
        out = ExposureSeries([self.images[i] for i in keep], self.exposures[keep], fn,
                             [self.names[i] for i in keep], block=self.block)
        out.__dict__["white_level"] = self.white_level  # the cached_property's slot
        if "moving" in self.__dict__:  # what moved in the series moved in its subsets too
            out.__dict__["moving"] = self.moving
        return out


def _as_hwc(im: np.ndarray, index: int) -> np.ndarray:
    if im.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise InputTypeError(f"image {index}: unsupported dtype {im.dtype}")
    if im.ndim == 2:
        return im[:, :, None]
    if im.ndim != 3:
        raise InputError(f"image {index}: expected H x W or H x W x C, got shape {im.shape}")
    return im[:, :, :3] if im.shape[2] == 4 else im  # alpha carries no exposure


def _check_times(times, n: int) -> np.ndarray:
    if times is None:
        raise InputError("exposure times are missing")
    t = np.asarray([parse_time(v) for v in times], dtype=np.float64)
    if t.size != n:
        raise InputError(f"got {t.size} exposure times for {n} images")
    bad = np.flatnonzero(~np.isfinite(t) | (t <= 0))
    if bad.size:
        raise InputError(f"exposure times must be positive and finite; entry {bad[0]} is "
                         f"{t[bad[0]]}")
    return t


def parse_time(value) -> float:
    """A time as a number or a string such as ``0.25``, ``1/1024`` or ``1/60s``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(
            value, (str, int, float, np.floating, np.integer)):
        raise InputTypeError(f"exposure time must be a number or a string, got {value!r}")
    try:
        if not isinstance(value, str):
            return float(value)
        text = value.strip().removesuffix("s").strip()
        return float(Fraction(text))
    except OverflowError:  # a number too large for a float: no exposure time
        raise InputError(f"exposure time {str(value)[:40]!r} is out of range") from None
    except (ValueError, ZeroDivisionError):
        raise InputError(f"cannot read exposure time {value!r}; use e.g. 0.5 or 1/1024") from None


class TimeRow(NamedTuple):
    """One line of a times file: the image it names (None when lines name none), its
    exposure time (seconds, or relative to ``2**0`` for stop offsets) and its F-number (None
    unless the file gives one)."""

    name: str | None
    time: float
    f_number: float | None = None


_STOPS = "EV"  # a time written as a stop offset: "+2EV" gathers 4x the light of "0EV"


def _time_or_stops(token: str) -> tuple[float, bool]:
    """A times file's exposure: ``(seconds, False)`` or, for ``[+-]N EV`` (a bracket's
    exposure compensation, brighter for +), ``(2**N, True)``."""
    if token.upper().endswith(_STOPS):
        try:
            stops = float(token[:-len(_STOPS)])
        except ValueError:
            raise InputError(f"cannot read stop offset {token!r}; use e.g. -2EV, 0EV, +1.5EV") \
                from None
        if not math.isfinite(stops) or abs(stops) > 60:
            raise InputError(f"stop offset {token!r} is out of range")
        return 2.0 ** stops, True
    t = parse_time(token)
    if not t > 0:  # a bracket listed as 0, -2, +2 is a list of stops, not of times
        raise InputError(f"exposure time {token!r} is not positive; if the file lists stop "
                         "offsets, write them with their unit (e.g. -2EV, 0EV, +2EV)")
    return t, False


def _hdrshop_row(parts: list[str]) -> TimeRow:
    """A line of an HDRShop image list (Debevec's stacks ship one: ``memorial0061.ppm
    0.03125 8 0 0``): name, 1/shutter time, f-stop, gain in dB, ND filters.  The gain scales
    the time as an amplitude (``10**(dB / 20)``); ND filters, whose unit the format leaves
    open, must be 0."""
    name, inverse, f_stop, gain, nd = parts
    try:
        inv, f, db, filters = parse_time(inverse), float(f_stop), float(gain), float(nd)
    except ValueError:
        raise InputError(f"expected numbers after the name, got {' '.join(parts[1:])!r}") \
            from None
    if not (inv > 0 and math.isfinite(1.0 / inv)):
        raise InputError(f"1/shutter_speed {inverse!r} is not a positive number")
    if not (f > 0 and math.isfinite(f)):
        raise InputError(f"f/stop {f_stop!r} is not a positive number")
    if not math.isfinite(db):
        raise InputError(f"gain {gain!r} dB is not a number")
    if filters != 0:
        raise InputError(f"ND_filters is {nd!r}: their attenuation is not stated by the "
                         "format; give the filtered images' effective times instead")
    return TimeRow(name, 10.0 ** (db / 20.0) / inv, f)


def read_times_file(path: str | os.PathLike) -> list[TimeRow]:
    """The exposures of a times file, one :class:`TimeRow` per image.

    Lines are ``TIME`` or ``NAME TIME`` (``#`` comments and blank lines ignored); a time is
    seconds (``0.5``, ``1/1024``, ``1/60s``) or a stop offset (``-2EV``, ``0EV``, ``+2EV``:
    ``2**N``, brighter for +), one kind in a file.  An HDRShop image list (lines ``NAME
    1/SHUTTER FSTOP GAIN_DB ND``, optionally after a line with their count: the format of
    Debevec & Malik's published stacks) gives times and F-numbers (``_hdrshop_row``).
    """
    path = Path(path)
    require_file(path, "times")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"times file {path} is not a text file") from None
    lines = [(n, line.split("#", 1)[0].split()) for n, line in enumerate(text.splitlines(), 1)]
    lines = [(n, parts) for n, parts in lines if parts]
    hdrshop = any(len(parts) == 5 for _, parts in lines)
    if hdrshop and lines and len(lines[0][1]) == 1 and lines[0][1][0].isdigit():
        count = int(lines[0][1][0])  # HDRShop's first line: how many images follow
        lines = lines[1:]
        if count != len(lines):
            raise InputError(f"{path}: the image list announces {count} images and lists "
                             f"{len(lines)}")
    rows, stops = [], set()
    for lineno, parts in lines:
        try:
            if hdrshop:
                if len(parts) != 5:
                    raise InputError("expected an HDRShop image list line 'NAME 1/SHUTTER "
                                     f"FSTOP GAIN_DB ND' like the others, got {' '.join(parts)!r}")
                rows.append(_hdrshop_row(parts))
                continue
            if len(parts) > 2:
                raise InputError(f"expected 'TIME' or 'NAME TIME', got {' '.join(parts)!r}")
            t, is_stops = _time_or_stops(parts[-1])
            stops.add(is_stops)
            rows.append(TimeRow(parts[0] if len(parts) == 2 else None, t))
        except ValueError as e:
            raise InputError(f"{path}:{lineno}: {e}") from None
    if len(stops) > 1:
        raise InputError(f"times file {path} mixes times and stop offsets (EV); use one kind")
    return rows


def _exif_numbers(path: Path, tags: tuple[int, ...]) -> list[float | None]:
    """Numeric EXIF tags of an image (the Exif IFD, else IFD0), None where absent or not a
    number; the first value of a tuple (ISO may be stored as one)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(_EXIF_IFD)
    except OSError:
        return [None] * len(tags)

    def get(tag):
        v = sub.get(tag, exif.get(tag))
        if isinstance(v, (tuple, list)):
            v = v[0] if v else None
        try:
            return None if v is None else float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            return None

    return [get(tag) for tag in tags]


def exif_exposure(path: Path) -> tuple[float | None, float | None]:
    """(ExposureTime, FNumber) from an image's EXIF, None where absent."""
    t, n = _exif_numbers(path, (_EXPOSURE_TIME, _F_NUMBER))
    return t, n


def exif_iso(path: Path) -> float | None:
    """The ISO speed (PhotographicSensitivity) from an image's EXIF, None where absent."""
    return _exif_numbers(path, (_ISO,))[0]


def series_files(folder: Path) -> list[Path]:
    """The images of an exposure series held in ``folder`` (by suffix, name order)."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def load_series(source: str | os.PathLike, times=None, align: bool = True) -> ExposureSeries:
    """Load an exposure series from a manifest (``.json``) or a folder of images.

    ``times``: for a folder, a times file path or a sequence of times in the images' sorted
    name order; a file may also name each image (``NAME TIME``).  Without times, each image's
    EXIF ExposureTime (and FNumber) is used.  ``align``: register the images and crop them to
    their common window (module Conventions); False takes them as they are.
    """
    source = Path(source)
    if source.is_file():
        if times is not None:
            raise InputError("times are given by the manifest; do not pass --times with one")
        m = load_manifest(source)
        if m.kind != "exposure-series":
            raise InputError(f"manifest {source} is of kind {m.kind!r}, expected "
                             "'exposure-series'")
    else:
        m = folder_series(source, times)
    series = ExposureSeries.create([light_channels(read_image(e.path)) for e in m.images],
                                   [e.exposure for e in m.images],
                                   [e.f_number for e in m.images],
                                   [e.path.name for e in m.images],
                                   block=max(codec_block(e.path) for e in m.images))
    return series.aligned() if align else series


def _match_converted(by_name: dict, files: list[Path]) -> dict:
    """``by_name`` keyed by the folder's file names where a times file names converted
    copies: an image list written for ``memorial0061.ppm`` names ``memorial0061.png`` once
    the stack is re-saved.  Only when no listed name is in the folder and every listed stem
    is the stem of exactly one image there; otherwise ``by_name`` as it is."""
    names = {p.name for p in files}
    stems = Counter(p.stem for p in files)
    if any(n in names for n in by_name) or \
            not all(stems.get(Path(n).stem) == 1 for n in by_name) or \
            len({Path(n).stem for n in by_name}) != len(by_name):
        return by_name
    by_stem = {p.stem: p.name for p in files}
    return {by_stem[Path(n).stem]: row for n, row in by_name.items()}


def folder_series(source: str | os.PathLike, times=None) -> Manifest:
    """The exposure-series manifest of a folder of images (nothing decoded yet).

    ``times``: a times file path, or a sequence of times in the images' sorted name order;
    without, each image's EXIF ExposureTime (and FNumber, when every image has one); where the
    EXIF ISO differs between images, the times are scaled by ISO to the lowest one (seconds
    at that ISO)."""
    source = Path(source)
    if not source.is_dir():
        raise InputError(f"exposure series not found: {source} (give a manifest or a folder)")
    # every image listed must lie in the folder (a symlink leading out of it is refused)
    files = series_files(source)
    for p in files:
        resolve_inside(source, p.name, f"exposure series {source}: image")
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder {source}")
    f_numbers = [None] * len(files)
    if times is None:
        found = [exif_exposure(p) for p in files]
        missing = [p.name for p, (t, _) in zip(files, found, strict=True) if t is None]
        if missing:
            raise InputError(f"exposure times missing: no times file given and no EXIF "
                             f"ExposureTime in {', '.join(missing[:3])}"
                             + (" ..." if len(missing) > 3 else ""))
        bad = [f"{p.name} ({t:g})" for p, (t, _) in zip(files, found, strict=True)
               if not (math.isfinite(t) and t > 0)]
        if bad:
            raise InputError(f"EXIF ExposureTime is not a positive time in {', '.join(bad[:3])}"
                             "; give a times file (--times)")
        times = [t for t, _ in found]
        # Auto-ISO brackets (phones) change the gain as well as the time: the exposure that
        # reaches the codes is t * ISO / N^2, so times are scaled to the lowest ISO.
        isos = [exif_iso(p) for p in files]
        if all(i is not None and math.isfinite(i) and i > 0 for i in isos) \
                and max(isos) > min(isos):
            times = [t * i / min(isos) for t, i in zip(times, isos, strict=True)]
        fns = [f for _, f in found]
        if all(f is not None and math.isfinite(f) and f > 0 for f in fns):
            f_numbers = fns
    elif isinstance(times, (str, os.PathLike)):
        times_path = Path(times)
        rows = read_times_file(times_path)
        if all(row.name is not None for row in rows) and rows:
            by_name = {row.name: row for row in rows}
            if len(by_name) != len(rows):
                twice = sorted(n for n, k in Counter(row.name for row in rows).items() if k > 1)
                raise InputError(f"times file {times_path} names {', '.join(twice[:3])} "
                                 "more than once")
            by_name = _match_converted(by_name, files)
            missing = sorted(set(by_name) - {p.name for p in files})
            if missing:
                raise InputError(f"times file names images not in {source}: {missing[:3]}")
            # An image without a time is refused, not dropped: a forgotten line would
            # otherwise calibrate on a silently smaller series.
            untimed = [p.name for p in files if p.name not in by_name]
            if untimed:
                raise InputError(f"times file {times_path} gives no time for "
                                 f"{', '.join(untimed[:3])}" + (" ..." if len(untimed) > 3
                                                                 else "")
                                 + f" in {source}; name every image of the folder")
            rows = [by_name[p.name] for p in files]
        elif any(row.name is not None for row in rows):
            raise InputError(f"times file {times_path}: name every image or none")
        elif len(rows) != len(files):
            raise InputError(f"times file {times_path} lists {len(rows)} times for "
                             f"{len(files)} images in {source}")
        times = [row.time for row in rows]
        if any(row.f_number is not None for row in rows):
            f_numbers = [row.f_number for row in rows]
    times = list(times)
    if len(times) != len(files):
        raise InputError(f"{len(times)} exposure times for {len(files)} images in {source}")
    if not all(isinstance(t, (int, float, np.number)) and not isinstance(t, bool)
               and math.isfinite(t) and t > 0 for t in times):
        raise InputError(f"exposure times must be positive numbers, got {times[:4]}")
    return Manifest("exposure-series", source, images=tuple(
        Exposure(p, t, f) for p, t, f in zip(files, times, f_numbers, strict=True)))
