"""The state a batch keeps in ``OUT_DIR/.clblur-batch/``: the job, its key, completion
markers and claims (conventions in ``clblur.batch``).

Conventions
-----------
* ``job_key``: SHA-256 over the content (size and SHA-256 of the bytes) of the input, flow,
  PSF and response document, every option that changes pixels, and the clblur version: a
  file touched, copied or synced without its modification time keeps its key.
* ``<output name>.json``: the completion marker (key and output size); ``<output name>.lock``:
  a claim, created with ``O_EXCL`` and refreshed every ``HEARTBEAT_S`` while its job runs;
  stale when its process is gone (same host) or not refreshed for ``STALE_LOCK_S``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

__all__ = ["HEARTBEAT_S", "MARKER_DIR", "STALE_LOCK_S", "Claim", "Job", "Result", "claim",
           "is_finished", "job_key", "lock_path", "marker_path", "partial_name", "remove_partials",
           "response_file"]

MARKER_DIR = ".clblur-batch"
STALE_LOCK_S = 120.0  # a claim not refreshed for this long belongs to a dead worker
HEARTBEAT_S = 15.0
BUILTIN_RESPONSES = ("linear", "exp", "gamma", "srgb")


@dataclass(frozen=True)
class Job:
    """One image to blur: only paths and plain options, so it pickles to any worker."""

    src: str
    dst: str
    motion: tuple[float, float] | None = None
    flow: str | None = None
    psf: str | None = None
    response: str | None = None  # None: the image file's (``clblur.io.response_for_file``)
    anchor: str = "center"
    samples: int | None = None
    saturation: float = 1.0
    exposure: str = "frames"
    backend: str = "auto"
    device: str | None = None
    memory_budget: str | None = None

    @property
    def name(self) -> str:
        return Path(self.src).name


@dataclass(frozen=True)
class Result:
    """What happened to one job: ``status`` is ``done``, ``failed``, ``finished`` (already
    done, found after claiming) or ``busy`` (another live batch holds it)."""

    name: str
    ok: bool
    seconds: float = 0.0
    backend: str | None = None
    error: str | None = None
    status: str = "done"


# --------------------------------------------------------------------------- the job key
_digests: dict[tuple, str] = {}


def _file_digest(path: str) -> list | None:
    """[size, sha256] of a file (cached per process on size, mtime and inode)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    ident = (path, st.st_size, st.st_mtime_ns, st.st_ino)
    if ident not in _digests:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _digests[ident] = h.hexdigest()
    return [st.st_size, _digests[ident]]


def response_file(spec: str | None) -> str | None:
    """The file a response spec names, or None for a built-in curve (``exp:2``, ``srgb``) or
    none given (the image file's own, ``clblur.io.response_for_file``)."""
    if spec is None or spec.split(":", 1)[0] in BUILTIN_RESPONSES:
        return None
    return spec


def job_key(job: Job) -> str:
    """SHA-256 over everything that decides the output's pixels (see the conventions)."""
    import clblur

    d = asdict(job)
    for key in ("backend", "device", "memory_budget"):  # same pixels either way
        d.pop(key)
    if d["exposure"] == "frames":  # the default before the option existed: the same keys
        d.pop("exposure")
    files = {"src": job.src, "flow": job.flow, "psf": job.psf,
             "response": response_file(job.response)}
    d["content"] = {k: _file_digest(p) for k, p in files.items() if p}
    d["clblur"] = clblur.__version__
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()


def marker_path(job: Job) -> Path:
    dst = Path(job.dst)
    return dst.parent / MARKER_DIR / f"{dst.name}.json"


def lock_path(job: Job) -> Path:
    dst = Path(job.dst)
    return dst.parent / MARKER_DIR / f"{dst.name}.lock"


def is_finished(job: Job) -> bool:
    """Output present and its marker records this very job (see module conventions)."""
    dst = Path(job.dst)
    try:
        marker = json.loads(marker_path(job).read_text())
        return dst.is_file() and marker["key"] == job_key(job) and \
            marker["output_bytes"] == dst.stat().st_size
    except (OSError, ValueError, KeyError, TypeError):
        return False


