"""Large images in bounded memory: blur tile by tile, each tile read with a halo.

Conventions
-----------
* A *tile* is a block of output pixels ``[r0:r1, c0:c1]``.  Its *window* is the tile grown by
  the halo on every side and clipped to the image.  The window is blurred with
  ``make_plan(..., region=(row0, col0, H, W))``, so every sample position is computed and
  clamped in full-image coordinates exactly as in the untiled run; only the tile is kept.  With
  a sufficient halo the tiled result is therefore bitwise identical to ``clblur.blur`` on the
  same backend.
* Halo, per axis: ``ceil(reach) + 2``, from how far the samples reach (``clblur.halo``).
  The halo is capped at the image size: a window never extends past the image, so a motion
  of 1e9 px on a small image needs a window of the whole image, not of 1e9 px.
* Sources and destinations are array-likes (``clblur.io.raster``): numpy arrays, zarr arrays,
  and ``MappedRaster`` (a raster in a file, e.g. an uncompressed BigTIFF).
* ``memory_budget`` (bytes) bounds the working set.  Image files that cannot be read window by
  window (PNG, JPEG, ...) and non-TIFF outputs are held whole; ``blur_file`` counts them
  against the budget (refusing before decoding when they alone exceed it) and gives the rest
  to the windows, each estimated at ``window_bytes_per_px`` per window pixel.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clblur.blur import blur_plan, resolve_backend
from clblur.errors import InputError, InputTypeError
from clblur.halo import fixed_halo, flow_halo, global_flow_halo, tiled_motion
from clblur.io import (
    IMAGE_FORMATS,
    as_array_like,
    atomic_write,
    check_decodable,
    check_output,
    create_tiff,
    describe_size,
    exr_layout,
    is_tiff,
    open_image,
    read_flow,
    response_for_file,
    write_image,
)
from clblur.motion import anchor_value
from clblur.request import make_plan

__all__ = ["DEFAULT_MEMORY_BUDGET", "TiledRun", "blur_file", "blur_tiled", "choose_tile",
           "parse_size", "tiles", "window_bytes_per_px"]

DEFAULT_MEMORY_BUDGET = 512 * 2**20
MIN_TILE = 32  # px a side: the smallest tile a memory budget may leave
FLOW_BYTES_PER_PX = 8  # float32 (dx, dy)
# longest motion run with the default ceil(|v|) + 1 samples (longer ones need samples=N)
MAX_DEFAULT_LENGTH = 2**16


def window_bytes_per_px(channels: int, itemsize: int, per_pixel_flow: bool) -> int:
    """Working set per window pixel (bytes), an upper estimate.

    The numpy reference keeps about a dozen float64 H x W x C arrays alive (normalised values,
    linear values, accumulator, output, bilinear corners) and about twenty float64 H x W
    coordinate arrays; ``tracemalloc`` measured 248 B/px (uniform) and 321 B/px (flow) for a
    512 x 512 RGB uint8 window (``python bench/bench_large.py --working-set-only``).  The
    OpenCL backend needs less.  Input and output windows, and the flow window, come on top.
    """
    return 8 * (12 * channels + 20) + 2 * channels * itemsize + \
        (FLOW_BYTES_PER_PX if per_pixel_flow else 0)


# --------------------------------------------------------------------------- tile geometry
_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_size(size: int | str | None) -> int:
    """A memory budget in bytes from an int or ``"512M"``/``"2G"``/``"1.5GiB"`` (binary
    units); None gives the default (512 MiB)."""
    if size is None:
        return DEFAULT_MEMORY_BUDGET
    if isinstance(size, str):
        text = size.strip().upper().removesuffix("B").removesuffix("I")
        unit = text[-1:] if text[-1:] in _UNITS else ""
        try:
            value = float(text[:len(text) - len(unit)]) * _UNITS[unit]
        except ValueError:
            raise InputError(f"memory budget must be bytes or a size like 500M or 2G, got "
                             f"{size!r}") from None
    elif isinstance(size, (int, float, np.integer)) and not isinstance(size, bool):
        value = float(size)
    else:
        raise InputTypeError(f"memory budget must be bytes or a size like '2G', got {size!r}")
    if not math.isfinite(value) or value <= 0:
        raise InputError(f"memory budget must be positive, got {size!r}")
    return int(value)

def choose_tile(shape: tuple[int, int], halo: tuple[int, int], bytes_per_px: int,
                memory_budget: int) -> tuple[int, int]:
    """The largest square tile (clipped to the image) whose window fits ``memory_budget``."""
    h, w = shape
    hy, hx = halo

    def cost(t: int) -> int:  # windows are clipped to the image
        return min(min(t, h) + 2 * hy, h) * min(min(t, w) + 2 * hx, w) * bytes_per_px

    # a tile smaller than MIN_TILE a side is mostly halo: a 200 KiB budget on a 3000 x 2000
    # frame ran for more than 12 minutes over hundreds of thousands of windows
    least = min(MIN_TILE, max(h, w))
    if cost(least) > memory_budget:
        raise InputError(f"memory budget {describe_size(memory_budget)} is too small for a halo "
                         f"of {hy} x {hx} px: tiles of {least} px a side need "
                         f"{describe_size(cost(least))}; raise --memory-budget")
    lo, hi = least, max(h, w)
    while lo < hi:  # largest t with cost(t) <= budget
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if cost(mid) <= memory_budget else (lo, mid - 1)
    return min(lo, h), min(lo, w)


def tiles(shape: tuple[int, int], tile: tuple[int, int]) -> Iterator[tuple[int, int, int, int]]:
    """Row-major ``(r0, r1, c0, c1)`` blocks covering ``shape``."""
    h, w = shape
    th, tw = tile
    for r0 in range(0, h, th):
        for c0 in range(0, w, tw):
            yield r0, min(r0 + th, h), c0, min(c0 + tw, w)


def _tile_shape(tile) -> tuple[int, int]:
    if isinstance(tile, (int, np.integer)) and not isinstance(tile, bool):
        tile = (tile, tile)
    try:
        th, tw = (int(t) for t in tile)
    except (TypeError, ValueError):
        raise InputTypeError(f"tile must be an int or (rows, cols), got {tile!r}") from None
    if th < 1 or tw < 1:
        raise InputError(f"tile must be at least 1 x 1, got {tile!r}")
    return th, tw


# --------------------------------------------------------------------------- the tiled blur
@dataclass(frozen=True)
class TiledRun:
    """What a tiled blur did (for logs, benches and tests)."""

    backend: str
    tile: tuple[int, int]
    tiles: int
    halo: tuple[int, int]  # largest (rows, cols) halo used


def _check_arrays(src, dst) -> tuple[int, int, int]:
    for name, a in (("source", src), ("destination", dst)):
        if not hasattr(a, "shape") or not hasattr(a, "dtype"):
            raise InputTypeError(f"{name} must be an array-like with shape and dtype, "
                            f"got {type(a).__name__}")
    if len(src.shape) not in (2, 3):
        raise InputError(f"image must be H x W or H x W x C, got shape {tuple(src.shape)}")
    if tuple(dst.shape) != tuple(src.shape) or np.dtype(dst.dtype) != np.dtype(src.dtype):
        raise InputError(f"destination {tuple(dst.shape)} {dst.dtype} does not match the source "
                         f"{tuple(src.shape)} {src.dtype}")
    h, w = (int(s) for s in src.shape[:2])
    return h, w, int(src.shape[2]) if len(src.shape) == 3 else 1


def blur_tiled(src, dst, motion, response="exp", *, anchor: str = "center",
               samples: int | None = None, weights=None, backend: str = "auto",
               saturation: float = 1.0, device: str | None = None, tile=None,
               memory_budget: int | None = None, progress: bool = False,
               exposure: str = "frames") -> TiledRun:
    """Blur array-like ``src`` into array-like ``dst`` (same shape and dtype), tile by tile.

    ``motion`` as for ``clblur.blur``; a flow may be any H x W x 2 array-like or a ``.npy``
    path and is read window by window.  ``tile`` (int or (rows, cols)) fixes the tile size;
    otherwise it is the largest that keeps a window within ``memory_budget`` (bytes or a size
    such as ``"2G"``; default 512 MiB).  Result: bitwise what ``clblur.blur`` gives on the
    same backend.
    """
    h, w, channels = _check_arrays(src, dst)
    src, dst = as_array_like(src), as_array_like(dst)
    a = anchor_value(anchor)
    budget = parse_size(memory_budget)
    try:
        tm = tiled_motion(motion, (h, w))
        if tm.flow is not None:  # size tiles for the worst halo; each tile then uses its own
            # a band is mapped, copied and maybe widened to float32: 1/8 of the budget
            band_bytes = w * 2 * max(np.dtype(tm.flow.dtype).itemsize, 4)
            halo = global_flow_halo(tm.flow, a, max(budget // (8 * band_bytes), 1))
        else:
            halo = fixed_halo(tm.fixed, a)
    except InputError as e:  # a flow file's fault names the file
        if not isinstance(motion, (str, os.PathLike)) or str(motion) in str(e):
            raise
        raise InputError(f"flow {motion}: {e}") from None
    per_px = window_bytes_per_px(channels, np.dtype(src.dtype).itemsize, tm.flow is not None)
    if samples is None and max(halo) - 2 > MAX_DEFAULT_LENGTH * max(a, 1.0 - a):
        # the default ceil(|v|) + 1 samples per pixel would run for hours
        raise InputError(f"motion longer than {MAX_DEFAULT_LENGTH} px needs that many samples "
                         "per pixel by default; give a sample count (--samples N)")
    halo = (min(halo[0], h), min(halo[1], w))  # a window never extends past the image
    if tile is None:
        tile = choose_tile((h, w), halo, per_px, budget)
    tile = _tile_shape(tile)
    tile = (min(tile[0], h), min(tile[1], w))
    ran = resolve_backend(backend, device)
    # Validate the options once on a tiny window so a bad option fails before any work.
    make_plan(np.zeros((1, 1, channels), np.dtype(src.dtype)), (0.0, 0.0), response,
              anchor=anchor, samples=samples, weights=weights, saturation=saturation,
              exposure=exposure)
    blocks = list(tiles((h, w), tile))
    used = (0, 0)
    bar = _progress(len(blocks), progress)
    try:
        for r0, r1, c0, c1 in blocks:
            m = tm.fixed
            hy, hx = halo
            if tm.flow is not None:
                # one read with the worst-case halo, then shrink to this tile's own halo
                gr0, gc0 = max(r0 - hy, 0), max(c0 - hx, 0)
                big = np.asarray(tm.flow[gr0:min(r1 + hy, h), gc0:min(c1 + hx, w)],
                                 dtype=np.float32)
                hy, hx = flow_halo(big[r0 - gr0:r1 - gr0, c0 - gc0:c1 - gc0], a)
                hy, hx = min(hy, h), min(hx, w)
            used = (max(used[0], hy), max(used[1], hx))
            wr0, wr1 = max(r0 - hy, 0), min(r1 + hy, h)
            wc0, wc1 = max(c0 - hx, 0), min(c1 + hx, w)
            window = np.asarray(src[wr0:wr1, wc0:wc1])
            if tm.flow is not None:
                m = big[wr0 - gr0:wr1 - gr0, wc0 - gc0:wc1 - gc0]
            plan = make_plan(window, m, response, anchor=anchor, samples=samples,
                             weights=weights, saturation=saturation,
                             region=(wr0, wc0, h, w), exposure=exposure)
            out = blur_plan(plan, ran, device)
            dst[r0:r1, c0:c1] = out[r0 - wr0:r1 - wr0, c0 - wc0:c1 - wc0]
            bar.update(1)
    finally:
        bar.close()
    return TiledRun(backend=ran, tile=tile, tiles=len(blocks), halo=used)


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    # disable=None: no bar when stderr is not a terminal (logs, pipes, captured errors)
    return tqdm(total=total, unit="tile", disable=None if enabled else True, desc="blur",
                leave=False)


# --------------------------------------------------------------------------- files
def blur_file(src: str | os.PathLike, dst: str | os.PathLike, motion, response=None, *,
              anchor: str = "center", samples: int | None = None, weights=None,
              backend: str = "auto", saturation: float = 1.0, device: str | None = None,
              memory_budget: int | None = None, progress: bool = False,
              tile=None, exposure: str = "frames") -> TiledRun:
    """Blur the image file ``src`` into ``dst``, in bounded memory where the formats allow.

    TIFF sources are read window by window; a TIFF destination is an uncompressed TIFF
    (BigTIFF above 2 GiB) written window by window.  Other formats are held whole.  The output
    goes to a temporary file beside ``dst`` that is renamed into place only when complete, so
    ``dst`` is either absent, the previous file, or the finished result.  ``motion``: as for
    ``blur_tiled`` (a flow may be a ``.npy``/``.flo`` path).  ``response``: None takes the
    file's (``clblur.io.response_for_file``: ``linear`` for an EXR, which holds scene-linear
    light, else ``exp``).
    """
    dst = check_output(dst, src, *([motion] if isinstance(motion, (str, os.PathLike)) else []),
                       suffixes=tuple(IMAGE_FORMATS))
    budget = parse_size(memory_budget)
    header = check_decodable(src)
    # what is held whole: a non-TIFF input as decoded; a non-TIFF output as the finished
    # array and the encoder's copy of it (OpenCV's colour order; a PNG of a 3000 x 2000
    # uint16 frame peaked at twice the array above the budget the TIFF path keeps)
    held = {str(src): header.nbytes} if not is_tiff(src) else {}
    if not is_tiff(dst):
        held[str(dst)] = 2 * header.nbytes
    whole = sum(held.values())
    if whole > budget:  # refused before anything is decoded
        raise InputError(
            f"{' and '.join(held)} {'are' if len(held) > 1 else 'is'} held whole "
            f"({header.width} x {header.height} x {header.channels}: {describe_size(whole)}), "
            f"more than the memory budget ({describe_size(budget)}); raise --memory-budget, or "
            "use TIFF input and output, which are read and written window by window (convert "
            "with e.g. `vips tiffsave IN OUT.tif --tile --bigtiff`)")
    layout = exr_layout(src)  # an EXR input's windows and header, kept by an EXR output
    if layout is not None and isinstance(motion, (str, os.PathLike)) and \
            str(motion).lower().endswith(".exr"):  # its pixels matched by place, not index
        from clblur.io.exr import align

        motion = align(read_flow(motion), motion, layout, "flow")
    image = open_image(src)
    if not is_tiff(dst) and dst.suffix.lower() != ".exr" and np.dtype(image.dtype).kind == "f":
        raise InputError(f"{dst.suffix} cannot hold float images; write .tif, .tiff or .exr "
                         "instead")
    if response is None:
        response = response_for_file(src)
    options = dict(response=response, anchor=anchor, samples=samples, weights=weights,
                   backend=backend, saturation=saturation, device=device, tile=tile,
                   memory_budget=max(budget - whole, 1), progress=progress, exposure=exposure)
    if is_tiff(dst):
        result: list[TiledRun] = []

        def write(tmp: Path) -> None:
            out = create_tiff(tmp, tuple(image.shape), np.dtype(image.dtype))
            result.append(blur_tiled(image, out, motion, **options))

        atomic_write(dst, write)
        return result[0]
    out = np.empty(tuple(image.shape), np.dtype(image.dtype))
    run = blur_tiled(image, out, motion, **options)
    write_image(dst, out, layout=layout)
    return run
