"""Clamp-to-edge bilinear corners: the one place both bilinear samplers take them from.

``clblur.reference.bilinear_at`` (the numpy backend's image sampler) and
``clblur.study.histograms`` (source-code histograms of the study) both read the four pixels
around a real position and the fractions between them from ``bilinear_corners``.

Conventions
-----------
Pixel ``(row, col)`` has its centre at ``x = col``, ``y = row`` (x right, y down, pixels), as
in ``clblur.motion``.  Positions outside the image clamp to its edge pixels.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bilinear_corners"]


def bilinear_corners(x: np.ndarray, y: np.ndarray, height: int, width: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                np.ndarray]:
    """The four bilinear corners of positions ``x``, ``y`` in a ``height`` x ``width`` image.

    Parameters
    ----------
    x, y : numpy.ndarray
        Positions (float64, any equal shapes), pixels.
    height, width : int
        Image size the positions clamp to.

    Returns
    -------
    y0, y1, x0, x1 : numpy.ndarray
        Integer (``intp``) rows and columns of the corners, inside the image.
    fx, fy : numpy.ndarray
        Fractions from ``x0`` to ``x1`` and from ``y0`` to ``y1``, in [0, 1]; the weight of
        corner ``(y1, x1)`` is ``fx * fy``.

    Conventions
    -----------
    Clamp to edge: ``x`` is clipped to ``[0, width - 1]`` and ``y`` to ``[0, height - 1]``
    first, so on the last row or column ``x1 == x0`` (or ``y1 == y0``) with fraction 0.
    """
    x = np.clip(x, 0.0, width - 1.0)
    y = np.clip(y, 0.0, height - 1.0)
    x0 = np.floor(x).astype(np.intp)
    y0 = np.floor(y).astype(np.intp)
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, height - 1)
    return y0, y1, x0, x1, x - x0, y - y0
