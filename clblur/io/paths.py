"""Where paths may point: inputs named by manifests stay inside their folder, outputs stay
inside the output folder, and an output never replaces an input; and where the shared
measured data lives (``data_dir``: read from there, never copied into the repository).

Conventions
-----------
* A path read from a manifest, CSV cell or folder listing is resolved (symlinks followed,
  ``..`` removed) and must land inside one of its allowed roots; otherwise ``InputError``.
  Absolute paths are accepted only when they too resolve inside a root.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from clblur.errors import InputError

__all__ = ["check_output", "data_dir", "refuse_folder_of_inputs", "refuse_overwrite",
           "require_file", "resolve_inside"]

PathLike = str | os.PathLike


def resolve_inside(roots: PathLike | Sequence[PathLike], path: PathLike, what: str) -> Path:
    """Resolve ``path`` (relative to the first root) and require it inside one of ``roots``.

    Parameters
    ----------
    roots : path or sequence of paths
        Allowed folders; a relative ``path`` is taken relative to the first.
    path : path
        The path as written in the manifest, CSV cell or listing.
    what : str
        What the path is for, used in the error message (e.g. ``"manifest row 3 flow"``).

    Returns
    -------
    pathlib.Path
        The resolved absolute path (symlinks followed).

    Raises
    ------
    InputError
        When the resolved path lies outside every root, or the text is not a usable path.
    """
    if isinstance(roots, (str, os.PathLike)):
        roots = [roots]
    resolved_roots = [Path(r).resolve() for r in roots]
    text = os.fspath(path)
    if not isinstance(text, str) or not text.strip() or "\x00" in text:
        raise InputError(f"{what}: {text!r} is not a usable path")
    try:
        full = (resolved_roots[0] / text).resolve()
    except (OSError, RuntimeError) as e:  # symlink loops, names too long
        raise InputError(f"{what}: cannot resolve {text!r}: {e}") from None
    if not any(full == r or full.is_relative_to(r) for r in resolved_roots):
        where = " or ".join(dict.fromkeys(str(r) for r in resolved_roots))  # each once
        raise InputError(f"{what} {text!r} resolves to {full}, outside {where}; paths must "
                         "stay inside that folder")
    return full


def require_file(path: PathLike, what: str) -> Path:
    """``path`` as a ``Path``; ``InputError`` naming ``what`` if it is missing or a folder."""
    path = Path(path)
    try:
        folder, file = path.is_dir(), path.is_file()
    except OSError as e:  # a name too long for the file system, a permission denied
        raise InputError(f"{what} {str(path)[:80]}: {e.strerror or e}") from None
    if folder:
        raise InputError(f"{what} {path} is a folder, not a file")
    if not file:
        raise InputError(f"{what} file not found: {path}")
    return path


def refuse_overwrite(out: PathLike, *inputs: PathLike | None) -> None:
    """Raise if ``out`` names one of the inputs (the same file, however spelled)."""
    o = Path(out)
    for i in inputs:
        if i is None or not isinstance(i, (str, os.PathLike)):
            continue
        ip = Path(i)
        if o.resolve() == ip.resolve() or (o.exists() and ip.exists() and o.samefile(ip)):
            raise InputError(f"output {out} is the input {i}; refusing to overwrite an input")


def refuse_folder_of_inputs(folder: PathLike, inputs: Sequence[PathLike], what: str) -> None:
    """Raise if the output ``folder`` directly holds one of ``inputs``: what is written
    there under fixed names could replace it, and new files would join a folder of inputs
    (a series read from a folder would take them in on the next run)."""
    f = Path(folder).resolve()
    for i in inputs:
        if Path(i).resolve().parent == f:
            raise InputError(f"{what} {folder} holds the input {i}; write it to another "
                             "folder")


def check_output(out: PathLike, *inputs: PathLike | None, suffixes: Sequence[str] = ()) -> Path:
    """Validate an output file path before any work: its folder exists, it is not a folder,
    not one of ``inputs``, and (when ``suffixes`` is given) has one of those suffixes."""
    o = Path(out)
    if o.is_dir():
        raise InputError(f"output {out} is an existing folder; name a file")
    if not o.parent.is_dir():
        raise InputError(f"output folder does not exist: {o.parent}")
    if suffixes and o.suffix.lower() not in suffixes:
        raise InputError(f"output {out}: unknown extension {o.suffix or '(none)'!r}; use one "
                         f"of {', '.join(suffixes)}")
    refuse_overwrite(o, *inputs)
    return o


def gopro_frames(root: Path | None = None) -> list[Path]:
    """The GoPro 240 fps frames of the measured data (``gopro240/frames/*.png`` under
    ``root``, default :func:`data_dir`), in frame order; empty when there are none."""
    root = data_dir() if root is None else Path(root)
    return [] if root is None else sorted((root / "gopro240" / "frames").glob("*.png"))


def data_dir(required: bool = False) -> Path | None:
    """``$CLBLUR_DATA``, else ``../shared/data`` beside the source tree or working directory.

    Returns None (or raises ``ValueError`` when ``required``) if no such folder exists.
    """
    candidates = []
    if os.environ.get("CLBLUR_DATA"):
        candidates.append(Path(os.environ["CLBLUR_DATA"]))
    repo = Path(__file__).resolve().parents[2]  # the checkout: clblur/io/paths.py
    candidates += [repo.parent / "shared" / "data", Path.cwd().parent / "shared" / "data"]
    for c in candidates:
        if c.is_dir():
            return c
    if required:
        raise InputError("measured data not found: set CLBLUR_DATA to the shared data folder "
                         "(see ../shared/data/README.md)")
    return None
