"""Host side of linearisation: per-channel tables for integer images, float64 maths for float
images (so the saturation policy and ``E_fs`` are exactly the reference's).
"""

from __future__ import annotations

import numpy as np

from clblur.pixels import linearisation_table, linearise, normalise

__all__ = ["linearisation_tables", "linearise_float_image"]


def linearisation_tables(responses, dtype: np.dtype, saturation: float) -> np.ndarray:
    """float64 (channels, Imax + 1): the exposure of every code, per channel."""
    return np.stack([linearisation_table(r, dtype, saturation) for r in responses])


def linearise_float_image(image: np.ndarray, responses, saturation: float) -> np.ndarray:
    """Float H x W x C image -> float32 linear exposures (float64 maths, as the reference)."""
    values = normalise(image)
    out = np.empty(image.shape, dtype=np.float32)
    for c, r in enumerate(responses):
        out[..., c] = linearise(values[..., c], r, image.dtype, saturation)
    return out


