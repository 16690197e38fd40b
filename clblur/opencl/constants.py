"""Every constant the host code and the kernels share, defined once, here.

The kernels (``*.cl`` beside this module) never spell these numbers: ``build_defines`` turns
them into ``-D`` build options, so a change here reaches both sides.

Conventions
-----------
* ``LANES``: consecutive pixels of a row per work-item of the CPU kernels (vector lanes);
  ``FIELD_LANES`` those of the CPU field kernel (one float16 per channel plane).
* ``GROUP``: channels per kernel pass (the RGBA-interleaved intermediate).
* ``RESP_STRIDE``: floats per channel in the packed forward-response array
  (``[kind, parameter, table offset, table length]``); kind codes are
  ``clblur.responses.KIND_CODES``.
* ``QHEAD``: header length of the quantisation bucket table
  (``[shift, base, bucket count, steps, threshold row stride]``).
* ``GRID_SEARCH``: flag of a uint8 code-grid cell that holds a code boundary (the kernel
  searches there; clblur/opencl/quantisation.py ``quantisation_grid``).
* Input kinds (what the image buffer holds) and output kinds (what the store writes).
* ``FLOW_LIMIT`` (``clblur.motion``): the largest flow component the kernels accept.
* ``BOX_RING_CPU`` / ``BOX_RING_GPU``: taps whose values a work-item of
  ``integrate_box_codes`` keeps in a private ring (``clblur.opencl.device.box_ring`` picks
  one by the device's type).
"""

from __future__ import annotations

import numpy as np

from clblur.motion import FLOW_LIMIT
from clblur.responses import KIND_CODES

__all__ = ["BOX_RING_CPU", "BOX_RING_GPU", "FIELD_LANES", "GROUP", "GRID_SEARCH", "IN_F32",
           "IN_KINDS", "IN_U8", "IN_U16", "LANES", "LAYERED_MAXK", "OUT_F32", "OUT_KINDS",
           "OUT_U8", "OUT_U16", "QHEAD", "RESP_STRIDE", "build_defines"]

LANES = 8
FIELD_LANES = 16
# layers one work-item of the layered compositor (layered.cl) holds in registers
LAYERED_MAXK = 8
GROUP = 4
RESP_STRIDE = 4
QHEAD = 5
GRID_SEARCH = 0x100  # uint8 code grid: flag of a cell that holds a code boundary
# A box work-item keeps up to BOX_RING taps' values (two long16, 128 bytes a tap) until they
# leave the box, so each step reads one pixel per line instead of two.  CPU devices: 1024 taps,
# 256 KiB of a thread's stack (boxes of 25 - 513 taps 1.2x on PoCL, 2026-11-23).  Other
# devices: none kept (1), each value read twice: a GPU reserves private memory per thread for
# the whole grid, and NVIDIA's driver refused the 1024-tap ring at launch (OUT_OF_HOST_MEMORY
# on an H100, 2026-11-26, after the GPU variant's value had been set to the CPU's).
BOX_RING_CPU = 1024
BOX_RING_GPU = 1

IN_U8, IN_U16, IN_F32 = 0, 1, 2
IN_KINDS = {np.dtype(np.uint8): IN_U8, np.dtype(np.uint16): IN_U16}  # float inputs: IN_F32

OUT_U8, OUT_U16, OUT_F32 = 0, 1, 2
# float64 outputs are computed in float32 and widened on the host
OUT_KINDS = {np.dtype(np.uint8): OUT_U8, np.dtype(np.uint16): OUT_U16,
             np.dtype(np.float32): OUT_F32, np.dtype(np.float64): OUT_F32}


def build_defines() -> tuple[str, ...]:
    """``-DNAME=value`` options for every shared constant (sorted: a stable cache key)."""
    values = {"LANES": LANES, "FIELD_LANES": FIELD_LANES, "GROUP": GROUP,
              "RESP_STRIDE": RESP_STRIDE, "QHEAD": QHEAD,
              "MAXK": LAYERED_MAXK, "GRID_SEARCH": GRID_SEARCH,
              "IN_U8": IN_U8, "IN_U16": IN_U16, "IN_F32": IN_F32,
              "OUT_U8": OUT_U8, "OUT_U16": OUT_U16, "OUT_F32": OUT_F32}
    values.update({f"KIND_{name.upper()}": code for name, code in KIND_CODES.items()})
    values["FLOW_LIMIT"] = f"{FLOW_LIMIT!r}f"
    return tuple(f"-D{k}={v}" for k, v in sorted(values.items()))
