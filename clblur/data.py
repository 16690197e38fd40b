"""Where the shared measured data lives (never copied into the repository)."""

from __future__ import annotations

import os
from pathlib import Path


def data_dir(required: bool = False) -> Path | None:
    """``$CLBLUR_DATA``, else ``../shared/data`` beside the source tree or working directory.

    Returns None (or raises ``ValueError`` when ``required``) if no such folder exists.
    """
    candidates = []
    if os.environ.get("CLBLUR_DATA"):
        candidates.append(Path(os.environ["CLBLUR_DATA"]))
    repo = Path(__file__).resolve().parent.parent
    candidates += [repo.parent / "shared" / "data", Path.cwd().parent / "shared" / "data"]
    for c in candidates:
        if c.is_dir():
            return c
    if required:
        raise ValueError("measured data not found: set CLBLUR_DATA to the shared data folder "
                         "(see ../shared/data/README.md)")
    return None
