"""The OpenCL package's host paths: named launches, generated constants, the GPU kernel
variants and GPU transfer paths (forced on the CPU device), device-side flow validation,
float16 flows, device-resident arrays, pinned host arrays, and the packaged kernel sources.

The GPU paths are exercised on whatever device the suite runs on (PoCL in CI): the variant
kernels are built with ``-DGPU_VARIANT`` and the banded, pinned, two-queue transfers are
forced by treating the device as one with its own memory.  Each is checked against the numpy
reference (``tests/test_opencl.py``'s tolerance) and against the default path, bit for bit.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from test_opencl import (
    assert_matches_reference,
    discontinuous_flow,
    near_integer_flow,
    random_image,
    smooth_flow,
)

from clblur.errors import InputError
from clblur.opencl.constants import build_defines
from clblur.opencl.program import KERNEL_FILES, build, kernel_signatures, kernel_source
from clblur.request import make_plan

REPO = Path(__file__).resolve().parent.parent


# --- constants and signatures (no device needed) ---------------------------------------------

def test_shared_constants_are_only_defined_in_python():
    # every program of the package (the main one and the layered compositor)
    source = "\n".join(p.read_text() for p in sorted((REPO / "clblur" / "opencl").glob("*.cl")))
    for option in build_defines():
        name = option[2:].split("=")[0]
        assert re.search(rf"\b{name}\b", source), f"{name} is never used by the kernels"
        assert not re.search(rf"#\s*define\s+{name}\b", source), f"{name} defined in C too"


def test_signatures_parse_with_macros_expanded():
    sig = kernel_signatures(kernel_source())
    names = [a.name for a in sig["integrate_taps"]]
    assert names[:5] == ["lin", "tap_dx", "tap_dy", "tap_w", "ntaps"]
    assert names[-9:] == ["resp", "tables", "thresholds", "buckets", "out", "out_kind",
                          "channels", "cbase", "cg"]  # STORE_PARAMS, expanded
    assert not {"r0", "c0", "fw", "fh"} & set(names)  # dead arguments removed
    field = {a.name: a.dtype for a in sig["integrate_field"]}
    assert field["anchor"] is np.float32 and field["fixed_n"] is np.int32
    assert field["flow"] is None  # a buffer


# --- named launches --------------------------------------------------------------------------

@pytest.mark.opencl
def test_named_launch_checks_names_and_matches_the_drivers_argument_info(opencl):
    cl = opencl.pyopencl_module()
    rt = opencl.runtime(None)
    prog = rt.program(half=False)
    with pytest.raises(TypeError, match="unknown argument.*'nope'.*missing"):
        prog.run("linearise", rt.queue, (64, 1), (64, 1), nope=1)
    # the driver's own view of the parameters, where it offers one
    built = build(rt.context, kernel_source(), [*prog.options, "-cl-kernel-arg-info"])
    for name, params in prog.signatures.items():
        kernel = getattr(built, name)
        try:
            got = [kernel.get_arg_info(i, cl.kernel_arg_info.NAME)
                   for i in range(kernel.num_args)]
        except cl.Error:
            pytest.skip("the driver gives no kernel argument names")
        assert got == [a.name for a in params], name


# --- the GPU variants and transfer paths, forced on this device --------------------------------

def _cases(rng):
    yield make_plan(random_image(rng, np.uint8, 3), smooth_flow(rng), "exp")
    yield make_plan(random_image(rng, np.uint16, 5), discontinuous_flow(rng), "gamma:2.2",
                    anchor="start")
    yield make_plan(random_image(rng, np.float32, 3), smooth_flow(rng), "srgb", samples=7)
    yield make_plan(random_image(rng, np.uint8, 4), smooth_flow(rng), "exp",
                    weights=[1, 3, 2, 1])
    yield make_plan(random_image(rng, np.uint8, 3), (4.6, -2.3), "exp")
    yield make_plan(random_image(rng, np.uint8, 3), rng.random((5, 7)), "srgb")
    yield make_plan(random_image(rng, np.uint16, 3), (40.5, 3.0), "exp")  # wider than a tile
    yield make_plan(random_image(rng, np.float32, 3), near_integer_flow(rng), "exp")
    # the continuous exposure: per-pixel half-weight ends in the field kernels
    yield make_plan(random_image(rng, np.uint8, 3), smooth_flow(rng), "srgb",
                    exposure="continuous")
    yield make_plan(random_image(rng, np.uint16, 4), discontinuous_flow(rng), "exp",
                    anchor="end", exposure="continuous")
    yield make_plan(random_image(rng, np.uint8, 3), (9.0, 0.0), "srgb", anchor="start",
                    exposure="continuous")  # a box with half-weight ends
    yield make_plan(random_image(rng, np.float32, 3), (0.0, 14.0), "exp",
                    exposure="continuous")


@pytest.mark.opencl
def test_gpu_kernel_variants_match_the_reference_and_the_cpu_variants(opencl, rng):
    rt = opencl.runtime(None)
    for plan in _cases(rng):
        for half in (False, True):
            with rt.lock:
                gpu = opencl.run_plan(rt, plan, gpu=True, half=half)
                cpu = opencl.run_plan(rt, plan, gpu=False, half=half)
            assert np.array_equal(gpu, cpu)
            assert_matches_reference(_Fixed(gpu), plan)


@pytest.mark.opencl
@pytest.mark.parametrize("name", ["linear", "exp", "exp3", "gamma", "srgb", "table"])
def test_half_storage_of_the_gpu_variants_keeps_the_tolerance(opencl, rng, name):
    """GPU variants store uint8 exposures as half floats where the bound allows: the same
    sweep as test_opencl.test_every_response, saturation 1 and 2.5."""
    from test_opencl import RESPONSES

    rt = opencl.runtime(None)
    img = random_image(rng, np.uint8, 3)
    for motion in (smooth_flow(rng), discontinuous_flow(rng), (4.6, -2.3), rng.random((5, 7))):
        for sat in (1.0, 2.5):
            plan = make_plan(img, motion, RESPONSES[name], saturation=sat)
            with rt.lock:
                got = opencl.run_plan(rt, plan, gpu=True)
            assert_matches_reference(_Fixed(got), plan)


class _Fixed:
    """A 'backend' that returns a precomputed result (for assert_matches_reference)."""

    def __init__(self, out):
        self.out = out

    def blur(self, plan):
        return self.out


# Device linearisation of float32 images (docs/tolerances.md, "Linearisation"): within
# this error of the host's float64 inverse; full-scale and near-top values exact.  The
# relative error of exp2(g log2 v) grows with |g log2 v|; the absolute floor, far below any
# 16-bit code's exposure, covers the tiniest values (v = 2^-59 under gamma 1.8: 4.3e-6).
FLOAT_LINEARISATION_RTOL = 4e-6
FLOAT_LINEARISATION_ATOL = 1e-12


def _device_exposures(opencl, rt, plan) -> np.ndarray:
    from clblur.opencl.backend import upload_input

    cl = opencl.pyopencl_module()
    with rt.lock:
        src = upload_input(rt, plan)
        out = np.empty(plan.image.shape, np.float32)
        cl.enqueue_copy(rt.queue, out, src.buffer, is_blocking=True,
                        wait_for=[ev for band in src.ready for ev in band])
    return out


@pytest.mark.opencl
@pytest.mark.parametrize("saturation", [1.0, 1.7])
def test_float_images_are_linearised_on_the_device_like_the_host(opencl, saturation):
    from clblur.opencl.linearisation import linearise_float_image
    from clblur.pixels import full_scale_exposure, top_value
    from clblur.responses import Table

    rt = opencl.runtime(None)
    one = np.float32(1.0)
    values = np.concatenate([
        np.linspace(-0.2, 1.2, 30001, dtype=np.float32),       # negatives and past full scale
        one - np.arange(1, 300, dtype=np.float32) * np.float32(2.0 ** -24),  # up to 1 from below
        np.float32(2.0) ** -np.arange(0, 60, dtype=np.float32),  # down to tiny values
        [0.0, 0.04045, np.float32(0.04045 / 12.92), 1.0, 1e30]]).astype(np.float32)
    values = values[:values.size // 7 * 7]
    # a non-contiguous window (a tile), one band per row block, an odd width
    image = np.repeat(values.reshape(-1, 7, 1), 5, axis=2)[:, ::-1]
    table = Table([0.0, 0.1, 0.5, 1.0, 2.0], [0.0, 0.3, 0.7, 0.9, 1.0])
    for spec in ("linear", "exp", "exp:7", "gamma:2.2", "gamma:0.45", "srgb", table,
                 ["srgb", "exp", "gamma:1.8", table, "linear"]):
        plan = make_plan(image, (0.0, 0.0), spec, saturation=saturation)
        got = _device_exposures(opencl, rt, plan)
        want = linearise_float_image(image, plan.responses, saturation)
        np.testing.assert_allclose(got, want, rtol=FLOAT_LINEARISATION_RTOL,
                                   atol=FLOAT_LINEARISATION_ATOL,
                                   err_msg=str(spec))
        for c, r in enumerate(plan.responses):
            if not r.bounded:  # scene-linear values pass through, bit for bit
                assert np.array_equal(got[..., c], image[..., c])
                continue
            f32 = np.dtype(np.float32)
            full = np.float32(saturation * full_scale_exposure(r, f32))
            assert np.all(got[..., c][image[..., c] >= 1] == full)
            near = (image[..., c] > top_value(r, f32)) & (image[..., c] < 1)
            assert np.all(got[..., c][near] == np.float32(r.inverse(top_value(r, f32))))


@pytest.mark.opencl
def test_banded_pinned_transfers_on_two_queues_equal_the_shared_path(opencl, rng,
                                                                      monkeypatch):
    from clblur.opencl import transfers

    rt = opencl.runtime(None)
    monkeypatch.setattr(transfers, "MIN_BAND_ROWS", 8)  # 37 rows -> 4 bands
    shape = (37, 53)
    plans = [make_plan(random_image(rng, np.uint8, 3, shape), smooth_flow(rng, shape), "exp"),
             make_plan(random_image(rng, np.float32, 5, shape), (3.5, 1.0), "exp"),
             make_plan(random_image(rng, np.uint16, 3, shape), (12.0, 0.0), "exp")]
    with rt.lock:  # half=False as below (a GPU's default stores some intermediates as half)
        shared = [opencl.run_plan(rt, p, half=False) for p in plans]
    cl = opencl.pyopencl_module()
    monkeypatch.setattr(rt, "unified", False)
    monkeypatch.setattr(rt, "queues", (cl.CommandQueue(rt.context),))
    pinned = opencl.pinned_empty(plans[0].image.shape, np.uint8)
    pinned[...] = plans[0].image
    plans.append(make_plan(pinned, plans[0].motion, "exp"))  # uploaded without staging
    shared.append(shared[0])
    for plan, want in zip(plans, shared, strict=True):
        for gpu in (False, True):
            with rt.lock:
                got = opencl.run_plan(rt, plan, gpu=gpu, half=False)
            assert np.array_equal(got, want)
    assert "image" in rt.pinned and "flow" in rt.pinned  # staging kept for the next call


@pytest.mark.opencl
def test_video_bent_path_variants_and_transfers_give_the_same_bits(opencl, rng, monkeypatch):
    """clblur/opencl/bent_path.py with the GPU kernel variants and the banded transfers of a
    device with its own memory, forced on this device: the default path's bits."""
    from clblur.opencl import transfers
    from clblur.opencl.bent_path import run_bent

    rt = opencl.runtime(None)
    monkeypatch.setattr(transfers, "MIN_BAND_ROWS", 8)  # 37 rows -> 4 bands
    shape = (37, 53)
    first, second = smooth_flow(rng, shape), smooth_flow(rng, shape)
    plans = [make_plan(random_image(rng, np.uint8, 3, shape), (0.0, 0.0), "srgb"),
             make_plan(random_image(rng, np.uint16, 5, shape), (0.0, 0.0), "exp")]
    with rt.lock:
        want = [run_bent(rt, p, first, second, None) for p in plans]
    cl = opencl.pyopencl_module()
    monkeypatch.setattr(rt, "unified", False)
    monkeypatch.setattr(rt, "queues", (cl.CommandQueue(rt.context),))
    for plan, expected in zip(plans, want, strict=True):
        for gpu in (False, True):
            with rt.lock:
                got = run_bent(rt, plan, first, second, None, gpu=gpu)
            assert np.array_equal(got, expected)


