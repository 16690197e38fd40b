"""Host <-> device transfers for devices with their own memory (GPUs), and pinned arrays.

Conventions
-----------
* The image, the flow and the output move in row bands (``bands_of``): band k on queue
  k mod (number of queues), so the upload of one band, the kernels of another and the
  download of a third overlap.  Devices that share host memory (CPUs) get one band and read
  the caller's arrays in place.
* Uploads go through the runtime's reused pinned staging buffers unless the caller's array is
  itself pinned (``pinned_empty``).
"""

from __future__ import annotations

import numpy as np

from clblur.opencl.device import Runtime, pyopencl_module, runtime

__all__ = ["BANDS", "MIN_BAND_ROWS", "bands_of", "download", "is_pinned", "pinned_empty",
           "upload_rows"]

BANDS = 4  # row bands whose transfers and kernels overlap (devices with their own memory)
MIN_BAND_ROWS = 64


def pinned_empty(shape, dtype, device: str | None = None) -> np.ndarray:
    """An uninitialised host array in pinned (page-locked, ``ALLOC_HOST_PTR``) memory.

    Images and flows passed to ``clblur.blur`` in such arrays are copied to a GPU at the
    bus's full speed without a staging copy.  The array keeps its OpenCL buffer alive.

    Parameters
    ----------
    shape : tuple of int
    dtype : numpy dtype
    device : OpenCL device selector (``clblur info``); default ``$CLBLUR_DEVICE`` or the first
        GPU.
    """
    cl = pyopencl_module()
    rt = runtime(device)
    nbytes = max(int(np.prod(shape)) * np.dtype(dtype).itemsize, 1)
    with rt.lock:
        buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.ALLOC_HOST_PTR,
                        nbytes)
        host, _ = cl.enqueue_map_buffer(rt.queue, buf, cl.map_flags.READ | cl.map_flags.WRITE,
                                        0, tuple(shape), dtype, is_blocking=True)
    return host


def is_pinned(array: np.ndarray) -> bool:
    """Whether ``array`` views a mapped OpenCL buffer (``pinned_empty``)."""
    base = array
    while base is not None:
        if type(base).__name__ == "MemoryMap":
            return True
        base = getattr(base, "base", None)
    return False


def bands_of(rt: Runtime, h: int) -> list[tuple[int, int]]:
    """Row ranges: one for devices that share host memory, up to BANDS otherwise."""
    count = 1 if rt.unified else max(1, min(BANDS, h // MIN_BAND_ROWS))
    # inner edges on multiples of 8 rows: work-groups of 8 rows never cross into a band
    edges = [0, *(round(h * k / count / 8) * 8 for k in range(1, count)), h]
    return [(edges[k], edges[k + 1]) for k in range(count)]


def upload_rows(rt: Runtime, role: str, array: np.ndarray, bands) -> tuple[object, list]:
    """``array`` (rows first) on the device: the array itself on unified devices, else one
    non-blocking copy per band on alternating queues (through pinned staging unless the
    array is pinned).  Returns (buffer, one event list per band)."""
    array = np.ascontiguousarray(array)
    if rt.unified:
        return rt.share(role, array), [[] for _ in bands]
    cl = pyopencl_module()
    buf = rt.buffer(role, array.nbytes)
    row_bytes = array.nbytes // max(array.shape[0], 1)
    staged = array if is_pinned(array) else rt.staging(role, array.nbytes)
    events = []
    for k, (r0, r1) in enumerate(bands):
        part = array[r0:r1].reshape(-1).view(np.uint8)
        if staged is not array:
            staged[r0 * row_bytes:r1 * row_bytes] = part
            part = staged[r0 * row_bytes:r1 * row_bytes]
        queue = rt.all_queues()[k % len(rt.all_queues())]
        events.append([cl.enqueue_copy(queue, buf, part, dst_offset=r0 * row_bytes,
                                       is_blocking=False)])
    return buf, events


def download(rt: Runtime, out: np.ndarray, out_buf, bands: list[tuple[int, int]],
             done: list) -> None:
    """Copy the output back: band by band on the band's queue, each after its own band's
    kernel (``done[k]``: earlier channel groups are finished), so band k comes down while
    band k + 1 computes; or one blocking copy on unified devices."""
    cl = pyopencl_module()
    if rt.unified or len(bands) == 1:
        cl.enqueue_copy(rt.queue, out, out_buf, wait_for=done, is_blocking=True)
        return
    row_bytes = out.nbytes // out.shape[0]
    flat = out.reshape(-1).view(np.uint8)
    per_band = len(done) == len(bands)  # the box kernel runs once for the whole image
    events = []
    for k, (r0, r1) in enumerate(bands):
        queue = rt.all_queues()[k % len(rt.all_queues())]
        events.append(cl.enqueue_copy(queue, flat[r0 * row_bytes:r1 * row_bytes], out_buf,
                                      src_offset=r0 * row_bytes,
                                      wait_for=[done[k]] if per_band else done,
                                      is_blocking=False))
    cl.wait_for_events(events)
