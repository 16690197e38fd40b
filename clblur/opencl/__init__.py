"""OpenCL backend: device selection, programs with named-argument launches, host-side
preparation by concern, the kernels (``*.cl`` beside this file) and the pipeline stages.

Modules: ``device`` (selection, contexts, queues, buffers), ``program`` (kernel wrapper),
``constants`` (every constant shared with the kernels, passed as ``-D`` options), ``taps``
(rasterising uniform motion and PSFs), ``response_pack`` (forward responses for the kernels),
``quantisation`` (code boundaries, their bucket index and the uint8 code grid),
``half_float`` (half-storage error bound), ``linearisation`` (host tables, the float
inverse's arguments), ``transfers``
(row bands on several queues, pinned memory), ``backend`` (stage functions and ``blur``),
``resident`` (``pyopencl.array.Array`` in and out).  Importing this package imports no pyopencl.
"""

from clblur.opencl.backend import blur, pinned_empty, run_plan
from clblur.opencl.device import (
    ENV_DEVICE,
    DeviceNotFound,
    OpenCLUnavailable,
    Runtime,
    current_device,
    devices,
    pyopencl_module,
    runtime,
    runtimes,
    usable,
)
from clblur.opencl.resident import blur_array

__all__ = ["ENV_DEVICE", "DeviceNotFound", "OpenCLUnavailable", "Runtime", "blur", "blur_array",
           "current_device", "devices", "pinned_empty", "pyopencl_module", "run_plan", "runtime",
           "runtimes", "usable"]