# --- flow validation on the device, float16 flows ---------------------------------------------

@pytest.mark.opencl
@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_bad_flows_are_refused_with_the_same_message(opencl, rng, backend):
    import clblur

    img = random_image(rng, np.uint8, 3)
    flow = smooth_flow(rng)
    flow[3, 4, 0], flow[7, 52, 1], flow[36, 0] = np.nan, np.inf, (-np.inf, np.nan)
    with pytest.raises(ValueError, match=r"^flow field contains 4 NaN or infinite value\(s\)$"):
        clblur.blur(img, flow, backend=backend)
    flow = smooth_flow(rng)
    flow[0, 0, 1] = 1e6
    with pytest.raises(ValueError, match=r"contains 1 value\(s\) beyond \+-65536 px"):
        clblur.blur(img, flow, backend=backend)


@pytest.mark.opencl
def test_float16_flow_is_read_as_given(opencl, rng):
    import clblur

    img = random_image(rng, np.uint8, 3)
    flow16 = smooth_flow(rng, scale=9.0).astype(np.float16)
    plan = make_plan(img, flow16, "exp")
    assert plan.motion.flow.dtype == np.float16  # no host conversion
    got = clblur.blur(img, flow16, backend="opencl")
    assert np.array_equal(got, clblur.blur(img, flow16.astype(np.float32), backend="opencl"))
    assert_matches_reference(opencl, plan)


