"""Layer labels of a float depth map on the OpenCL device, equal to the host's.

:func:`layer_labels` is ``clblur.layering.layer_labels`` (``rule="depth"``, float depth) with
the O(pixels) work on the device and the int32 result identical.

Conventions
-----------
* Device (``labels.cl``): inverse depth, the continuity joins of ``layering._continuous`` in
  float64 with contraction off (numpy's operations one for one), the connected components of
  the joined 4-neighbour grid (union-find: per tile in local memory, then across the seams
  with ``atomic_min``; the root is each component's smallest flat index) numbered in raster
  order of their first pixel (a prefix sum over root bits), as ``layering._components``
  numbers them.  It also compacts what the rest needs: the pairs of neighbours in different
  components (edge records), per-run sums for each component's pixel count, non-sliver count
  and inverse-depth sum, and the count of invalid pixels.  At the end it maps the host's
  component -> layer table to the labels image.
* Host (numpy on the compact records only, O(boundary)): ``depth_components``' sliver merge,
  ``order_components``' medians and topological order and ``layer_labels``' cut, the same
  formulas on the same values (the log-depths of the boundary pixels only, numpy's log).
* The sliver merge compares components' mean inverse depths.  The device's sums round in
  another order than numpy's raster-order ``bincount``; both are within ``(count + 1) * 2^-53``
  of the exact mean (relative; all terms >= 0), so where two compared means lie further apart
  than twice that (with margin), they order the same way.  Where they do not (two surfaces at
  one depth next to one sliver), the component image is downloaded and the means are taken
  with the reference's own ``bincount``: exact either way.
* Invalid depth (NaN, -inf, <= 0) is found on the device; the host then raises
  ``layering._inverse_depth``'s error (the same one-line message).
* Served by the host function: integer orders, ``rule != "depth"``, maps that are not 2-D or
  are empty, float types other than float32 / float64 (widened as the host does), more than
  2^30 pixels, and devices without fp64.
* Program build and caching as ``clblur.opencl.layered``: built once per runtime and options.
  Buffers are the runtime's reused roles, so a call holds ``rt.lock`` from the upload to the
  labels' download.  A view of rows (``order[crop]``) goes to a device with its own memory in
  one rectangular copy, not through a contiguous host copy first.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np

from clblur import layering
from clblur.layering import DEPTH_TAU, MAX_LAYERS
from clblur.opencl.device import pyopencl_module
from clblur.opencl.program import Program

__all__ = ["MAX_PIXELS", "TILE", "WG", "layer_labels", "surface_components"]

TILE = 16  # side of the union-find tiles (labels_tiles: TILE^2 = 256 work-items, local memory)
WG = 256  # work-items of the 1-D groups (a multiple of 32: root bits are 32 to a word)
MAX_PIXELS = 1 << 30  # edge codes 2 p + 1, flat indices and counts stay in int32
PREFIX = 4096  # records read with the counters, before their count is known (one wait)
_U = 2.0 ** -53  # unit roundoff of float64


def _program(rt, depth_type: str) -> Program:
    """The labels program for ``depth_type`` (``float`` or ``double``) input, built once per
    runtime and options (kept in the runtime's program cache, keyed by its build options)."""
    return rt.built(("labels.cl",), f"-DDEPTH_T={depth_type}", f"-DLABELS_TILE={TILE}",
                    f"-DLABELS_WG={WG}")


def _padded(n: int, m: int) -> int:
    return -(-n // m) * m


def layer_labels(order: np.ndarray, max_layers: int = MAX_LAYERS, rule: str = "depth",
                 device: str | None = None) -> np.ndarray:
    """Layer index per pixel (0 = nearest, int32): ``clblur.layering.layer_labels`` with a
    float depth's surfaces found on the OpenCL device, the result equal to the host's.

    Integer orders, ``rule="speed"`` (or any rule but ``"depth"``), 1-D or other non 2-D
    orders and the cases of the module Conventions simply call the host function.

    Parameters
    ----------
    order : numpy.ndarray
        H x W ordering signal; here a float depth (> 0, +inf the sky).
    max_layers : int
        At most this many layers (``layering.MAX_LAYERS``).
    rule : str
        ``"depth"`` (continuous surfaces) or ``"speed"`` (host).
    device : str, optional
        OpenCL device selector (``clblur.opencl.device``).

    Returns
    -------
    numpy.ndarray
        int32, the shape of ``order``: ``layering.layer_labels(order, max_layers, rule)``.

    Raises
    ------
    ValueError
        As the host function: NaN, -inf or values <= 0 in a float depth (its message).
    """
    order = np.asarray(order)
    if (np.issubdtype(order.dtype, np.integer) or rule != "depth" or order.ndim != 2
            or order.size == 0 or order.size >= MAX_PIXELS
            or order.dtype not in (np.float32, np.float64)):
        return layering.layer_labels(order, max_layers, rule)
    from clblur.opencl import runtime

    rt = runtime(device)
    if not rt.device.double_fp_config:
        return layering.layer_labels(order, max_layers, rule)
    return _device_labels(rt, order, max_layers)


_RUN = np.dtype([("comp", np.int32), ("pixels", np.int32), ("inner", np.int32),
                 ("pad", np.int32), ("sum", np.float64)])  # labels_stats' run record


@dataclass
class _Surfaces:
    """What ``labels_stats`` leaves: the component image stays on the device (``comp``, the
    buffer of role ``labels.comp``), the counts and records come to the host."""

    shape: tuple[int, int]
    n: int  # components before the sliver merge
    bad: int  # invalid pixels
    runs: np.ndarray  # _RUN records
    code: np.ndarray  # edge records: 2 p + (0 right | 1 down) ...
    x: np.ndarray  # ... comp[p] ...
    y: np.ndarray  # ... and the neighbour's, x != y
    comp: object  # the device buffer
    program: Program


def _depth_buffer(rt, depth: np.ndarray, rect: bool | None = None):
    """The depth map on the device.  A view of rows (``order[crop]``, as the layered build
    passes it) is sent row by row in one rectangular copy on a device with its own memory
    (``rect``, default: not ``rt.unified``), without a contiguous copy on the host first."""
    cl = pyopencl_module()
    h, w = depth.shape
    item = depth.itemsize
    if rect is None:
        rect = not rt.unified
    if depth.flags.c_contiguous or not rect or depth.strides[1] != item \
            or depth.strides[0] < w * item:
        return rt.share("labels.depth", np.ascontiguousarray(depth))
    span = (h - 1) * depth.strides[0] + w * item
    rows = (ctypes.c_char * span).from_address(depth.__array_interface__["data"][0])
    buf = rt.buffer("labels.depth", h * w * item)
    cl.enqueue_copy(rt.queue, buf, rows, buffer_origin=(0, 0), host_origin=(0, 0),
                    region=(w * item, h), buffer_pitches=(w * item,),
                    host_pitches=(depth.strides[0],), is_blocking=True)
    return buf


def _surfaces(rt, depth: np.ndarray) -> _Surfaces:
    """Joins, components and their records on the device (``labels.cl`` up to
    ``labels_stats``); one wait for the counters and the records' first ``PREFIX``, a second
    only for longer lists.  The caller holds ``rt.lock`` (the buffers are the runtime's,
    reused by the next call)."""
    cl = pyopencl_module()
    h, w = depth.shape
    n = h * w
    nwords = -(-n // 32)
    i4 = np.dtype(np.int32).itemsize
    tiles = (_padded(w, TILE), _padded(h, TILE))
    flat = (_padded(n, WG),)
    program = _program(rt, "double" if depth.dtype == np.float64 else "float")
    depth_buf = _depth_buffer(rt, depth)
    edges = rt.buffer("labels.edges", n)
    parent = rt.buffer("labels.parent", i4 * n)
    words = rt.buffer("labels.words", i4 * nwords)
    offset = rt.buffer("labels.offset", i4 * nwords)
    counters = rt.buffer("labels.counters", 4 * i4)
    comp = rt.buffer("labels.comp", i4 * n)
    runs = rt.buffer("labels.runs", _RUN.itemsize * n)
    records = rt.buffer("labels.records", 3 * i4 * 2 * n)
    program.run("labels_tiles", rt.queue, tiles, (TILE, TILE), depth=depth_buf, h=h, w=w,
                tau=DEPTH_TAU, edges=edges, parent=parent)
    program.run("labels_seams", rt.queue, tiles, (TILE, TILE), edges=edges, h=h, w=w,
                parent=parent)
    program.run("labels_roots", rt.queue, flat, (WG,), parent=parent, n=n, nwords=nwords,
                words=words)
    program.run("labels_scan", rt.queue, (WG,), (WG,), words=words, nwords=nwords,
                offset=offset, counters=counters)
    program.run("labels_stats", rt.queue, flat, (WG,), depth=depth_buf, edges=edges,
                parent=parent, words=words, offset=offset, h=h, w=w, capacity_runs=n,
                capacity_edges=2 * n, comp=comp, counters=counters, runs=runs,
                records=records)
    count = np.empty(4, np.int32)
    got_runs = np.empty(min(PREFIX, n), _RUN)
    got_records = np.empty((min(PREFIX, 2 * n), 3), np.int32)
    cl.enqueue_copy(rt.queue, count, counters, is_blocking=False)
    cl.enqueue_copy(rt.queue, got_runs, runs, is_blocking=False)
    cl.enqueue_copy(rt.queue, got_records, records, is_blocking=False)
    rt.queue.finish()
    n0, nruns, nedges, bad = (int(v) for v in count)
    longer = []
    for host, buf, total in ((got_runs, runs, nruns), (got_records, records, nedges)):
        if total > len(host):
            whole = np.empty((total, *host.shape[1:]), host.dtype)
            whole[:len(host)] = host
            cl.enqueue_copy(rt.queue, whole[len(host):], buf, src_offset=host.nbytes,
                            is_blocking=False)
            host = whole
        longer.append(host[:total])
    if nruns > len(got_runs) or nedges > len(got_records):
        rt.queue.finish()
    rec = longer[1]
    return _Surfaces((h, w), n0, bad, longer[0], rec[:, 0], rec[:, 1], rec[:, 2], comp,
                     program)


def _download_comp(rt, surf: _Surfaces) -> np.ndarray:
    """The component image (H x W int32) from the device (the caller holds ``rt.lock``)."""
    comp = np.empty(surf.shape, np.int32)
    pyopencl_module().enqueue_copy(rt.queue, comp, surf.comp, is_blocking=True)
    return comp


def surface_components(depth: np.ndarray, device: str | None = None) -> tuple[np.ndarray, int]:
    """The device's continuous surfaces before the sliver merge: (H x W int32 labels 0..n-1
    in raster order of their first pixel, n), ``layering._components`` of the joins of
    ``layering._continuous``.  For the tests; float32 / float64 2-D depth, valid (unchecked).
    """
    from clblur.opencl import runtime

    rt = runtime(device)
    with rt.lock:
        surf = _surfaces(rt, np.asarray(depth))
        return _download_comp(rt, surf), surf.n


def _device_labels(rt, order: np.ndarray, max_layers: int) -> np.ndarray:
    """The device path of :func:`layer_labels` (module Conventions).  Holds ``rt.lock`` for
    the whole call: the component image stays in the runtime's buffer until the end."""
    with rt.lock:
        surf = _surfaces(rt, order)
        if surf.bad:
            layering._inverse_depth(order)  # raises the host's error
            raise AssertionError("the device flagged invalid depth the host accepts")
        if surf.n == 1:
            return np.zeros(order.shape, np.int32)
        table = _layer_table(rt, order, surf, max_layers)
        if table is None:  # a component without boundary: never on a connected grid
            return layering.layer_labels(order, max_layers, "depth")
        if not table.any():
            return np.zeros(order.shape, np.int32)
        labels = np.empty(order.shape, np.int32)
        n = labels.size
        out = rt.buffer("labels.out", labels.nbytes)
        surf.program.run("labels_map", rt.queue, (_padded(n, WG),), (WG,), comp=surf.comp,
                    table=rt.upload("labels.table", table, table=True), n=n, labels=out)
        pyopencl_module().enqueue_copy(rt.queue, labels, out, is_blocking=True)
    return labels


def _layer_table(rt, order: np.ndarray, surf: _Surfaces, max_layers: int) -> np.ndarray | None:
    """The layer of each component of ``surf`` (int32; None: ask the host), from the records:
    the sliver merge, the front-to-back order and the cut."""
    n0 = surf.n
    # the records in the host's traversal order (right pairs, then down; raster order): the
    # sliver merge's assignments follow it where two candidates tie exactly
    srt = np.lexsort((surf.code >> 1, surf.code & 1))
    code, ex, ey = surf.code[srt], surf.x[srt], surf.y[srt]

    def exact_means() -> np.ndarray:
        """The reference's means: bincount over the whole component image in raster order."""
        comp = _download_comp(rt, surf).ravel()
        with np.errstate(divide="ignore"):
            wi = 1.0 / np.asarray(order, np.float64).ravel()
        wf = np.where(np.isfinite(wi), wi, 0.0)
        return np.bincount(comp, wf, n0) / np.bincount(comp, None, n0)

    new_of_old, n1 = _merge_slivers(n0, surf.runs, code, ex, ey, exact_means)
    if n1 == 1:
        return np.zeros(n0, np.int32)
    x, y = new_of_old[ex], new_of_old[ey]
    keep = x != y
    layer_of_comp = _order_and_cut(order, code[keep], x[keep], y[keep], n1, max_layers)
    if layer_of_comp is None:
        return None
    return layer_of_comp[new_of_old].astype(np.int32)


def _merge_slivers(n0: int, runs: np.ndarray, code, ex, ey,
                   exact_means) -> tuple[np.ndarray, int]:
    """``depth_components``' sliver merge on the edge records: (new component of each old one,
    the new count).  ``exact_means()`` gives the reference's means when the device's are too
    close to decide a comparison (module Conventions)."""
    interior = np.bincount(runs["comp"], runs["inner"], n0) > 0
    if interior.all():
        return np.arange(n0), n0
    count = np.bincount(runs["comp"], runs["pixels"], n0)
    mean_w = np.bincount(runs["comp"], runs["sum"], n0) / count
    bound = 4.0 * (count + 2.0) * _U * np.abs(mean_w)  # twice the two roundings' bound
    right = (code & 1) == 0
    # the reference's loop order: right pairs (a, b) then (b, a), then the down pairs
    seq = [(a, b) for part in (right, ~right) for a, b in ((ex[part], ey[part]),
                                                          (ey[part], ex[part]))]
    xs = np.concatenate([a for a, _ in seq])
    ys = np.concatenate([b for _, b in seq])
    sliver = ~interior[xs]
    sx, sy = xs[sliver], ys[sliver]
    ambiguous = not np.isfinite(mean_w).all() or bool(
        (np.abs(mean_w[sx] - mean_w[sy]) <= bound[sx] + bound[sy]).any())
    if not ambiguous:  # two neighbours of one sliver as close: the pick among them could differ
        pair = np.unique(sx.astype(np.int64) * n0 + sy)
        px, py = pair // n0, pair % n0
        s = np.lexsort((mean_w[py], px))
        px, py = px[s], py[s]
        same = px[1:] == px[:-1]
        ambiguous = bool((same & (np.abs(mean_w[py[1:]] - mean_w[py[:-1]])
                                  <= bound[py[1:]] + bound[py[:-1]])).any())
    if ambiguous:
        mean_w = exact_means()
    # as depth_components, on the records (pairs inside one component never select)
    target = layering.sliver_targets(interior, mean_w, seq)
    kept = np.unique(target)  # every component has pixels: np.unique(target[comp])'s values
    return np.searchsorted(kept, target), int(kept.size)


def _order_and_cut(order: np.ndarray, code, x, y, n: int,
                   max_layers: int) -> np.ndarray | None:
    """``order_components`` and ``layer_labels``' cut on the edge records (pairs of
    neighbours in components x != y): the layer of each component, or None where a component
    has no boundary pixel (never, for n >= 2 on a connected grid)."""
    h, w = order.shape
    p = code >> 1
    q = p + np.where((code & 1) == 1, w, 1)
    # log-depth at the boundary pixels only (numpy's log, elementwise as the reference's)
    pix = np.concatenate([p, q])
    with np.errstate(divide="ignore"):
        logz_all = np.log(np.asarray(order[pix // w, pix % w], np.float64))
    lp, lq = logz_all[:p.size], logz_all[p.size:]
    with np.errstate(invalid="ignore"):
        dz = lq - lp  # > 0: x nearer than y
    dz = np.where(np.isnan(dz), 0.0, dz)  # sky next to sky
    lo, hi = np.minimum(x, y), np.maximum(x, y)
    sign = np.where(x == lo, dz, -dz)  # > 0: lo nearer than hi
    # keys: median log-depth of each component's boundary pixels
    border, first = np.unique(pix, return_index=True)
    c_at = np.concatenate([x, y])[first]
    z_at = logz_all[first]
    if not np.bincount(c_at, minlength=n).all():
        return None
    keys = layering.median_keys(c_at, z_at, n)
    # median over each pair's boundary pairs (np.median: the middle one, or the mean of the
    # middle two); only its sign is used
    key = lo.astype(np.int64) * n + hi
    srt = np.lexsort((sign, key))
    key, sign = key[srt], sign[srt]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    sizes = np.diff(np.r_[starts, key.size])
    a, b = sign[starts + (sizes - 1) // 2], sign[starts + sizes // 2]
    with np.errstate(invalid="ignore"):
        med = np.where(sizes % 2 == 1, a, (a + b) / 2)
    before = [((k // n, k % n) if m > 0 else (k % n, k // n))
              for k, m in zip(key[starts].tolist(), med.tolist(), strict=True) if m != 0.0]
    ranked = layering.rank_components(keys, before)  # each pair once, as the reference's dict
    return layering.layer_of_components(ranked, keys, max_layers)
