"""A results file that keeps its notes: a rerun rewrites the measured tables at its top and
keeps the notes written by hand below its marker line (readings, earlier measurements)."""

from __future__ import annotations

from pathlib import Path

MARKER = "<!-- the bench script rewrites what is above this line and keeps what follows -->"


def write_results(path: Path, generated: str) -> None:
    """Write ``generated`` at the top of ``path`` (atomically), then the marker and whatever
    followed the marker in the file before."""
    from clblur.io.atomic import atomic_write_text

    kept = path.read_text().partition(MARKER)[2] if path.exists() else ""
    atomic_write_text(path, generated.rstrip("\n") + "\n\n" + MARKER + (kept or "\n"))
