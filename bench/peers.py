"""Peers for bench_blur.py with clblur's semantics (linearise -> integrate -> forward -> round).

* ``numba_field``: the strongest CPU gather we could write, numba ``prange`` over rows, float32,
  the same per-pixel N, positions ``p - v (j - a (N-1)) / (N-1)``, bilinear, clamp-to-edge; the
  image is linearised by ``cv2.LUT`` and the result forward-mapped by a dense table.
* ``torch_field``: ``torch.nn.functional.grid_sample`` (bilinear, border padding,
  ``align_corners=True``) once per sample index j, accumulated with the per-pixel weights
  ``[j < N] / N``; on the CPU, and on CUDA where present (end-to-end and device-resident).
* ``opencv_box``: the all-OpenCV box pipeline for the exp response:
  ``cv2.LUT`` (to ``-k E``) -> ``cv2.blur`` on float32 -> ``cv2.exp`` ->
  ``cv2.convertScaleAbs(alpha=-255, beta=255)``, i.e. ``rint(255 (1 - exp(-k mean E)))``.
* ``layers_apart_then_over``: the compositor's way with a multi-layer render and no
  per-sample occlusion: every layer blurred alone (``clblur.blur(..., alpha=True)`` in linear
  light, its vectors extended from the pixels it covers at least half, as
  ``clblur.render_layers`` extends them, so its streak leaves its silhouette), then merged
  front to back with ``over``; the peer of ``clblur.blur_layers`` (``bench_render_layers.py``).
Each peer that is not installed is skipped (``available`` says why).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from clblur.motion import sample_counts
from clblur.pixels import linearisation_table
from clblur.responses import Exp, response

__all__ = ["available", "best_time", "layers_apart_then_over", "numba_field", "opencv_box",
           "torch_cuda_field", "torch_field"]


def available(name: str) -> str | None:
    """None if the peer's package imports, else the reason."""
    try:
        __import__(name)
    except Exception as e:  # noqa: BLE001 - any import failure skips the peer
        return f"{name} not importable ({type(e).__name__}: {e})"
    return None


def _lin(img: np.ndarray, spec: str) -> np.ndarray:
    lut = linearisation_table(response(spec), np.uint8, 1.0).astype(np.float32)
    return cv2.LUT(img, lut)


def _counts(flow: np.ndarray) -> np.ndarray:
    return sample_counts(flow[..., 0], flow[..., 1])


_NUMBA = None


def _numba_kernel():
    global _NUMBA
    if _NUMBA is None:
        import numba

        @numba.njit(parallel=True, fastmath=False, cache=False)
        def gather(lin, flow, counts, anchor, scale, table, out):
            h, w, c = lin.shape
            for r in numba.prange(h):
                acc = np.zeros(c, np.float32)
                for col in range(w):
                    n = counts[r, col]
                    n1 = np.float32(n - 1)
                    den = max(n1, np.float32(1.0))
                    sx = flow[r, col, 0] / den
                    sy = flow[r, col, 1] / den
                    a_n1 = np.float32(anchor) * n1
                    acc[:] = 0
                    for j in range(n):
                        t = np.float32(j) - a_n1
                        x = np.float32(col) - sx * t
                        y = np.float32(r) - sy * t
                        x0f, y0f = np.floor(x), np.floor(y)
                        fx, fy = x - x0f, y - y0f
                        x0, y0 = int(x0f), int(y0f)
                        xa, xb = min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1)
                        ya, yb = min(max(y0, 0), h - 1), min(max(y0 + 1, 0), h - 1)
                        for k in range(c):
                            top = lin[ya, xa, k] * (1 - fx) + lin[ya, xb, k] * fx
                            bottom = lin[yb, xa, k] * (1 - fx) + lin[yb, xb, k] * fx
                            acc[k] += top * (1 - fy) + bottom * fy
                    for k in range(c):
                        idx = acc[k] / np.float32(n) * scale + np.float32(0.5)
                        i = min(max(int(idx), 0), table.size - 1)
                        out[r, col, k] = table[i]

        _NUMBA = gather
    return _NUMBA


def numba_field(img, flow, anchor, forward, spec="exp"):
    """The numba prange gather; ``forward`` is bench_blur.ForwardLut (65536-entry table)."""
    lin = _lin(img, spec)
    out = np.empty_like(img)
    _numba_kernel()(lin, flow, _counts(flow), np.float32(anchor), np.float32(forward.scale),
                    forward.table, out)
    return out


def warm_numba(img, flow, anchor, forward, spec="exp"):
    """Compile the numba kernel on a small crop (compilation is not what is timed)."""
    numba_field(np.ascontiguousarray(img[:16, :16]), np.ascontiguousarray(flow[:16, :16]),
                anchor, forward, spec)


