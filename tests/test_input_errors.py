"""Bad input to a public entry raises ``clblur.errors.InputError`` (README: "Library code raises
``clblur.errors.InputError`` (a ``ValueError``) for bad input"); input of the wrong type raises
``InputTypeError``, which is also a ``TypeError``."""

from __future__ import annotations

import numpy as np
import pytest

import clblur
from clblur.errors import InputError, InputTypeError

H, W = 8, 10
IMG = np.full((H, W, 3), 128, np.uint8)
FLOW = np.zeros((H, W, 2), np.float32)
NAN_FLOW = FLOW.copy()
NAN_FLOW[2, 3, 0] = np.nan
NAN_DEPTH = np.ones((H, W))
NAN_DEPTH[0, 0] = np.nan


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("CLBLUR_QUIET", "1")


def _raises(call, typed: bool):
    """``call()`` raises an InputError naming the problem; ``typed``: an InputTypeError."""
    with pytest.raises(InputError) as info:
        call()
    assert str(info.value)
    assert isinstance(info.value, TypeError) == typed, type(info.value)
    assert isinstance(info.value, InputTypeError) == typed
    assert isinstance(info.value, ValueError)  # every InputError stays a ValueError


# (name, keyword overrides of blur(IMG, (1.5, 0.5), backend="numpy"), wrong type?)
BLUR_CASES = [
    ("nan motion", dict(motion=(np.nan, 0.0)), False),
    ("inf motion", dict(motion=(np.inf, 1.0)), False),
    ("flow of wrong shape", dict(motion=np.zeros((4, 4, 2), np.float32)), False),
    ("flow with NaN", dict(motion=NAN_FLOW), False),
    ("motion of 4 dims", dict(motion=np.zeros((2, 2, 2, 2))), False),
    ("motion of strings", dict(motion=["a", "b"]), True),
    ("negative PSF", dict(motion=np.array([[0.5, -0.1, 0.6]])), False),
    ("depth of wrong shape", dict(motion=FLOW, depth=np.ones((H + 1, W))), False),
    ("depth with NaN", dict(motion=FLOW, depth=NAN_DEPTH), False),
    ("depth <= 0", dict(motion=FLOW, depth=np.zeros((H, W))), False),
    ("depth of strings", dict(motion=FLOW, depth="nearest"), True),
    ("background without depth", dict(background=IMG), False),
    ("background of wrong shape", dict(motion=FLOW, depth=np.ones((H, W)),
                                       background=IMG[:4]), False),
    ("bad anchor", dict(anchor="middle"), False),
    ("samples=0", dict(samples=0), False),
    ("samples=2.5", dict(samples=2.5), True),
    ("negative weights", dict(weights=[-1.0, 2.0]), False),
    ("weights for other samples", dict(weights=[1.0, 1.0], samples=3), False),
    ("continuous PSF", dict(motion=np.ones((3, 3)), exposure="continuous"), False),
    ("samples of a PSF", dict(motion=np.ones((3, 3)), samples=3), False),
    ("weights of a PSF", dict(motion=np.ones((3, 3)), weights=[1.0, 5.0, 1.0]), False),
    ("an RGB set for an RGBA image with its alpha",
     dict(image=np.dstack([IMG, IMG[..., :1]]), alpha=True,
          response=["srgb", "srgb", "srgb", "srgb"]), False),
    ("alpha not a bool", dict(alpha="yes"), True),
    ("weights from a generator", dict(weights=(w for w in (1.0, 2.0))), True),
    ("anchor in a list", dict(anchor=["start"]), False),
    ("alpha of one channel", dict(image=IMG[..., :1], alpha=True), False),
    ("response out of range", dict(response="exp:-1"), False),
    ("response not a number", dict(response="gamma:abc"), False),
    ("unknown response", dict(response="nope"), False),
    ("response of wrong type", dict(response=42), True),
    ("responses per channel miscounted", dict(response=["linear", "srgb"]), False),
    ("unknown backend", dict(backend="cuda"), False),
    ("bool image", dict(image=IMG > 0), True),
    ("int8 image", dict(image=IMG.astype(np.int8)), True),
    ("float16 image", dict(image=IMG.astype(np.float16)), True),
    ("list as image", dict(image=IMG.tolist()), True),
    ("image of 4 dims", dict(image=IMG[None]), False),
    ("empty image", dict(image=IMG[:0]), False),
    ("NaN image", dict(image=np.full((H, W, 3), np.nan, np.float32)), False),
    ("saturation below 1", dict(saturation=0.5), False),
    ("saturation not a number", dict(saturation="bright"), True),
    ("device selector not a string", dict(backend="auto", device=3), True),
]


