"""Camera response models: normalised pixel value <-> linear exposure.

Conventions
-----------
* ``forward(x)`` maps linear exposure ``x >= 0`` (time x irradiance, arbitrary units) to a
  normalised pixel value ``v`` in [0, 1] (code value / Imax).
* ``inverse(v)`` maps ``v`` back to exposure.  It may be infinite at ``v == 1`` (the paper's
  Eq. 3 reaches Imax only at infinite exposure); the blur's saturation policy handles that.
* The ``linear`` response is unbounded: it passes any real value through, so scene-linear float
  images (values above 1) are blurred as they are.  Every other response clips ``v`` to [0, 1].

Every model shares this small interface, so the numpy reference and the OpenCL kernels read the
same description (``KIND_CODES``) and curves of any other family run as a ``table``
(``for_device``).

This package is the only place where curve formulas live.  Device kinds: ``Linear``, ``Exp``
(the paper's Eq. 3, Lin & Chang 2006), ``Gamma``, ``SRGB``, ``Table``.  Families fitted by
``clblur.calibration`` and ``clblur.study`` (each with a parameter vector: ``param_names``,
``vector()``, ``from_vector``): ``ExpOffset`` (Eq. 3 above a black level), ``GammaOffset``,
``ExpShape`` (Eq. 3 generalised: black level, power, curvature and a free smooth warp, nested
so that its null parameters give Eq. 3 exactly), ``Polynomial`` (Mitsunaga & Nayar 1999),
``Emor`` (Grossberg & Nayar 2004, basis from ``$CLBLUR_DATA/crf``) and ``MonotoneSpline`` (a
free monotone piecewise-linear curve, itself a ``Table``).

Valid parameter ranges (``RANGES``) are enforced when a response is built or parsed: outside
them float32 kernels under- or overflow on some codes and cannot match the float64 reference.
"""

from clblur.responses.base import FORMAT_VERSION, KIND_CODES, RANGES, Parametric, Response
from clblur.responses.documents import (
    CHANNEL_SET_KIND,
    FAMILY_CLASSES,
    channel_set_to_dict,
    check_spec,
    for_device,
    from_dict,
    load_response,
    per_channel,
    response,
    save_channel_set,
)
from clblur.responses.emor import Emor, EmorBasis
from clblur.responses.families import (
    ExpOffset,
    ExpShape,
    GammaOffset,
    MonotoneSpline,
    Polynomial,
    default_knots,
    warp_basis,
    warp_basis_slopes,
)
from clblur.responses.kernel_curves import SRGB, Exp, Gamma, Linear, Table

__all__ = ["Response", "Linear", "Exp", "Gamma", "SRGB", "Table", "ExpOffset", "GammaOffset",
           "ExpShape", "Polynomial", "Emor", "EmorBasis", "MonotoneSpline", "KIND_CODES",
           "RANGES", "FAMILY_CLASSES", "response", "from_dict", "load_response", "per_channel",
           "for_device", "default_knots", "warp_basis", "warp_basis_slopes",
           "channel_set_to_dict", "save_channel_set", "CHANNEL_SET_KIND", "Parametric",
           "FORMAT_VERSION", "check_spec"]
