"""Grossberg & Nayar's (2004) empirical model of response (EMoR): basis and family.

The basis (mean curve and principal components of measured curves) is read from
``emor.txt`` in ``$CLBLUR_DATA/crf`` unless a folder is given.

Conventions
-----------
Exposure on the basis grid, full scale at exposure 1; values normalised to [0, 1].
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clblur.errors import InputError
from clblur.responses.base import Parametric, _strictly_increasing

__all__ = ["Emor", "EmorBasis"]


@dataclass(frozen=True)
class EmorBasis:
    """Grossberg & Nayar's EMoR: ``f(E) = f0(E) + sum_m c_m h_m(E)`` sampled on grid E."""

    grid: np.ndarray
    mean: np.ndarray
    components: np.ndarray  # (25, len(grid))

    @classmethod
    def load(cls, folder: str | os.PathLike | None = None) -> EmorBasis:
        """Read ``emor.txt`` from ``folder`` (default: the shared data's ``crf`` folder)."""
        from clblur.io import data_dir

        if folder is None:
            root = data_dir()
            if root is None:
                raise InputError("EMoR basis not found: pass emor_dir= (--emor-dir) or set "
                                 "CLBLUR_DATA to a folder holding crf/emor.txt")
            folder = root / "crf"
        path = Path(folder) / "emor.txt"
        cached = _EMOR_CACHE.get(str(path))
        if cached is not None:
            return cached
        if not path.is_file():
            raise InputError(f"EMoR basis file not found: {path}")
        blocks, current = {}, None
        for line in path.read_text().splitlines():
            if "=" in line:
                current = line.split("=")[0].strip()
                blocks[current] = []
            elif current is not None and line.strip():
                blocks[current].extend(float(t) for t in line.split())
        try:
            grid, mean = np.array(blocks["E"]), np.array(blocks["f0"])
            comps = np.array([blocks[f"h({m})"] for m in range(1, 26)])
        except (KeyError, ValueError) as e:
            raise InputError(f"{path}: missing or ragged block ({e})") from None
        if grid.size != mean.size or comps.shape[1] != grid.size:
            raise InputError(f"{path}: blocks of different lengths")
        _EMOR_CACHE[str(path)] = basis = cls(grid, mean, comps)
        return basis


_EMOR_CACHE: dict[str, EmorBasis] = {}


@dataclass(frozen=True, eq=False, repr=False)
class Emor(Parametric):
    """Grossberg & Nayar (2004) EMoR: mean curve plus principal components of real curves.

    Forward ``v = f0(x) + sum_m c_m h_m(x)`` on the basis grid (full scale at exposure 1),
    made strictly increasing and normalised to ``f(0) = 0, f(1) = 1``.  ``emor_dir``: folder
    of ``emor.txt`` (default ``$CLBLUR_DATA/crf``).
    """

    coefficients: tuple[float, ...] = ()
    emor_dir: str | None = None
    kind = "emor"

    def __post_init__(self):
        c = tuple(float(t) for t in self.coefficients)
        if not 1 <= len(c) <= 25 or not all(math.isfinite(t) for t in c):
            raise InputError(f"EMoR response needs 1..25 finite coefficients, got {c}")
        object.__setattr__(self, "coefficients", c)

    @property
    def param_names(self):  # type: ignore[override]
        return tuple(f"c{m}" for m in range(1, len(self.coefficients) + 1))

    def vector(self) -> np.ndarray:
        return np.array(self.coefficients)

    @classmethod
    def from_vector(cls, theta, **fixed) -> Emor:
        return cls(tuple(float(t) for t in theta), **fixed)

    def params(self):
        p = {"coefficients": list(self.coefficients)}
        if self.emor_dir is not None:
            p["emor_dir"] = str(self.emor_dir)
        return p

    def raw_curve(self) -> np.ndarray:
        """``f0 + sum c_m h_m`` on the basis grid, unconstrained (what the fit adjusts)."""
        b = EmorBasis.load(self.emor_dir)
        return b.mean + np.asarray(self.coefficients) @ b.components[:len(self.coefficients)]

    def _curve(self) -> tuple[np.ndarray, np.ndarray]:
        cache = self.__dict__.get("_c")
        if cache is None:
            f = _strictly_increasing(np.clip(self.raw_curve(), 0.0, 1.0))
            cache = (EmorBasis.load(self.emor_dir).grid, (f - f[0]) / (f[-1] - f[0]))
            object.__setattr__(self, "_c", cache)
        return cache

    def forward(self, x):
        grid, f = self._curve()
        return np.interp(np.asarray(x, dtype=np.float64), grid, f)

    def inverse(self, v):
        grid, f = self._curve()
        return np.interp(np.asarray(v, dtype=np.float64), f, grid)