@pytest.mark.parametrize("kwargs, typed", [c[1:] for c in BLUR_CASES],
                         ids=[c[0] for c in BLUR_CASES])
def test_blur_bad_input(kwargs, typed):
    args = dict(image=IMG, motion=(1.5, 0.5), backend="numpy") | kwargs
    _raises(lambda: clblur.blur(args.pop("image"), args.pop("motion"), **args), typed)


def _layer(motion=FLOW, dtype=np.uint8):
    return (np.full((H, W, 4), 200, dtype), motion)


LAYER_CASES = [
    ("nan vectors", dict(layers=[_layer(NAN_FLOW)]), False),
    ("vectors of wrong shape", dict(layers=[_layer(FLOW[:4])]), False),
    ("bad anchor", dict(anchor="middle"), False),
    ("samples=2.5", dict(samples=2.5), True),
    ("response out of range", dict(response="exp:-1"), False),
    ("bool layer", dict(layers=[_layer(dtype=bool)]), True),
]


@pytest.mark.parametrize("kwargs, typed", [c[1:] for c in LAYER_CASES],
                         ids=[c[0] for c in LAYER_CASES])
def test_blur_layers_bad_input(kwargs, typed):
    args = dict(layers=[_layer()], backend="numpy") | kwargs
    _raises(lambda: clblur.blur_layers(args.pop("layers"), **args), typed)


RESPONSE_CASES = [
    ("exp:-1", lambda: clblur.response("exp:-1"), False),
    ("gamma:100", lambda: clblur.response("gamma:100"), False),
    ("gamma:", lambda: clblur.response("gamma"), False),
    ("unknown name", lambda: clblur.response("nope"), False),
    ("a number", lambda: clblur.response(2.2), True),
    ("unknown key", lambda: clblur.response({"kind": "gamma", "gamma": 2.4}), False),
    ("unknown kind", lambda: clblur.response({"kind": "nope", "params": {}}), False),
    ("bad parameter", lambda: clblur.response({"kind": "exp", "params": {"x": 1}}), False),
    ("Exp(-1)", lambda: clblur.Exp(-1.0), False),
    ("Exp('k')", lambda: clblur.Exp("k"), True),
    ("Gamma(100)", lambda: clblur.Gamma(100.0), False),
    ("Table decreasing", lambda: clblur.Table([0.0, 1.0], [1.0, 0.0]), False),
    ("Table too short", lambda: clblur.Table([0.0], [0.0]), False),
    ("Table of words", lambda: clblur.response(
        {"kind": "table", "params": {"exposure": "ab", "value": [0.0, 1.0]}}), False),
    ("params not an object", lambda: clblur.response({"kind": "gamma", "params": [1]}), False),
]


@pytest.mark.parametrize("call, typed", [c[1:] for c in RESPONSE_CASES],
                         ids=[c[0] for c in RESPONSE_CASES])
def test_response_bad_spec(call, typed):
    _raises(call, typed)


@pytest.mark.parametrize("content", [None, "{not json", '{"kind": "exp", "params": {"k": -1}}',
                                     '{"kind": "gamma", "gamma": 2.4}'],
                         ids=["missing", "not json", "out of range", "unknown key"])
def test_load_response_bad_file(tmp_path, content):
    path = tmp_path / "r.json"
    if content is not None:
        path.write_text(content)
    _raises(lambda: clblur.load_response(path), False)
    _raises(lambda: clblur.response(str(path)), False)


