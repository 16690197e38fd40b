"""Atomic writes: every output goes to a temporary file beside it, renamed into place when
complete, so a reader sees either the old file, nothing, or the finished result."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from clblur.errors import InputError

__all__ = ["atomic_write", "atomic_write_text", "tmp_beside"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def tmp_beside(path: Path) -> Path:
    """A new empty temporary file next to ``path`` (same folder, so the rename is atomic),
    with the permissions a plainly created file would get (mkstemp makes it 0600)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part" + path.suffix,
                               dir=path.parent)
    os.fchmod(fd, 0o666 & ~_umask())
    os.close(fd)
    return Path(tmp)


def atomic_write(path: str | os.PathLike, writer: Callable[[Path], None]) -> None:
    """Call ``writer(tmp)`` on a temporary file beside ``path``, then rename it into place."""
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"output folder does not exist: {path.parent}")
    if path.is_dir():
        raise InputError(f"output {path} is an existing folder; name a file")
    tmp = tmp_beside(path)
    try:
        writer(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    atomic_write(path, lambda tmp: tmp.write_text(text))