@pytest.mark.opencl
def test_device_sample_counts_equal_the_hosts_for_tiny_and_huge_vectors(opencl, rng,
                                                                         monkeypatch):
    from clblur.motion import sample_counts

    shape = (16, 40)
    flow = np.zeros(shape + (2,), np.float32)
    flow[0, :8] = [(1e-30, 0), (0, -1e-42), (3e-20, 4e-20), (4095.5, 0), (5000.25, 3.0),
                   (0.6, 0.8), (-3.0, 4.0), (1e-3, 0)]
    flow[1:] = rng.normal(0, 30, (shape[0] - 1, shape[1], 2))
    n = sample_counts(flow[..., 0], flow[..., 1])
    img = random_image(rng, np.float32, 1, shape)
    rt = opencl.runtime(None)
    if not rt.fp64:
        pytest.skip("device has no fp64: counts always come from the host")
    plan = make_plan(img, flow, "linear", anchor="start")
    on_device = opencl.blur(plan)
    monkeypatch.setattr(rt, "fp64", False)  # routes counts through the host buffer
    assert np.array_equal(opencl.blur(plan), on_device)
    monkeypatch.undo()
    assert n[0, 0] == n[0, 1] == n[0, 2] == 2 and n[0, 3] == 4097 and n[0, 4] == 5002
    # positions carry |offset| 2^-23 px of error, so compare the short vectors only
    short = np.tile(flow[:1, [0, 1, 2, 5, 6, 7]], (16, 7, 1))[:, :40]
    small = make_plan(img, short, "linear", anchor="start")
    assert_matches_reference(opencl, small)


