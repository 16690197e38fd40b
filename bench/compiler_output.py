"""What the OpenCL compiler says about each of clblur's programs on a device.

pyopencl only warns "Non-empty compiler output encountered" unless PYOPENCL_COMPILER_OUTPUT=1;
this script sets it, builds every program a blur can use (the main program in its half and
float variants, the layered compositor, the layer-building transforms) by running small
blurs, and prints each distinct message once.

Run:  python bench/compiler_output.py [--device SELECTOR]
"""

from __future__ import annotations

import argparse
import os
import warnings

os.environ["PYOPENCL_COMPILER_OUTPUT"] = "1"

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
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for kw in (dict(), dict(depth=depth), dict(depth="speed")):
            clblur.blur(img, flow, "srgb", backend="opencl", device=args.device, **kw)
        clblur.blur(img, (7.0, 3.0), "srgb", backend="opencl", device=args.device)
        clblur.blur(img.astype(np.float32) / 255, flow, "srgb", backend="opencl",
                    device=args.device)
        for w in caught:
            text = str(w.message)
            if text not in seen:
                seen.append(text)
    print(f"{len(seen)} distinct compiler message(s)")
    for text in seen:
        print("-" * 72)
        print(text)


if __name__ == "__main__":
    main()
