"""The blur pipeline, composed once: linearise -> integrate -> finish.

Every caller (``clblur.blur``, the numpy reference, video's bent path, layered exposure,
tiling and Dask through ``clblur.blur.blur_plan``) runs a plan through :func:`run`; none of them
strings the steps together itself.

Conventions
-----------
* ``linearise(plan)`` -> the linear image: exposures, H x W x C (float64 on the numpy backend).
  With ``plan.alpha`` the last channel is coverage: it is *not* linearised, and the colour
  channels are premultiplied by it (see :func:`clblur.reference.linearise`).
* ``integrate(linear, plan)`` -> linear image of the same shape: the exposure each output
  pixel collects during the shutter.  Any callable with this signature plugs in: the plain
  gather (``clblur.reference.integrate``), a sum of bent-path halves (``clblur.video``), or the
  layered compositor (``clblur.layered_exposure.integrate``).
* ``finish(linear, plan)`` -> the output: forward response per colour channel, (with alpha:
  un-premultiply for integer outputs), quantise, and the input's layout.
* A backend is any object with these three methods (:class:`Backend`).  A backend may also
  offer ``fused(plan)``, one call that does all three with the plain gather (the OpenCL backend
  fuses the response and the quantisation into its integration kernel); :func:`run` uses it
  when no other integrator is asked for and the backend's optional ``can_fuse(plan)`` agrees.
* A *sparse* integrator (attribute ``sparse = True``) changes the plain result at a few pixels
  only: it is called with a function that returns the linear image on demand, and answers
  None (nothing differs from the gather) or ``(rows, cols, values)``, the exposures (n x C)
  of those pixels.  :func:`run` runs the plain pipeline (on a second thread, beside the
  integrator) and replaces those pixels by their finished values, so every other pixel is the
  plain result bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from clblur import reference
from clblur.request import BlurPlan

__all__ = ["Backend", "Integrator", "NUMPY", "NumpyStages", "run", "run_numpy"]

Integrator = Callable[[Any, BlurPlan], Any]


class Backend(Protocol):
    """The three stages a backend provides (see the module Conventions)."""

    def linearise(self, plan: BlurPlan) -> Any: ...

    def integrate(self, linear: Any, plan: BlurPlan) -> Any: ...

    def finish(self, linear: Any, plan: BlurPlan) -> np.ndarray: ...


class NumpyStages:
    """The float64 numpy reference stages (``clblur.reference``)."""

    name = "numpy"

    @staticmethod
    def linearise(plan: BlurPlan) -> np.ndarray:
        return reference.linearise(plan)

    @staticmethod
    def integrate(linear: np.ndarray, plan: BlurPlan) -> np.ndarray:
        return reference.integrate(linear, plan)

    @staticmethod
    def finish(linear: np.ndarray, plan: BlurPlan) -> np.ndarray:
        return reference.finish(linear, plan)


NUMPY = NumpyStages()


def run(plan: BlurPlan, backend: Backend = NUMPY,
        integrate: Integrator | None = None) -> np.ndarray:
    """``finish(integrate(linearise(plan), plan), plan)`` on ``backend``.

    Parameters
    ----------
    plan : a validated request (``clblur.request.make_plan``).
    backend : the stages to run; default the numpy reference.
    integrate : the integrator; default the backend's own (the plain gather), or its fused
        path when it has one.

    Returns
    -------
    The blurred image with the input's dtype and shape.
    """
    if integrate is None:
        fused = getattr(backend, "fused", None)
        can_fuse = getattr(backend, "can_fuse", None)
        if fused is not None and (can_fuse is None or can_fuse(plan)):
            return fused(plan)
        integrate = backend.integrate
    if getattr(integrate, "sparse", False):
        # The plain result does not depend on the patch: it runs on a second thread while
        # this one prepares the patch (a device backend's kernels then overlap the host work).
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(1) as pool:
            plain = pool.submit(run, plan, backend)
            patch = integrate(lambda: backend.linearise(plan), plan)
            out = plain.result()
        if patch is None:
            return out
        rows, cols, values = patch
        # finish the patch as a 1-pixel-wide image with the plan's channels
        column = backend.finish(values[:, None, :], replace(plan, squeeze=False))
        out = out.copy() if not out.flags.writeable or not out.flags.c_contiguous else out
        # by flat index: fancy (rows, cols) indexing of a whole frame is several times slower
        flat = out.reshape((-1,) + out.shape[2:])
        flat[np.ravel_multi_index((rows, cols), out.shape[:2])] = \
            column[:, 0, 0] if plan.squeeze else column[:, 0]
        return out
    return backend.finish(integrate(backend.linearise(plan), plan), plan)


def run_numpy(plan: BlurPlan, integrate: Integrator | None = None) -> np.ndarray:
    """:func:`run` on the numpy reference stages."""
    return run(plan, NUMPY, integrate)
