#!/usr/bin/env bash
# Install clblur and a working OpenCL CPU device on a fresh Debian/Ubuntu machine.
# Idempotent: a second run only re-installs the package.
#
# Why Debian's PoCL: the pip package pocl-binary-distribution lists a device on this kind of
# machine but cannot compile kernels ("unknown target CPU 'generic'"); Debian's pocl-opencl-icd
# works with the pyopencl wheel.
set -euo pipefail
cd "$(dirname "$0")"

if [ ! -e /etc/OpenCL/vendors/pocl.icd ]; then
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends \
    pocl-opencl-icd ocl-icd-libopencl1 clinfo >/dev/null
fi

# pyproject.toml's [build-system] requires, in this environment as well: the packaging test
# (tests/test_opencl_host_paths.py) builds a wheel without build isolation, and a fresh
# machine's setuptools may be older than 68 and lack `wheel`
python3 -m pip install -q --disable-pip-version-check "setuptools>=68" wheel
python3 -m pip install -q --disable-pip-version-check ".[all]"
python3 -c "from clblur import opencl; ok, why = opencl.usable(None); \
print('OpenCL device:', opencl.current_device() if ok else 'NONE (' + why + ')')"
