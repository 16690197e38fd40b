"""Shared fixtures.

OpenCL tests use the ``opencl`` fixture: they skip without a usable device, except under CI
(``CI`` set), where a missing device is a failure, so kernel tests can never silently vanish.
``pytest --opencl-only`` runs just those tests (the ``opencl`` fixture or mark): the kernel
cross-check on another device, ``CLBLUR_DEVICE=NAME pytest --opencl-only`` (``bench/gpu_check.sh``).
"""

from __future__ import annotations

import os

# BLAS on one thread in this process and, through the environment, in the processes tests
# start (CLI runs, the study's fold workers), as the library's fits run (clblur.blas).  Why:
# OpenBLAS's idle threads spin.  On a 2-core VM a calibration test took twice the CPU time on
# 2 threads for the same wall time (test_the_spline_s_smoothness_is_chosen_on_held_out_pixels:
# 55 against 27 CPU-s, 31 / 29 s), and beside a second pytest-xdist worker 444 s.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from clblur.blas import one_blas_thread  # noqa: E402
from clblur.io import data_dir  # noqa: E402

# numpy may have been imported (by a pytest plugin) before the variable was set
_BLAS_LIMIT = one_blas_thread()


def pytest_addoption(parser):
    parser.addoption("--opencl-only", action="store_true",
                     help="run only the tests that use an OpenCL device")


def pytest_collection_modifyitems(config, items):
    if not config.getoption("--opencl-only"):
        return
    keep, drop = [], []
    for item in items:
        uses = "opencl" in getattr(item, "fixturenames", ()) or item.get_closest_marker("opencl")
        (keep if uses else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


@pytest.fixture(scope="session")
def opencl():
    from clblur import opencl as backend

    ok, why = backend.usable(None)
    if not ok:
        if os.environ.get("CI"):
            pytest.fail(f"CI requires a working OpenCL device: {why}")
        pytest.skip(f"no usable OpenCL device: {why}")
    return backend


@pytest.fixture(scope="session")
def shared_data():
    d = data_dir()
    if d is None:
        pytest.skip("shared measured data not found (set CLBLUR_DATA)")
    return d


@pytest.fixture
def rng():
    return np.random.default_rng(20061213)
