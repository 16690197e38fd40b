"""Shared fixtures.

OpenCL tests use the ``opencl`` fixture: they skip without a usable device, except under CI
(``CI`` set), where a missing device is a failure, so kernel tests can never silently vanish.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from clblur.io import data_dir


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
