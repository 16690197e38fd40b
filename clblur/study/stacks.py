"""Frame stacks (short frames, one long exposure) -> study groups: the temporal Eq. 8.

The long exposure of pixel ``p`` is predicted from the frames at the same pixel, frame ``t``
of ``F`` at shutter time ``s = t / (F - 1)``; there is no spatial motion to trace.
"""

from __future__ import annotations

import numpy as np

from clblur.errors import InputError
from clblur.study.histograms import Taps, as_hwc, build_group, sample_grid, shifted
from clblur.study.model import Group
from clblur.study.variants import SHIFTS

__all__ = ["stack_group"]


def stack_group(frames: list[np.ndarray], long: np.ndarray, *, max_pixels: int = 60000,
                name: str = "stack") -> Group:
    if len(frames) < 2:
        raise InputError(f"a frame stack needs at least 2 frames, got {len(frames)}")
    src = [as_hwc(f, f"frame {i}") for i, f in enumerate(frames)]
    tgt = as_hwc(long, "long exposure")
    for i, f in enumerate(src):
        if f.shape != tgt.shape:
            raise InputError(f"frame {i} has shape {f.shape}, the long exposure {tgt.shape}")
    rows, cols = sample_grid(tgt.shape[:2], max_pixels)
    nf = len(src)

    def taps(yy, xx):
        for t in range(nf):
            yield Taps(t, 0.0, 0.0, 1.0 / nf, t / (nf - 1))

    return build_group(name, src, tgt, rows, cols, taps, 1.0, vignetting=False, timed=True,
                       variants={"misregistration": {sh: shifted(taps, *sh) for sh in SHIFTS}})
