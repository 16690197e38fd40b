"""Photometric calibration from exposure series (the paper's Eq. 3 fit and richer families).

``load_series`` reads a stack, ``fit`` fits one response family (``MODELS``) per channel or
shared, ``evaluate`` measures held-out prediction error between exposures; ``calibrate`` does
all three for several models and ranks them (the API behind ``clblur calibrate``).
"""

from clblur.calibration.compare import Calibration, calibrate
from clblur.calibration.evaluate import evaluate
from clblur.calibration.fitting import ResponseFit, fit, radiance_map
from clblur.calibration.models import MODELS
from clblur.calibration.series import ExposureSeries, load_series

__all__ = ["load_series", "ExposureSeries", "fit", "ResponseFit", "evaluate", "calibrate",
           "Calibration", "MODELS", "radiance_map"]
