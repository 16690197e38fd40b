"""File input and output: images, flow fields, PSFs; atomic writes that never touch inputs."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

FLO_MAGIC = 202021.25  # Middlebury .flo tag


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def tmp_beside(path: Path) -> Path:
    """A new empty temporary file next to ``path`` (same folder, so the rename is atomic),
    with the permissions a plainly created file would get (mkstemp makes it 0600)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part" + path.suffix,
                               dir=path.parent)
    os.fchmod(fd, 0o666 & ~_umask())
    os.close(fd)
    return Path(tmp)


def atomic_write(path: str | os.PathLike, writer: Callable[[Path], None]) -> None:
    """Call ``writer(tmp)`` on a temporary file beside ``path``, then rename it into place."""
    path = Path(path)
    if not path.parent.exists():
        raise ValueError(f"output folder does not exist: {path.parent}")
    tmp = tmp_beside(path)
    try:
        writer(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write(path, lambda tmp: tmp.write_text(text))


def refuse_overwrite(out: str | os.PathLike, *inputs: str | os.PathLike) -> None:
    """Raise if ``out`` names one of the inputs (the same file, however spelled)."""
    o = Path(out)
    for i in inputs:
        if i is None:
            continue
        ip = Path(i)
        if o.resolve() == ip.resolve() or (o.exists() and ip.exists() and o.samefile(ip)):
            raise ValueError(f"output {out} is the input {i}; refusing to overwrite an input")


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read PNG/TIFF/JPEG/EXR/... as uint8, uint16 or float32 (H x W or H x W x C; RGB order)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"image file not found: {path}")
    if path.suffix.lower() == ".exr":  # linear float channels: clblur.exr
        from clblur import exr

        return exr.read_image(path)
    if path.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            img = tifffile.imread(path)
        except Exception as e:  # tifffile raises many types for corrupt files
            raise ValueError(f"cannot read image {path}: {e}") from None
    else:
        import cv2

        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"cannot read image {path}: not an image file or corrupt")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA if img.shape[2] == 4
                               else cv2.COLOR_BGR2RGB)
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64) or img.ndim not in (2, 3):
        raise ValueError(f"unsupported image {path}: dtype {img.dtype}, shape {img.shape}")
    return img


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an image atomically; the format follows the suffix (PNG, TIFF, JPEG, EXR, ...)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        from clblur import exr

        exr.write_image(path, image)
        return
    if suffix in (".tif", ".tiff"):
        import tifffile

        rgb = image.ndim == 3 and image.shape[2] in (3, 4)
        atomic_write(path, lambda tmp: tifffile.imwrite(
            tmp, image, photometric="rgb" if rgb else "minisblack"))
        return
    import cv2

    if image.dtype.kind == "f":
        raise ValueError(f"{suffix} cannot hold float images; write .tif or .tiff instead")
    bgr = image
    if image.ndim == 3 and image.shape[2] in (3, 4):
        bgr = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA if image.shape[2] == 4
                           else cv2.COLOR_RGB2BGR)

    def write(tmp: Path) -> None:
        ok, buf = cv2.imencode(suffix or ".png", bgr)
        if not ok:
            raise ValueError(f"cannot encode image as {suffix}")
        tmp.write_bytes(buf.tobytes())

    atomic_write(path, write)


def read_flow(path: str | os.PathLike) -> np.ndarray:
    """Read a flow field (.npy H x W x 2, Middlebury .flo, or EXR flow.x/flow.y) as float32."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"flow file not found: {path}")
    if path.suffix.lower() == ".exr":
        from clblur import exr

        return exr.read_flow(path)
    if path.suffix.lower() == ".flo":
        raw = path.read_bytes()
        if len(raw) < 12 or np.frombuffer(raw[:4], "<f4")[0] != FLO_MAGIC:
            raise ValueError(f"{path} is not a Middlebury .flo file (bad header)")
        w, h = (int(v) for v in np.frombuffer(raw[4:12], "<i4"))
        if w <= 0 or h <= 0 or len(raw) != 12 + 8 * w * h:
            raise ValueError(f"{path}: truncated or malformed .flo ({w} x {h} declared)")
        return np.frombuffer(raw[12:], "<f4").reshape(h, w, 2).copy()
    try:
        flow = np.load(path, allow_pickle=False)
    except Exception as e:
        raise ValueError(f"cannot read flow {path}: {e}") from None
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow {path} has shape {flow.shape}, expected H x W x 2")
    return flow.astype(np.float32)


def write_flow(path: str | os.PathLike, flow: np.ndarray) -> None:
    """Write a flow field as .flo, .exr or .npy (by suffix), atomically."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        from clblur import exr

        exr.write_flow(path, flow)
        return
    flow = np.asarray(flow, dtype=np.float32)
    if path.suffix.lower() == ".flo":
        h, w = flow.shape[:2]
        data = (np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
                + flow.astype("<f4").tobytes())
        atomic_write(path, lambda tmp: tmp.write_bytes(data))
    else:
        atomic_write(path, lambda tmp: np.save(tmp, flow))


def read_psf(path: str | os.PathLike) -> np.ndarray:
    """Read a PSF from an image (grey, any scale) or .npy; returned as float64 (unnormalised)."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        if not path.is_file():
            raise ValueError(f"PSF file not found: {path}")
        k = np.load(path, allow_pickle=False)
    else:
        k = read_image(path)
        if k.ndim == 3:
            k = k[..., :3].mean(axis=2)
    return np.asarray(k, dtype=np.float64)
