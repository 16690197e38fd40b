"""Measurement manifests shared by ``clblur calibrate`` and ``clblur study``.

Three kinds, paths relative to the manifest file.  Every path must resolve (symlinks followed)
inside the manifest's folder or the measured-data folder (``clblur.io.data_dir``:
``$CLBLUR_DATA``), so manifests written elsewhere may name the shared data; any other path
(``..``, absolute or through a symlink) is refused.  ``"psf": "estimate"`` asks for the kernel
to be measured from the pair itself (``clblur.psf_estimation``; ``"psf_size": N``, odd, sets
the window searched)::

    {"kind": "exposure-series",
     "images": [{"path": "e00.png", "exposure": 0.5, "f_number": 5.0}, ...]}
    {"kind": "blur-pair",
     "pairs": [{"static": "s.png", "blurred": "b.png",
                "motion": [dx, dy] | "flow": "f.npy" | "psf": "k.png" | "psf": "estimate",
                "anchor": "center", "exposure_ratio": 1.0}, ...]}
    {"kind": "frame-stack",
     "stacks": [{"frames": ["f0.png", "f1.png", ...], "long": "long.png"}, ...]}
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from clblur.errors import InputError
from clblur.io.paths import resolve_inside
from clblur.motion import ANCHORS

__all__ = ["ESTIMATE", "KINDS", "BlurPair", "Exposure", "FrameStack", "Manifest", "load_manifest",
           "manifest_inputs", "write_manifest"]

KINDS = ("exposure-series", "blur-pair", "frame-stack")
ESTIMATE = "estimate"  # a blur pair's "psf": measure the kernel from the pair


@dataclass(frozen=True)
class Exposure:
    path: Path
    exposure: float
    f_number: float | None = None


@dataclass(frozen=True)
class BlurPair:
    static: Path
    blurred: Path
    motion: tuple[float, float] | None = None
    flow: Path | None = None
    psf: Path | None = None
    anchor: str = "center"
    exposure_ratio: float = 1.0
    estimate_psf: bool = False  # the kernel is measured from the pair (clblur.psf_estimation)
    psf_size: int | None = None  # the window it is searched in (None: grown)


@dataclass(frozen=True)
class FrameStack:
    frames: tuple[Path, ...]
    long: Path


@dataclass(frozen=True)
class Manifest:
    kind: str
    path: Path
    images: tuple[Exposure, ...] = field(default_factory=tuple)
    pairs: tuple[BlurPair, ...] = field(default_factory=tuple)
    stacks: tuple[FrameStack, ...] = field(default_factory=tuple)


def _number(value, what: str) -> float:
    """A JSON number as a float: not a boolean (JSON's true is no exposure), not a string,
    and finite (an integer too large for a float is refused, not a traceback)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{what} must be a number, got {str(value)[:40]!r}")
    try:
        v = float(value)
    except OverflowError:
        v = math.inf
    if not math.isfinite(v):
        raise InputError(f"{what} must be finite, got {str(value)[:40]}")
    return v


def _positive(value, what: str) -> float:
    v = _number(value, what)
    if v <= 0:
        raise InputError(f"{what} must be positive and finite, got {value!r}")
    return v


def _require(entry: dict, key: str, where: str):
    if not isinstance(entry, dict) or key not in entry:
        raise InputError(f"{where} lacks {key!r}")
    return entry[key]


def _entries(doc: dict, key: str, where: str) -> list:
    entries = _require(doc, key, where)
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{where}: {key!r} must be a non-empty list")
    return entries


def _path(roots: list[Path], value, where: str) -> Path:
    if not isinstance(value, str):
        raise InputError(f"{where} must be a path string, got {value!r}")
    return resolve_inside(roots, value, where)


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Parse and validate a manifest; raises ``InputError`` naming the problem."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"manifest not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise InputError(f"cannot read manifest {path}: {e}") from None
    if not isinstance(doc, dict) or doc.get("kind") not in KINDS:
        raise InputError(f"manifest {path}: 'kind' must be one of {', '.join(KINDS)}")
    from clblur.io import data_dir

    shared = data_dir()
    base = [path.parent] + ([shared] if shared is not None else [])  # the allowed roots
    kind = doc["kind"]
    if kind == "exposure-series":
        entries = _entries(doc, "images", f"manifest {path}")
        images = []
        for i, e in enumerate(entries):
            where = f"manifest {path}, images[{i}]"
            fn = e.get("f_number") if isinstance(e, dict) else None
            images.append(Exposure(_path(base, _require(e, "path", where), f"{where} path"),
                                   _positive(_require(e, "exposure", where), f"{where} exposure"),
                                   None if fn is None else _positive(fn, f"{where} f_number")))
        _once([im.path for im in images], f"manifest {path}")
        return Manifest(kind, path, images=tuple(images))
    if kind == "blur-pair":
        pairs = []
        for i, p in enumerate(_entries(doc, "pairs", f"manifest {path}")):
            where = f"manifest {path}, pairs[{i}]"
            forms = [k for k in ("motion", "flow", "psf") if isinstance(p, dict) and k in p]
            if len(forms) != 1:
                raise InputError(f"{where} needs exactly one of motion, flow, psf")
            motion = None
            if "motion" in p:
                m = p["motion"]
                if not (isinstance(m, list) and len(m) == 2):
                    raise InputError(f"{where} motion must be [dx, dy], finite numbers")
                motion = (_number(m[0], f"{where} motion dx"),
                          _number(m[1], f"{where} motion dy"))
            anchor = p.get("anchor", "center") if isinstance(p, dict) else "center"
            if not isinstance(anchor, str) or anchor not in ANCHORS:
                raise InputError(f"{where} anchor must be one of {', '.join(ANCHORS)}, got "
                                 f"{str(anchor)[:40]!r}")
            estimate = p.get("psf") == ESTIMATE
            size = p.get("psf_size")
            if size is not None and (not estimate or isinstance(size, bool)
                                     or not isinstance(size, int) or size < 3 or size % 2 == 0):
                raise InputError(f"{where} psf_size must be an odd integer >= 3, with "
                                 f"\"psf\": \"{ESTIMATE}\"; got {str(size)[:40]!r}")
            pairs.append(BlurPair(
                static=_path(base, _require(p, "static", where), f"{where} static"),
                blurred=_path(base, _require(p, "blurred", where), f"{where} blurred"),
                motion=motion,
                flow=_path(base, p["flow"], f"{where} flow") if "flow" in p else None,
                psf=_path(base, p["psf"], f"{where} psf") if "psf" in p and not estimate
                else None,
                anchor=anchor,
                exposure_ratio=_positive(p.get("exposure_ratio", 1.0),
                                         f"{where} exposure_ratio"),
                estimate_psf=estimate, psf_size=size))
        return Manifest(kind, path, pairs=tuple(pairs))
    stacks = []
    for i, s in enumerate(_entries(doc, "stacks", f"manifest {path}")):
        where = f"manifest {path}, stacks[{i}]"
        frames = _require(s, "frames", where)
        if not isinstance(frames, list) or len(frames) < 2:
            raise InputError(f"{where} needs at least 2 frames")
        stacks.append(FrameStack(
            tuple(_path(base, f, f"{where} frames[{k}]") for k, f in enumerate(frames)),
            _path(base, _require(s, "long", where), f"{where} long")))
    return Manifest(kind, path, stacks=tuple(stacks))


def _once(paths: list[Path], where: str) -> None:
    """Refuse a file listed twice (two exposures of one image cannot both be right)."""
    seen: set[Path] = set()
    for q in paths:
        if q in seen:
            raise InputError(f"{where} lists {q} more than once")
        seen.add(q)


def manifest_inputs(m: Manifest) -> list[Path]:
    """Every file a manifest names (with the manifest itself): what no output may replace."""
    out = [m.path, *(e.path for e in m.images)]
    for p in m.pairs:
        out += [q for q in (p.static, p.blurred, p.flow, p.psf) if q is not None]
    for s in m.stacks:
        out += [*s.frames, s.long]
    return out


def write_manifest(path: str | os.PathLike, doc: dict) -> None:
    """Write a manifest document atomically (paths in ``doc`` relative to ``path``)."""
    from clblur.io import atomic_write_text

    if doc.get("kind") not in KINDS:
        raise InputError(f"manifest kind must be one of {', '.join(KINDS)}")
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