# --- device-resident arrays and pinned host arrays -------------------------------------------

@pytest.mark.opencl
def test_device_arrays_in_and_out(opencl, rng):
    import pyopencl.array as cla

    import clblur

    rt = opencl.runtime(None)
    img = random_image(rng, np.uint8, 3)
    flow = smooth_flow(rng)
    want = clblur.blur(img, flow, backend="opencl")
    got = clblur.blur(cla.to_device(rt.queue, img), cla.to_device(rt.queue, flow))
    assert isinstance(got, cla.Array) and got.dtype == np.uint8
    assert np.array_equal(got.get(), want)
    gray = img[..., 0].copy()
    got = clblur.blur(cla.to_device(rt.queue, gray), (5.5, 2.0))
    assert np.array_equal(got.get(), clblur.blur(gray, (5.5, 2.0), backend="opencl"))
    bad = flow.copy()
    bad[1, 1, 0] = np.nan
    with pytest.raises(ValueError, match="1 NaN or infinite"):
        clblur.blur(cla.to_device(rt.queue, img), cla.to_device(rt.queue, bad))


@pytest.mark.opencl
@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_device_arrays_take_every_option_of_blur(opencl, rng, dtype):
    # a device flow was planned as the motion (0, 0): a continuous exposure then took one
    # sample and returned the input unblurred; a float image dropped the exposure
    import pyopencl.array as cla

    import clblur

    rt = opencl.runtime(None)
    img = random_image(rng, dtype, 3)
    flow = smooth_flow(rng)
    for exposure in ("frames", "continuous"):
        want = clblur.blur(img, flow, "srgb", exposure=exposure, backend="opencl")
        got = clblur.blur(cla.to_device(rt.queue, img), cla.to_device(rt.queue, flow), "srgb",
                          exposure=exposure).get()
        np.testing.assert_array_equal(got, want)
    assert not np.array_equal(want, clblur.blur(img, flow, "srgb", backend="opencl"))
    with pytest.raises(InputError, match="device array"):
        clblur.blur(cla.to_device(rt.queue, img), (3.0, 1.0), backend="numpy")


@pytest.mark.opencl
def test_pinned_empty_is_an_ordinary_array(opencl, rng):
    import clblur

    arr = opencl.pinned_empty((37, 53, 3), np.uint8)
    img = random_image(rng, np.uint8, 3)
    arr[...] = img
    assert np.array_equal(clblur.blur(arr, (3.0, 1.0), backend="opencl"),
                          clblur.blur(img, (3.0, 1.0), backend="opencl"))


# --- packaging ---------------------------------------------------------------------------------

