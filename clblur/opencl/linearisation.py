"""Host side of linearisation: per-channel tables for integer images; for float32 images the
arguments of the device's inverse responses (``linearise_float`` in integrate.cl); float64
maths for float64 images.

The saturation policy and ``E_fs`` always come from ``clblur.pixels`` in float64.  float64
images stay on the host: rounding their values to float32 first would move an exposure near
full scale under ``exp`` by up to a percent (the inverse's slope there is ``1 / (k (1 - v))``).
"""

from __future__ import annotations

import numpy as np

from clblur.opencl.response_pack import response_params
from clblur.pixels import full_scale_exposure, linearisation_table, linearise, normalise, top_value
from clblur.responses import Gamma

__all__ = ["exposure_bound", "float_inverse_args", "linearisation_tables",
           "linearise_float_image"]


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


def _below(x: float) -> np.float32:
    """The largest float32 not above ``x``: a clamp to it never lets a value past ``x``."""
    f = np.float32(x)
    return np.nextafter(f, np.float32(-np.inf)) if float(f) > x else f


def float_inverse_args(responses, saturation: float) -> tuple[np.ndarray, np.ndarray,
                                                              np.ndarray]:
    """(params, tables, limits) of ``linearise_float`` for a float32 image's channels.

    ``params`` and ``tables`` pack the responses as for the forward (``response_params``);
    ``limits`` is float32 (channels, 8): the top value linearised as is (rounded down), its
    exposure and that of a full-scale value (``saturation * E_fs``), both in float64, the
    gamma exponent, and 1 where the response is bounded (0: ``linear``, whose float values
    pass through); three unused.
    """
    params, tables = response_params(responses)
    limits = np.zeros((len(responses), 8), np.float32)
    dtype = np.dtype(np.float32)
    for c, r in enumerate(responses):
        if not r.bounded:
            continue
        top = top_value(r, dtype)
        limits[c, :5] = (_below(top), float(r.inverse(np.array(top))),
                         saturation * full_scale_exposure(r, dtype),
                         r.gamma if isinstance(r, Gamma) else 0.0, 1.0)
    return params, tables, limits


def exposure_bound(image: np.ndarray, responses, saturation: float) -> float:
    """The largest ``|exposure|`` of a float image's linearisation (float64), from each
    channel's extreme values: linearisation is monotone in the value."""
    flat = image.reshape(-1, image.shape[-1])
    ends = np.stack([flat.min(axis=0), flat.max(axis=0)]).astype(np.float64)
    return max(float(np.max(np.abs(linearise(ends[:, c], r, image.dtype, saturation))))
               for c, r in enumerate(responses))
