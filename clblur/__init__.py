"""clblur: photo-consistent motion blur (Lin & Chang, PSIVT 2006) with OpenCL kernels.

Importing clblur creates no OpenCL context; the backend creates one lazily, once per process.
"""

from clblur.blur import blur
from clblur.motion import PSF, Field, Uniform
from clblur.render_layers import blur_layers
from clblur.responses import (
    SRGB,
    Exp,
    Gamma,
    Linear,
    Response,
    Table,
    load_response,
    response,
)

__version__ = "0.1.0"

__all__ = ["blur", "blur_layers", "response", "load_response", "Response", "Linear", "Exp",
           "Gamma", "SRGB", "Table", "Uniform", "Field", "PSF", "__version__"]
