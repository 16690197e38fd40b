#!/usr/bin/env bash
# The checks a GPU machine is for, in one run (a lent machine's time is short):
#   1. the kernel tests on its OpenCL device (pytest --opencl-only: every test that uses the
#      device, each against the float64 numpy reference at docs/tolerances.md's bounds);
#   2. the occlusion path's cost against the plain gather (bench/results_occlusion_gpu.md);
#   3. where a layered call's time goes (bench/profile_occlusion.py, both scenes).
# Usage: bench/gpu_check.sh OUTDIR   (from the repository root; CLBLUR_DEVICE picks the device,
# else the first GPU). Writes info.txt, tests.txt, profile_*.md and the results file to OUTDIR.
set -u
out=${1:?usage: bench/gpu_check.sh OUTDIR}
mkdir -p "$out"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
python -m clblur.cli info 2>&1 | tee "$out/info.txt"
workers=$(python -c "import os; print(min(8, os.cpu_count() or 1))")
xdist=$(python -c "import xdist" 2>/dev/null && echo "-n $workers")
# shellcheck disable=SC2086  # $xdist is empty or two words
timeout 330 python -m pytest -q --opencl-only -p no:cacheprovider $xdist tests/ \
    >"$out/tests.txt" 2>&1
echo "tests: exit $? (tail of $out/tests.txt)"; tail -n 25 "$out/tests.txt"
python bench/bench_occlusion.py --backend opencl --timing-only --repeat 15 \
    --results bench/results_occlusion_gpu.md && cp bench/results_occlusion_gpu.md "$out/"
for scene in panning static; do
    python bench/profile_occlusion.py --scene "$scene" | tee "$out/profile_$scene.md"
done
