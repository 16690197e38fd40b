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


@pytest.mark.parametrize("through", ["pipe", "file"])
def test_the_worker_gives_the_sequential_fits_bit_for_bit(monkeypatch, tmp_path, through):
    """Fold 1 fitted in the child equals the fit in this process, bit for bit, whether the
    fold went to the child through the pipe or its arrays through a file (which is gone
    once the child ends)."""
    from clblur.study import fold_worker

    if not _parallel_folds():
        pytest.skip("one core: the folds are fitted in this process")
    made = []
    if through == "file":
        monkeypatch.setattr(fold_worker, "OUT_OF_BAND_BYTES", 0)
        monkeypatch.setattr(fold_worker, "_scratch_folder", lambda n: str(tmp_path))
        real = fold_worker.tempfile.mkstemp

        def mkstemp(**kw):
            made.append(real(**kw))
            return made[-1]
        monkeypatch.setattr(fold_worker.tempfile, "mkstemp", mkstemp)
    null = null_params()
    model = frozenset({"black_level", "channel_gain"})
    with _folds() as folds:
        parallel = folds.fit(model, [null, null], 3)
        worker = folds._worker
        assert worker is not None  # fold 1 went to the child
        assert (worker._path is not None) == (through == "file")
    assert worker._proc.poll() is not None  # ended with its folds
    assert len(made) == (through == "file") and not list(tmp_path.iterdir())
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


def test_remembered_products_give_the_predictions_computed_afresh():
    """``Group.product`` remembers sparse products per code table: a run of predictions in
    the order a gradient takes them (the point, then one parameter at a time, with and
    without a shift mixing in the variant histograms) equals predictions on fresh copies
    of the group, bit for bit; the memory stays bounded and is not pickled to a worker."""
    import copy
    import pickle

    from clblur.study.model import _PRODUCTS_KEPT
    from clblur.study.variants import predict

    sc = scenario({"misregistration": 0.4}, np.random.default_rng(3))
    g = sc.groups[0]
    assert "misregistration" in g.__dict__.get("variants", {})
    base = {**null_params(), "gamma": 1.3}
    steps = [base] + [{**base, name: base[name] + 0.01}
                      for name in ("gain", "na", "gamma", "t1", "vig", "sx", "black")
                      if name in base]
    steps += [{**s, "sx": 0.3} for s in steps]
    for p in steps:
        fresh = copy.copy(g)
        fresh.__dict__ = {k: v for k, v in g.__dict__.items() if k != "_products"}
        want, got = predict(fresh, p), predict(g, p)
        for a, b in zip(want, got, strict=True):
            assert np.array_equal(a, b)
    held = g.__dict__["_products"]
    assert held and len(held) <= _PRODUCTS_KEPT * 2 * g.channels
    assert "_products" not in pickle.loads(pickle.dumps(g)).__dict__


def test_remembered_image_factors_give_the_predictions_computed_afresh():
    """``model._image_factors`` remembers each row's exposure and white-balance factors for
    the last values of the images' deviations (``lt:I``, ``lw:I:c``): predictions in a
    gradient's order, each image's deviation moved in turn and back, equal predictions on
    fresh copies of the group bit for bit; the memory stays bounded, is not pickled, and
    a moved deviation does change the prediction (the comparison can fail)."""
    import copy
    import pickle

    from clblur.study.model import _PRODUCTS_KEPT, predict
    from clblur.study.variants import pack

    sc = scenario({"exposure_times": 0.2}, np.random.default_rng(5))
    assign_blocks(sc.groups)
    (g,) = pack(sc.groups)  # the series' steps in one group: several pairs of images
    assert np.unique(g.images, axis=0).shape[0] > 1
    base = {**null_params(), "lt:1": 0.1, "lt:2": -0.05, "lw:1:1": 0.02, "lw:3:2": -0.03}
    steps = [base] + [{**base, k: base[k] + 0.01} for k in ("gain", "lt:1", "lw:3:2", "lt:2")]
    steps += [base, {**base, "lt:3": 0.2}, {**null_params()}]
    predictions = []
    for p in steps:
        fresh = copy.copy(g)
        fresh.__dict__ = {k: v for k, v in g.__dict__.items()
                          if k not in ("_factors", "_image_pairs", "_products")}
        want, got = predict(fresh, p), predict(g, p)
        for a, b in zip(want, got, strict=True):
            assert np.array_equal(a, b)
        predictions.append(got[0])
    assert not np.array_equal(predictions[0], predictions[2])  # lt:1 moved
    assert not np.array_equal(predictions[0], predictions[4])  # lt:2 moved
    held = g.__dict__["_factors"]
    assert held and len(held) <= 2 * _PRODUCTS_KEPT
    assert "_factors" not in pickle.loads(pickle.dumps(g)).__dict__


@pytest.mark.parametrize("processes", ["1", "0"])
def test_improve_keeps_the_better_fit_of_each_fold(monkeypatch, processes):
    """``Folds.improve`` descends from the given starts and keeps, per fold, whichever fit
    of the model fits that fold better: a poorer cached fit is replaced, and a kept fit is
    never worse than the one cached (fold 1 in the worker, and in this process)."""
    from clblur.study.crossfit import penalised_nll

    monkeypatch.setenv("CLBLUR_STUDY_PROCESSES", processes)

    null = null_params()
    model = frozenset({"black_level", "response_shape"})
    with _folds() as folds:
        good = folds.fit(model, [null, null], 3)
        nll = [penalised_nll(part, p) for part, p in zip(folds.part, good, strict=True)]
        assert penalised_nll(folds.part[0], null) > nll[0] + 1.0  # the comparison can fail
        folds.cache[(model, None)] = [null, good[1]]  # fold 0's fit forgotten
        assert folds.improve(model, good, 3)
        kept = folds.fit(model, [null, null], 3)
        assert penalised_nll(folds.part[0], kept[0]) <= nll[0] + 1e-6
        assert penalised_nll(folds.part[1], kept[1]) <= nll[1]
