"""``clblur info``: versions and OpenCL devices."""

from __future__ import annotations

import argparse
import platform

__all__ = ["register", "run"]


def register(sub) -> None:
    p = sub.add_parser("info", help="versions and OpenCL devices")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    import clblur

    print(f"clblur {clblur.__version__}  python {platform.python_version()}  "
          f"numpy {np.__version__}")
    try:
        import pyopencl

        print(f"pyopencl {pyopencl.VERSION_TEXT}")
    except ImportError as e:
        print(f"pyopencl: not importable ({e})")
        return 0
    from clblur import opencl

    found = opencl.devices()
    if not found:
        print("OpenCL devices: none found")
    for d in found:
        state = "builds and runs kernels" if d["works"] else f"UNUSABLE: {d['error']}"
        print(f"[{d['index']}] {d['platform']} / {d['device']} ({d['type']}, {d['version']}, "
              f"fp64={'yes' if d['fp64'] else 'no'}): {state}")
    ok, why = opencl.usable(None)
    print(f"default device: {opencl.current_device() if ok else 'none (' + why + ')'}")
    return 0