def _torch_accumulate(torch, lin_t, flow_t, n_t, anchor):
    """grid_sample once per sample index: lin_t (1, C, H, W), flow_t (H, W, 2), n_t (H, W)."""
    import torch.nn.functional as F

    h, w = flow_t.shape[:2]
    dev = lin_t.device
    yy, xx = torch.meshgrid(torch.arange(h, device=dev, dtype=torch.float32),
                            torch.arange(w, device=dev, dtype=torch.float32), indexing="ij")
    n1 = (n_t - 1).to(torch.float32)
    den = torch.clamp(n1, min=1.0)
    sx, sy = flow_t[..., 0] / den, flow_t[..., 1] / den
    a_n1 = anchor * n1
    inv_n = 1.0 / n_t.to(torch.float32)
    acc = torch.zeros_like(lin_t)
    for j in range(int(n_t.max())):
        t = j - a_n1
        gx = (xx - sx * t) * (2.0 / max(w - 1, 1)) - 1.0
        gy = (yy - sy * t) * (2.0 / max(h - 1, 1)) - 1.0
        grid = torch.stack([gx, gy], -1)[None]
        sample = F.grid_sample(lin_t, grid, mode="bilinear", padding_mode="border",
                               align_corners=True)
        acc += sample * torch.where(j < n_t, inv_n, 0.0)[None, None]
    return acc


def _torch_forward(torch, acc, forward):
    idx = torch.clamp(acc * float(forward.scale) + 0.5, 0, 65535).to(torch.int64)
    table = torch.as_tensor(forward.table, device=acc.device)
    return table[idx]


def torch_field(img, flow, anchor, forward, spec="exp"):
    """torch grid_sample on the CPU (all threads torch uses)."""
    import torch

    lin = torch.from_numpy(_lin(img, spec)).permute(2, 0, 1)[None].contiguous()
    acc = _torch_accumulate(torch, lin, torch.from_numpy(flow),
                            torch.from_numpy(_counts(flow)), anchor)
    out = _torch_forward(torch, acc, forward)
    return out[0].permute(1, 2, 0).contiguous().numpy()


def torch_cuda_field(img, flow, anchor, forward, spec="exp", resident=False):
    """torch grid_sample on CUDA.  End-to-end (numpy in, numpy out) unless ``resident``:
    then returns a callable that runs on tensors already on the device (timed by the
    caller, synchronised)."""
    import torch

    dev = torch.device("cuda")
    lut = torch.as_tensor(linearisation_table(response(spec), np.uint8, 1.0).astype(
        np.float32), device=dev)
    counts = _counts(flow)

    def run(img_t, flow_t, n_t):
        lin = lut[img_t.to(torch.int64)].permute(2, 0, 1)[None]
        acc = _torch_accumulate(torch, lin, flow_t, n_t, anchor)
        return _torch_forward(torch, acc, forward)[0].permute(1, 2, 0)

    if resident:
        args = (torch.as_tensor(img, device=dev), torch.as_tensor(flow, device=dev),
                torch.as_tensor(counts, device=dev))

        def once():
            out = run(*args)
            torch.cuda.synchronize()
            return out
        return once
    out = run(torch.as_tensor(img, device=dev), torch.as_tensor(flow, device=dev),
              torch.as_tensor(counts, device=dev))
    return out.cpu().numpy()


def opencv_box(img, length: int, spec="exp"):
    """All-OpenCV horizontal box of ``length`` (centred) under the exp response."""
    r = response(spec)
    assert isinstance(r, Exp)
    neg = (-r.k * linearisation_table(r, np.uint8, 1.0)).astype(np.float32)
    lin = cv2.LUT(img, neg)
    acc = cv2.blur(lin, (length, 1), borderType=cv2.BORDER_REPLICATE)
    e = cv2.exp(acc)
    return cv2.convertScaleAbs(e, alpha=-255.0, beta=255.0)


def best_time(fn, repeats: int):
    """Fastest wall time of ``fn`` (which must synchronise any device work) after one warm-up."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def layers_apart_then_over(layers, spec: str = "srgb", backend: str = "auto",
                           exposure: str = "frames") -> np.ndarray:
    """``layers`` as ``clblur.blur_layers`` takes them (nearest first, ``(image, flow)``
    straight): each blurred alone (with ``exposure``, ``clblur.blur``'s), then ``over`` front
    to back in linear light; the result in the layers' dtype and alpha convention."""
    from scipy.ndimage import distance_transform_edt

    import clblur
    from clblur.reference import finish, linearise
    from clblur.request import make_plan

    acc = plan = None
    for image, flow in layers:
        plan = make_plan(image, flow, spec, alpha=True)
        lin = linearise(plan).astype(np.float32)  # premultiplied linear light, coverage
        solid = lin[..., -1] >= 0.5
        if not solid.any():
            solid = lin[..., -1] > 0
        flow = np.asarray(flow, np.float32)
        if solid.any():
            idx = distance_transform_edt(~solid, return_indices=True, return_distances=False)
            flow = flow[idx[0], idx[1]]
        out = clblur.blur(lin, flow, "linear", alpha=True, backend=backend,
                          exposure=exposure).astype(np.float64)
        acc = out if acc is None else acc + (1.0 - acc[..., -1:]) * out
    return finish(acc, plan)
