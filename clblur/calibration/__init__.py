"""Photometric calibration from exposure series (the paper's Eq. 3 fit and richer families).

``load_series`` reads a stack, ``fit`` fits one response family (``MODELS``) per channel or
shared, ``evaluate`` measures held-out prediction error between exposures.
"""

from clblur.calibration.evaluate import evaluate
from clblur.calibration.fitting import ResponseFit, fit, radiance_map
from clblur.calibration.models import MODELS
from clblur.calibration.series import ExposureSeries, load_series

__all__ = ["load_series", "ExposureSeries", "fit", "ResponseFit", "evaluate", "MODELS",
           "radiance_map"]
