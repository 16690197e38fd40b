"""What the OpenCL compiler says about each of clblur's programs on a device.

pyopencl only warns "Non-empty compiler output encountered" unless PYOPENCL_COMPILER_OUTPUT=1;
this script sets it, builds every program a blur can use (the main program in its half and
float variants, the layered compositor, the layer-building kernels of both builds) by running
small blurs, and prints each distinct message once.  A build served from a cache prints
nothing, so pyopencl's cache and NVIDIA's (``CUDA_CACHE_DISABLE``) are turned off here.
Uncached, NVIDIA's compiler takes minutes for all of them (a 90 s limit on an H100 was not
enough, 2026-11-26): each blur's messages are printed as soon as it returns.

Run:  python bench/compiler_output.py [--device SELECTOR]
"""

from __future__ import annotations

import argparse
import os
import warnings

os.environ["PYOPENCL_COMPILER_OUTPUT"] = "1"
os.environ["PYOPENCL_NO_CACHE"] = "1"
os.environ["CUDA_CACHE_DISABLE"] = "1"

import numpy as np  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    args = ap.parse_args()

    import clblur

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    flow = np.zeros((64, 96, 2), np.float32)
    flow[16:48, 24:60] = (9.0, 2.0)
    depth = np.where(flow[..., 0] > 0, 5.0, 50.0)
    seen: list[str] = []

    def report(what: str, caught: list) -> None:
        for w in caught:
            text = str(w.message)
            if text not in seen:
                seen.append(text)
                print(f"--- {what}\n{text}", flush=True)
        caught.clear()

    runs = [(f"{build} build, {label}", build, kw)
            for build in ("device", "host")
            for label, kw in (("plain", {}), ("depth", dict(depth=depth)),
                              ("speed", dict(depth="speed")))]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for what, build, kw in runs:
            os.environ["CLBLUR_LAYER_BUILD"] = build
            clblur.blur(img, flow, "srgb", backend="opencl", device=args.device, **kw)
            report(what, caught)
        clblur.blur(img, (7.0, 3.0), "srgb", backend="opencl", device=args.device)
        report("uniform motion", caught)
        clblur.blur(img.astype(np.float32) / 255, flow, "srgb", backend="opencl",
                    device=args.device)
        report("float image", caught)
    print(f"{len(seen)} distinct compiler message(s)", flush=True)

if __name__ == "__main__":
    main()