# --------------------------------------------------------------------------- claims
def _lock_is_stale(path: Path) -> bool:
    try:
        info = json.loads(path.read_text())
        age = time.time() - path.stat().st_mtime
    except FileNotFoundError:
        return False  # released meanwhile: try to claim again
    except (OSError, ValueError):
        # unreadable: its creator opened it and has not written it yet (a concurrent batch
        # reading in that instant must not take it over: both would blur the image), or a
        # crash while writing it: stale once older than a heartbeat
        try:
            return time.time() - path.stat().st_mtime > HEARTBEAT_S
        except FileNotFoundError:
            return False
    if info.get("host") == socket.gethostname():
        try:
            os.kill(int(info["pid"]), 0)
        except ProcessLookupError:
            return True
        except (PermissionError, KeyError, ValueError, TypeError):
            pass
    return age > STALE_LOCK_S


class Claim:
    """An exclusive claim on one job (a lock file refreshed by a heartbeat thread)."""

    def __init__(self, path: Path):
        self.path = path
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                os.utime(self.path)
            except OSError:
                return

    def release(self) -> None:
        self._stop.set()
        self._thread.join()
        self.path.unlink(missing_ok=True)


def _create(path: Path, body: str) -> bool:
    """Create ``path`` holding ``body`` if it does not exist (``O_EXCL``: one creator wins)."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        f.write(body)
    return True


def claim(job: Job) -> Claim | None:
    """Claim ``job`` atomically; None when another live batch holds it.

    A stale claim is taken over under a second ``O_EXCL`` file (``NAME.lock.takeover``),
    so that of two batches that both find it stale only one takes it: renaming the stale
    lock aside unguarded let the slower one move aside the claim the faster had just made,
    and both blurred the image (a reviewer measured 2 in 300 trials)."""
    path = lock_path(job)
    path.parent.mkdir(exist_ok=True)
    body = json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "time": time.time()})
    if _create(path, body):
        return Claim(path)
    if not _lock_is_stale(path):
        return None
    guard = path.with_name(path.name + ".takeover")
    if not _create(guard, body):
        try:  # another batch is taking it over; a guard left by a crash is cleared
            if time.time() - guard.stat().st_mtime > HEARTBEAT_S:
                guard.unlink(missing_ok=True)
        except OSError:
            pass
        return None
    try:
        if path.exists() and not _lock_is_stale(path):
            return None  # released and claimed again meanwhile
        path.unlink(missing_ok=True)  # the guard makes this taker the only one
        return Claim(path) if _create(path, body) else None
    finally:
        guard.unlink(missing_ok=True)


def _live_claims(out_dir: Path) -> list[str]:
    """Output names that a live batch holds."""
    locks = (out_dir / MARKER_DIR).glob("*.lock") if (out_dir / MARKER_DIR).is_dir() else []
    return [p.name.removesuffix(".lock") for p in locks if not _lock_is_stale(p)]


def partial_name(name: str) -> re.Pattern:
    """The temporary files ``clblur.io.atomic_write`` makes for an output named ``name``:
    ``.NAME.XXXXXXXX.partSUFFIX`` (``tempfile.mkstemp``'s eight random characters)."""
    return re.compile(rf"\.{re.escape(name)}\.[a-z0-9_]{{8}}\.part{re.escape(Path(name).suffix)}")


def remove_partials(out_dir: Path, names: list[str]) -> int:
    """Delete the temporary files that interrupted runs left for the outputs ``names`` (and
    their completion markers), except those of images a live batch holds.  Only those
    names: another hidden file of OUT_DIR is the user's, whatever it is called."""
    held = set(_live_claims(out_dir))
    free = [n for n in names if n not in held]
    patterns = {out_dir: [partial_name(n) for n in free],
                out_dir / MARKER_DIR: [partial_name(f"{n}.json") for n in free]}
    stale = [p for folder, found in patterns.items() if folder.is_dir()
             for p in folder.glob(".*.part*") if p.is_file()
             and any(f.fullmatch(p.name) for f in found)]
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)
