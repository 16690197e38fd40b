"""The study's fold worker: fold 1 fitted in a child process gives the sequential fits."""

from __future__ import annotations

import numpy as np
import pytest

from clblur.study.crossfit import Folds, _parallel_folds, assign_blocks
from clblur.study.fold_worker import FoldWorker
from clblur.study.model import null_params
from clblur.study.synthetic import scenario


def _folds() -> Folds:
    sc = scenario({"black_level": 0.03, "response_shape": 1.8}, np.random.default_rng(7))
    return Folds(sc.groups, assign_blocks(sc.groups))


def test_the_worker_gives_the_sequential_fits_bit_for_bit(monkeypatch):
    if not _parallel_folds():
        pytest.skip("one core: the folds are fitted in this process")
    null = null_params()
    model = frozenset({"black_level", "channel_gain"})
    with _folds() as folds:
        parallel = folds.fit(model, [null, null], 3)
        worker = folds._worker
        assert worker is not None  # fold 1 went to the child
    assert worker._proc.poll() is not None  # ended with its folds
    monkeypatch.setenv("CLBLUR_STUDY_PROCESSES", "0")
    with _folds() as folds:
        sequential = folds.fit(model, [null, null], 3)
        assert folds._worker is None
    assert parallel == sequential
    assert parallel[0] != parallel[1]  # two folds, two fits: the comparison can fail


def test_a_fit_that_fails_in_the_worker_is_raised_with_its_traceback():
    folds = _folds()
    worker = FoldWorker(folds.part[1], folds.nvalid[1], folds.bounds)
    try:
        worker.submit(["no_such_parameter"], null_params(), None, False)
        with pytest.raises(RuntimeError, match="no_such_parameter"):
            worker.result()
        # the worker carries on after a failed fit
        worker.submit(["gain"], null_params(), None, False)
        assert set(worker.result()) >= {"gain"}
    finally:
        worker.close()
    assert worker._proc.poll() == 0
