"""Response families fitted to calibration samples: the registry of every family.

The families live by fitting role: ``forward_families`` (exp, exp-offset, gamma-offset,
emor), ``inverse_families`` (polynomial, nonparametric) and ``cross_exposure`` (spline).

Conventions
-----------
* Each family fits one response curve to a ``SampleSet`` (rows: samples, columns: exposures)
  given the nominal relative exposures ``tau`` (longest = 1).  The unknowns are the curve and
  one radiance per sample; the radiance scale and the exposure unit are the same degree of
  freedom, so every family fixes it by a convention stated on the class.
* The result is a ``FamilyFit``: a ``clblur.responses.Response`` (``Exp`` for the paper's
  family; a ``Table`` with ``meta = {"family", "params"}`` for the others, so ``clblur blur
  --response FILE`` runs them on the same kernel path), the family's parameters, the number of
  curve parameters and the exposures used (re-estimated when ``refine_times`` is set).
* ``exp``, ``exp-offset``, ``gamma-offset`` and ``emor`` are fitted in the *forward*
  direction: least squares on code values, the quantity the evaluation measures.
  ``polynomial`` (Mitsunaga & Nayar) and ``nonparametric`` (Debevec & Malik) are fitted in the
  inverse direction as their authors specify, then made monotone.
* ``refine_times`` (uncertain shutter times) re-estimates one exposure per image, tied to the
  nominal value by a Gaussian prior (``TIME_SIGMA`` in log units) with the mean and the
  overall trend of ``ln tau`` held at their nominal values (see ``time_deviation_basis``).
"""

from __future__ import annotations

from clblur.calibration.cross_exposure import (
    PAIR_HIGH_CODE,
    PAIR_LOW_CODE,
    SplineFamily,
    curve_black_level,
    fit_cross_exposure,
    pooled_pairs,
)
from clblur.calibration.forward_families import (
    CURVE_LOW,
    FLOOR_LOW,
    TABLE_SIZE,
    TIME_PRIOR_SCALE,
    TIME_SIGMA,
    EmorFamily,
    ExpFamily,
    ExpOffsetFamily,
    FamilyFit,
    ForwardFamily,
    GammaOffsetFamily,
    time_deviation_basis,
)
from clblur.calibration.inverse_families import NonparametricFamily, PolynomialFamily
from clblur.responses import EmorBasis  # the basis the emor family loads (re-exported)

__all__ = ["FAMILIES", "MODELS", "FamilyFit", "ForwardFamily", "ExpFamily", "ExpOffsetFamily",
           "GammaOffsetFamily", "EmorFamily", "PolynomialFamily", "NonparametricFamily",
           "SplineFamily", "EmorBasis", "time_deviation_basis", "curve_black_level",
           "pooled_pairs", "fit_cross_exposure", "TABLE_SIZE", "FLOOR_LOW", "CURVE_LOW",
           "TIME_SIGMA", "TIME_PRIOR_SCALE", "PAIR_LOW_CODE", "PAIR_HIGH_CODE"]

FAMILIES = {f.name: f for f in (ExpFamily(), ExpOffsetFamily(), GammaOffsetFamily(),
                                PolynomialFamily(), NonparametricFamily(), EmorFamily(),
                                SplineFamily())}
MODELS = tuple(FAMILIES)