def test_other_public_modules():
    from clblur.camera import Camera
    from clblur.flow import FlowEstimator, grey8
    from clblur.layering import layer_labels, named_order
    from clblur.registration import pair_shift
    from clblur.vectors import exposure_flow, from_blender

    _raises(lambda: Camera(storage="ceil"), False)
    _raises(lambda: Camera().capture(np.ones((H, W, 3)).tolist()), True)
    _raises(lambda: Camera().capture(np.ones((H, W, 3)), -1.0), False)
    _raises(lambda: grey8(IMG.astype(np.int8)), True)
    _raises(lambda: FlowEstimator("magic"), False)
    _raises(lambda: named_order("nearest"), False)
    _raises(lambda: layer_labels(np.ones((H, W)), rule="size"), False)
    _raises(lambda: pair_shift(np.ones((H, W)), np.ones((H, W + 1))), False)
    _raises(lambda: exposure_flow(FLOW, FLOW, shutter=0.0), False)
    _raises(lambda: from_blender(np.zeros((H, W, 3), np.float32)), False)


def test_calibration_bad_input(tmp_path):
    # the calibration package raised plain ValueError / TypeError: `except InputError`
    # missed them
    from clblur.calibration import ExposureSeries, calibrate, fit
    from clblur.calibration.series import parse_time

    ramp = np.linspace(20, 230, H * W * 3).reshape(H, W, 3).astype(np.uint8)
    series = ExposureSeries.create([ramp // 2, ramp], [0.5, 1.0])
    _raises(lambda: fit(series, "gamma"), False)
    _raises(lambda: fit([ramp, ramp], "exp"), True)
    _raises(lambda: ExposureSeries.create([ramp], [1.0]), False)
    _raises(lambda: ExposureSeries.create([ramp, ramp], [1.0, 1.0]), False)
    _raises(lambda: ExposureSeries.create([ramp, ramp[:4]], [0.5, 1.0]), False)
    _raises(lambda: calibrate(tmp_path / "missing", [0.5, 1.0]), False)
    _raises(lambda: parse_time("fast"), False)
    _raises(lambda: parse_time([1.0]), True)


def test_dask_blur_bad_input():
    da = pytest.importorskip("dask.array")
    from clblur import dask_array

    _raises(lambda: dask_array.blur(IMG, (1.0, 0.0)), True)
    arr = da.from_array(IMG, chunks=(4, 5, 3))
    _raises(lambda: dask_array.blur(arr, da.from_array(FLOW[:4], chunks=(4, 5, 2))), False)


@pytest.mark.opencl
def test_opencl_flow_refused_on_the_device_is_an_input_error(opencl):
    # the device counts bad flow components (NaN, beyond the limit) instead of the host
    _raises(lambda: clblur.blur(IMG, NAN_FLOW, backend="opencl"), False)
    _raises(lambda: clblur.blur(IMG, (1.0, 0.0), backend="opencl", device="9:9"), False)


def test_what_an_augmentation_pipeline_hands_over(rng):
    """A random draw's huge vector is refused before it allocates (1e9 px had allocated
    7.5 GiB of sample positions, or drawn the OOM killer), unless a sample count is given; a
    big-endian image is its values; round-off just below 0 in a resampled PSF is 0, a real
    negative lobe is named; a 1 x 2 array is a PSF, with a warning that it is no vector."""
    img = rng.random((12, 14, 3)).astype(np.float32)
    for v in ((1e9, 0.0), (0.0, -7e4), (5e4, 5e4)):
        with pytest.raises(InputError, match="longer than 65536 px.*samples=N"):
            clblur.blur(img, v, "srgb", backend="numpy")
    assert clblur.blur(img, (1e9, 0.0), "srgb", samples=3, backend="numpy").shape == img.shape
    np.testing.assert_array_equal(clblur.blur(img.astype(">f4"), (3.0, 1.0), "srgb",
                                              backend="numpy"),
                                  clblur.blur(img, (3.0, 1.0), "srgb", backend="numpy"))
    kernel = np.array([[0.0, 1.0, 1.0, 1.0, 0.0]])
    rounded = kernel.copy()
    rounded[0, 4] = -1e-12
    np.testing.assert_array_equal(clblur.blur(img, rounded, "srgb", backend="numpy"),
                                  clblur.blur(img, kernel, "srgb", backend="numpy"))
    rounded[0, 4] = -0.01
    with pytest.raises(InputError, match=r"-0.01 at \(row, col\) \(0, 4\)"):
        clblur.blur(img, rounded, "srgb", backend="numpy")
    with pytest.warns(UserWarning, match="PSF of two taps, not a vector"):
        clblur.blur(img, np.array([[8.0, 3.0]]), "srgb", backend="numpy")
