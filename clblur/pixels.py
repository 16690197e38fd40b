"""Pixel values <-> linear exposure: the two ends of the blur pipeline.

Conventions
-----------
* dtypes: uint8 (Imax 255), uint16 (Imax 65535), float32 / float64 (Imax 1.0).  The output
  has the input's dtype and shape.
* Normalised value ``v = code / Imax``.
* Linearise (``E = I^-1(v)``), with a saturation policy for full-scale pixels:
  - integer images: a pixel at code Imax is clipped, so its true exposure is only known to be
    at least ``E_fs``; it gets ``saturation * E_fs``.  ``saturation >= 1``, default 1.
  - float images: ``v >= 1`` is full scale and treated the same way, except under the
    unbounded ``linear`` response, where values pass through untouched.
  - ``E_fs = I^-1(1)`` when that is finite; for responses that reach full scale only at
    infinite exposure (the paper's Eq. 3) it is ``I^-1(1 - q/4)`` with ``q`` one code step
    (1/255 for uint8, 1/65535 for uint16 and floats): a finite exposure whose value lies inside
    the top code bin with a margin for float32 arithmetic, so a constant saturated region stays
    at full scale.
* Clipping below full scale (``clip_level``): a camera whose highlights stop under full
  scale; measurement code (calibration, the study) treats that level as the clip point.
* Quantise: integer outputs are ``rint(clip(v, 0, 1) * Imax)``, round half to even (the IEEE
  default, identical in numpy and OpenCL).  Float outputs are not rounded; bounded responses
  already land in [0, 1].
"""

from __future__ import annotations

import math

import numpy as np

from clblur.responses import Response

__all__ = ["SUPPORTED_DTYPES", "clip_level", "code_step", "full_scale_exposure", "imax",
           "linearisation_table", "linearise", "normalise", "quantise", "top_value",
           "validate_saturation"]

SUPPORTED_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)


def imax(dtype: np.dtype) -> float:
    """Full-scale code value of a dtype."""
    dtype = np.dtype(dtype)
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    if dtype in (np.float32, np.float64):
        return 1.0
    raise TypeError(f"unsupported image dtype {dtype}; use uint8, uint16, float32 or float64")


def code_step(dtype: np.dtype) -> float:
    """One code value in normalised units; floats are treated as 16-bit precise."""
    return 1.0 / 255.0 if np.dtype(dtype) == np.uint8 else 1.0 / 65535.0


def full_scale_exposure(resp: Response, dtype: np.dtype) -> float:
    """``E_fs``: the exposure assigned to a full-scale pixel before the saturation factor."""
    top = float(resp.inverse(np.array(1.0)))
    if math.isfinite(top):
        return top
    return float(resp.inverse(np.array(1.0 - code_step(dtype) / 4.0)))


def top_value(resp: Response, dtype: np.dtype) -> float:
    """Largest normalised value linearised as is; above it the saturation policy applies."""
    return 1.0 if math.isfinite(float(resp.inverse(np.array(1.0)))) else \
        1.0 - code_step(dtype) / 4.0


def linearise(values: np.ndarray, resp: Response, dtype: np.dtype,
              saturation: float) -> np.ndarray:
    """Normalised values of one channel (float64) -> linear exposure (float64)."""
    if not resp.bounded:
        if np.dtype(dtype).kind == "f":
            return resp.inverse(values)
        return np.where(values >= 1.0, saturation * resp.inverse(np.array(1.0)),
                        resp.inverse(values))
    e_fs = full_scale_exposure(resp, dtype)
    v = np.clip(values, 0.0, top_value(resp, dtype))
    return np.where(values >= 1.0, saturation * e_fs, resp.inverse(v))


def linearisation_table(resp: Response, dtype: np.dtype, saturation: float) -> np.ndarray:
    """Exposure for every code value of an integer dtype (float64, length Imax + 1)."""
    n = int(imax(dtype))
    return linearise(np.arange(n + 1, dtype=np.float64) / n, resp, dtype, saturation)


def normalise(image: np.ndarray) -> np.ndarray:
    """Image -> float64 normalised values (same shape)."""
    return image.astype(np.float64) / imax(image.dtype)


def quantise(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Normalised float64 values -> output dtype (rounding rule in the module docstring)."""
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        return values.astype(dtype)
    full = imax(dtype)
    return np.rint(np.clip(values, 0.0, 1.0) * full).astype(dtype)


def validate_saturation(saturation: float) -> float:
    try:
        s = float(saturation)
    except (TypeError, ValueError):
        raise TypeError(f"saturation must be a number, got {saturation!r}") from None
    if not math.isfinite(s) or s < 1.0:
        raise ValueError(f"saturation must be a finite number >= 1 (a clipped pixel is at "
                         f"least as bright as full scale), got {saturation}")
    return s


# a pile-up at the highest code: at least this share of the pixels (and 50), and this many
# times the mean count of the 8 codes below it (a scene's own highlights taper off)
_PILE_SHARE = 5e-4
_PILE_RATIO = 4.0
# clipped pixels hold many radiances: one exposure shorter they spread over at least this
# fraction of full scale (10th to 90th percentile), or sit at the same top code again
_CLIP_SPREAD = 8.0 / 255.0


def clip_level(brightest: np.ndarray, darker: np.ndarray | None = None) -> float:
    """The fraction of full scale at which an integer image clips, 1.0 when it clips at full
    scale or shows no clipping (float images: 1.0).

    A clipped channel piles its pixels up at one highest code.  A channel whose highest code
    is below full scale and holds such a pile-up (``_PILE_SHARE`` of the pixels and
    ``_PILE_RATIO`` times the codes just below) clips there, if ``darker`` (the same scene
    at a shorter exposure, when there is one) agrees: a clipped code stands for every
    radiance above the clip point, so in the darker image those pixels spread over at least
    ``_CLIP_SPREAD`` or are clipped again, where a flat patch that is merely the brightest
    thing in view (a test chart) stays one value.  The lowest such level over the channels
    is returned (one valid range serves every channel)."""
    if brightest.dtype.kind != "u":
        return 1.0
    if brightest.ndim == 2:
        brightest = brightest[..., None]
        darker = None if darker is None else darker.reshape(brightest.shape)
    full = imax(brightest.dtype)
    level = 1.0
    for c in range(brightest.shape[2]):
        plane = brightest[..., c]
        counts = np.bincount(plane.ravel())
        top = counts.size - 1
        if top >= full or top < 16:
            continue
        piled = (counts[top] >= max(50, _PILE_SHARE * plane.size)
                 and counts[top] >= _PILE_RATIO * counts[top - 8:top].mean())
        if piled and darker is not None:
            there = darker[..., c][plane == top].astype(np.float64)
            lo, hi = np.percentile(there, [10, 90])
            piled = hi - lo >= _CLIP_SPREAD * full or np.mean(there == top) >= 0.5
        if piled:
            level = min(level, top / full)
    return level
