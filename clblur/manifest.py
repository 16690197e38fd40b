"""Measurement manifests shared by ``clblur calibrate`` and ``clblur study``.

Three kinds, paths relative to the manifest file::

    {"kind": "exposure-series",
     "images": [{"path": "e00.png", "exposure": 0.5, "f_number": 5.0}, ...]}
    {"kind": "blur-pair",
     "pairs": [{"static": "s.png", "blurred": "b.png",
                "motion": [dx, dy] | "flow": "f.npy" | "psf": "k.png",
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

KINDS = ("exposure-series", "blur-pair", "frame-stack")


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


def _positive(value, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{what} must be positive and finite, got {value!r}")
    return v


def _require(entry: dict, key: str, where: str):
    if not isinstance(entry, dict) or key not in entry:
        raise ValueError(f"{where} lacks {key!r}")
    return entry[key]


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Parse and validate a manifest; raises ``ValueError`` naming the problem."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"manifest not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"cannot read manifest {path}: {e}") from None
    if not isinstance(doc, dict) or doc.get("kind") not in KINDS:
        raise ValueError(f"manifest {path}: 'kind' must be one of {', '.join(KINDS)}")
    base = path.parent
    kind = doc["kind"]
    if kind == "exposure-series":
        entries = _require(doc, "images", f"manifest {path}")
        images = []
        for i, e in enumerate(entries):
            where = f"manifest {path}, images[{i}]"
            fn = e.get("f_number") if isinstance(e, dict) else None
            images.append(Exposure(base / _require(e, "path", where),
                                   _positive(_require(e, "exposure", where), f"{where} exposure"),
                                   None if fn is None else _positive(fn, f"{where} f_number")))
        return Manifest(kind, path, images=tuple(images))
    if kind == "blur-pair":
        pairs = []
        for i, p in enumerate(_require(doc, "pairs", f"manifest {path}")):
            where = f"manifest {path}, pairs[{i}]"
            forms = [k for k in ("motion", "flow", "psf") if isinstance(p, dict) and k in p]
            if len(forms) != 1:
                raise ValueError(f"{where} needs exactly one of motion, flow, psf")
            motion = None
            if "motion" in p:
                m = p["motion"]
                if not (isinstance(m, list) and len(m) == 2):
                    raise ValueError(f"{where} motion must be [dx, dy]")
                motion = (float(m[0]), float(m[1]))
            pairs.append(BlurPair(
                static=base / _require(p, "static", where),
                blurred=base / _require(p, "blurred", where),
                motion=motion,
                flow=base / p["flow"] if "flow" in p else None,
                psf=base / p["psf"] if "psf" in p else None,
                anchor=p.get("anchor", "center"),
                exposure_ratio=_positive(p.get("exposure_ratio", 1.0),
                                         f"{where} exposure_ratio")))
        return Manifest(kind, path, pairs=tuple(pairs))
    stacks = []
    for i, s in enumerate(_require(doc, "stacks", f"manifest {path}")):
        where = f"manifest {path}, stacks[{i}]"
        frames = _require(s, "frames", where)
        if not isinstance(frames, list) or len(frames) < 2:
            raise ValueError(f"{where} needs at least 2 frames")
        stacks.append(FrameStack(tuple(base / f for f in frames),
                                 base / _require(s, "long", where)))
    return Manifest(kind, path, stacks=tuple(stacks))


def write_manifest(path: str | os.PathLike, doc: dict) -> None:
    """Write a manifest document atomically (paths in ``doc`` relative to ``path``)."""
    from clblur.io import atomic_write_text

    if doc.get("kind") not in KINDS:
        raise ValueError(f"manifest kind must be one of {', '.join(KINDS)}")
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
