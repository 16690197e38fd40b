"""Forward responses packed for response.cl, four channels per kernel pass.

Conventions
-----------
* A channel's response is ``RESP_STRIDE`` float32 values ``[kind, parameter, table offset,
  table length]``; kind codes are ``clblur.responses.KIND_CODES``.  exp: parameter = k;
  gamma: parameter = 1/gamma; table: ``tables[offset .. offset+len)`` holds exposures, the next
  ``len`` floats the values.
"""

from __future__ import annotations

import numpy as np

from clblur.opencl.constants import GROUP, RESP_STRIDE
from clblur.responses import KIND_CODES, Gamma, Response, Table

__all__ = ["channel_groups", "four_channels", "response_params"]


def channel_groups(channels: int) -> list[tuple[int, int]]:
    """``(first channel, count)`` of each kernel pass."""
    return [(c, min(GROUP, channels - c)) for c in range(0, channels, GROUP)]


def four_channels(group):
    """A channel group padded to four by repeating its first response (the kernels read
    per-channel tables for all four lanes; the padding lanes are never stored)."""
    group = list(group)
    return group + [group[0]] * (GROUP - len(group))


def response_params(responses: tuple[Response, ...] | list[Response]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Pack channels' responses for clblur/opencl/response.cl: a channel group (up to four)
    for the forward response, or every channel of an image for its inverse.

    Returns (params: float32[max(GROUP, channels) * RESP_STRIDE], tables: float32, at least
    one element).
    """
    params = np.zeros(max(GROUP, len(responses)) * RESP_STRIDE, dtype=np.float32)
    tables: list[np.ndarray] = []
    offset = 0
    for k, r in enumerate(responses):
        p = 0.0
        if isinstance(r, Gamma):
            p = 1.0 / r.gamma
        elif r.kind == "exp":
            p = r.device_params()[0]
        start, length = 0, 0
        if isinstance(r, Table):
            start, length = offset, r.exposure.size
            tables += [r.exposure, r.value]
            offset += 2 * length
        params[k * RESP_STRIDE:(k + 1) * RESP_STRIDE] = (KIND_CODES[r.kind], p, start, length)
    flat = np.concatenate(tables).astype(np.float32) if tables else np.zeros(1, np.float32)
    return params, flat


