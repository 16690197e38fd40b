#!/usr/bin/env bash
# The checks a GPU machine is for, in one run (a lent machine's time is short):
#   1. the kernel tests on its OpenCL device (pytest --opencl-only: every test that uses the
#      device, each against the float64 numpy reference at docs/tolerances.md's bounds);
#      CHECK_TESTS (default tests/) narrows them to the files a change touched;
#   2. the occlusion path's cost against the plain gather (bench/results_occlusion_gpu.md),
#      and the same with the layers built on the host (CLBLUR_LAYER_BUILD=host: the baseline
#      on the same machine);
#   3. where a layered call's time goes (bench/profile_occlusion.py, both scenes, both builds);
#   4. the GPU section of the throughput bench (bench/results_gpu.md; the CPU-style table of
#      that run goes to OUTDIR, not over bench/results.md, which is this VM's);
#   5. what the OpenCL compiler says about each program (bench/compiler_output.py).
# Usage: bench/gpu_check.sh OUTDIR   (from the repository root; CLBLUR_DEVICE picks the device,
# else the first GPU). Writes 8 files to OUTDIR (a lent machine returns at most 8): info.txt
# (device and compiler output), tests.txt, results_occlusion_gpu.md, occlusion_host.txt,
# profile_panning.md, profile_static.md, results_blur.md, results_gpu.md.
set -u
out=${1:?usage: bench/gpu_check.sh OUTDIR}
mkdir -p "$out"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
python -m clblur.cli info 2>&1 | tee "$out/info.txt"
workers=$(python -c "import os; print(min(8, os.cpu_count() or 1))")
xdist=$(python -c "import xdist" 2>/dev/null && echo "-n $workers")
# shellcheck disable=SC2086  # $xdist is empty or two words; CHECK_TESTS may name several
timeout "${CHECK_TESTS_TIMEOUT:-330}" python -m pytest -q --opencl-only -p no:cacheprovider \
    $xdist ${CHECK_TESTS:-tests/} >"$out/tests.txt" 2>&1
echo "tests: exit $? (tail of $out/tests.txt)"; tail -n 25 "$out/tests.txt"
python bench/bench_occlusion.py --backend opencl --timing-only --repeat 15 \
    --results bench/results_occlusion_gpu.md && cp bench/results_occlusion_gpu.md "$out/"
CLBLUR_LAYER_BUILD=host python bench/bench_occlusion.py --backend opencl --timing-only \
    --repeat 15 --results /tmp/results_occlusion_host.md 2>&1 | tee "$out/occlusion_host.txt"
for scene in panning static; do
    for build in device host; do
        echo "### $scene background, CLBLUR_LAYER_BUILD=$build"
        CLBLUR_LAYER_BUILD=$build python bench/profile_occlusion.py --scene "$scene"
    done 2>&1 | tee "$out/profile_$scene.md"
done
python bench/bench_blur.py --skip-remap --repeats 5 --out "$out/results_blur.md" \
    --gpu-out bench/results_gpu.md && cp bench/results_gpu.md "$out/"
python bench/compiler_output.py 2>&1 | tee -a "$out/info.txt"