def test_wheel_ships_the_kernel_sources(tmp_path):
    """A non-editable install finds the .cl files: build the wheel, load them from it."""
    src = tmp_path / "src"  # a copy: building in place would leave build/ in the checkout
    shutil.copytree(REPO / "clblur", src / "clblur",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps",
                          "--no-build-isolation", "-q", "-w", str(tmp_path)],
                         capture_output=True, text=True, timeout=300)
    if res.returncode != 0 and "No module named" in res.stderr:
        pytest.skip(f"cannot build a wheel here: {res.stderr.strip()[-200:]}")
    assert res.returncode == 0, res.stderr
    wheel = next(tmp_path.glob("clblur-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        assert {f"clblur/opencl/{f}" for f in KERNEL_FILES} <= names
        z.extractall(tmp_path / "site")
    site = str(tmp_path / "site")
    code = (f"import clblur.opencl.program as p; assert p.__file__.startswith({site!r}); "
            "print(len(p.kernel_source()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path, env={"PYTHONPATH": str(tmp_path / "site")}, timeout=60)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) == len(kernel_source())


@pytest.mark.opencl
@pytest.mark.parametrize("spec", ["exp", "gamma:2.2", "linear"])
def test_box_code_grid_equals_the_search(opencl, rng, monkeypatch, spec):
    """uint8 boxes give the same codes through the code grid as through the bucket search
    (gamma: dark values fall in cells holding boundaries and take the search), with one grid
    row for all channels or one per channel."""
    from clblur.opencl import quantisation
    from clblur.opencl.taps import space_invariant_taps

    img = random_image(rng, np.uint8, 3)
    img[:, : img.shape[1] // 2] //= 8  # dark half: dense boundaries for gamma
    plans = [make_plan(img, (6.0, 0.0), spec), make_plan(img, (0.0, 8.0), spec),
             make_plan(img[..., :1].copy(), (6.0, 0.0), spec),
             make_plan(img, (0.0, 4.0), [spec, "srgb", "exp:3"])]  # a grid row per channel
    assert all(space_invariant_taps(plan).box() for plan in plans)  # running sums
    rt = opencl.runtime(None)
    with rt.lock:
        grid = [opencl.run_plan(rt, plan) for plan in plans]
        monkeypatch.setattr(quantisation, "quantisation_grid", lambda t: None)
        search = [opencl.run_plan(rt, plan) for plan in plans]
    for a, b in zip(grid, search, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.opencl
@pytest.mark.parametrize("length", [1, 2, 3, 5, 24, 60, 130, 1100])
def test_boxes_of_every_length_match_the_reference(opencl, rng, monkeypatch, length):
    """Running sums whose values are kept until they leave the box (integrate_box_codes; past
    BOX_RING taps, read twice), including boxes longer than the line (clamped values entering
    and leaving), with equal weights and with the continuous exposure's half-weight ends; and
    the same with no ring, as a GPU builds it, on whatever device runs the tests."""
    from clblur.opencl import device as device_module
    from clblur.opencl.taps import space_invariant_taps

    img = random_image(rng, np.uint8, 3)
    plans = []
    for motion in ((float(length - 1), 0.0), (0.0, float(length - 1))):
        for exposure in ("frames", "continuous"):
            plans.append(make_plan(img, motion, "exp", anchor="start", exposure=exposure))
            assert length == 1 or space_invariant_taps(plans[-1]).box()
    for ring in (None, 1):
        if ring is not None:  # a new build option, a program of its own
            monkeypatch.setattr(device_module, "BOX_RING_CPU", ring)
        for plan in plans:
            assert_matches_reference(opencl, plan)


@pytest.mark.opencl
def test_a_gpu_keeps_no_box_ring(opencl):
    """A GPU reserves a thread's private memory for every thread of the grid: the CPU
    devices' ring (BOX_RING_CPU taps of two long16, 256 KiB) made NVIDIA's driver refuse
    every box launch (OUT_OF_HOST_MEMORY, H100).  Off a CPU the ring stays within 2 KiB."""
    from types import SimpleNamespace

    from clblur.opencl.device import box_ring

    cl = opencl.pyopencl_module()
    rt = opencl.runtime(None)
    for variant in (False, True):
        assert f"-DBOX_RING={box_ring(rt.device)}" in rt.build_options(False, variant)
    for kind in (cl.device_type.GPU, cl.device_type.ACCELERATOR):
        assert 2 * 128 * box_ring(SimpleNamespace(type=kind)) <= 2048
    assert box_ring(SimpleNamespace(type=cl.device_type.CPU)) > 16
