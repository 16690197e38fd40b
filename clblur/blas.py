"""BLAS on one thread while the library fits: the study's and the calibration's fits.

Their BLAS calls are small (L-BFGS-B's on a few dozen parameters, least squares on a
spline's 64 knots), and OpenBLAS's worker threads, woken by each, spin on cores that other
work needs.  Measured on a 2-core VM (2026-12-03): ``clblur calibrate`` on the Memorial stack
took 115 s wall and 179 CPU-s on two BLAS threads, 105 s and 103 CPU-s on one, with the same
output to the byte; a study spent a third of its CPU time so.  Where two such processes
share the cores the spinning starves both (a calibration test went from 27 s to 444 s beside
a second pytest worker).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

from threadpoolctl import threadpool_limits

__all__ = ["one_blas_thread", "with_one_blas_thread"]

F = TypeVar("F", bound=Callable)


def one_blas_thread() -> threadpool_limits:
    """A context manager that keeps BLAS on one thread until it exits (called bare, until
    the process ends)."""
    return threadpool_limits(limits=1, user_api="blas")


def with_one_blas_thread(func: F) -> F:
    """``func`` run under :func:`one_blas_thread`."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return func(*args, **kwargs)
    return wrapper  # type: ignore[return-value]
