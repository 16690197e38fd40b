"""Fold 1's fits in a process of its own, beside fold 0's (``clblur.study.crossfit.Folds``).

Why a process: a fit evaluates the likelihood of a few thousand pooled rows a hundred
thousand times, so it is bound by the interpreter, and two threads sharing its lock ran
slower than one fit after the other (a series study: 278 s against 246 s).  Why a plain
``python -m clblur.study.fold_worker`` child rather than ``multiprocessing``: its spawn and
forkserver methods run the caller's main script again in the child (a script without an
``if __name__ == "__main__"`` guard would study itself), and fork copies a process whose
other threads (an OpenCL runtime, a progress bar) may hold locks.

Conventions
-----------
Pickles on the child's stdin and stdout.  First the fold the child keeps, ``(groups, nvalid,
bounds)``, in two messages: ``(path, sizes)``, then the fold.  Where ``path`` is a file, the
fold was pickled with its arrays out of band (protocol 5) and ``path`` holds their bytes, one
after the other at 64-byte boundaries (``sizes``); the child maps the file copy-on-write,
removes it and reads its arrays from the mapping.  Why: a 600 x 600 blur pair's fold
pickles to 1.7 GB, and pickling it in band and through the pipe took 13 s of a 110 s study
(``bench/results_study.md``, 2026-11-28); the arrays' bytes written to a file in
``/dev/shm`` (else the temporary folder) are one copy, and the child shares their pages
until it writes to one.  Where ``path`` is None (a fold under ``OUT_OF_BAND_BYTES``, or no
folder with room for it) the fold follows in band.  Then one ``(free, start, warm,
shape_search, search)`` per fit, answered by ``("ok", params)`` or ``("error", traceback
text)``.  The child's stdout carries nothing else (what the fits might print goes to
stderr).  It ends at the end of its input, so it ends with its parent too.  It runs the
same code on the same values as the parent would, with BLAS on one thread as
``clblur.study.select`` keeps it: its fits are the sequential ones, bit for bit.
"""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["OUT_OF_BAND_BYTES", "FoldWorker"]

# a fold whose arrays hold at least this many bytes goes to the child through a file
# (module Conventions); smaller ones through the pipe, where a file's cost would dominate
OUT_OF_BAND_BYTES = 64 << 20
_ALIGN = 64  # each array's bytes start at a multiple of this in the file


def _aligned(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


def _scratch_folder(nbytes: int) -> str | None:
    """A folder with room for ``nbytes`` and a margin: ``/dev/shm`` (memory, where a
    container's is often only 64 MB) or the temporary folder; None if neither has it."""
    for folder in ("/dev/shm", tempfile.gettempdir()):
        try:
            if os.path.isdir(folder) and shutil.disk_usage(folder).free > 2 * nbytes:
                return folder
        except OSError:
            continue
    return None


class FoldWorker:
    """A child process that holds one fold and fits models on it, one request at a time.

    Parameters
    ----------
    groups : list of Group
        The fold's packed groups.
    nvalid : int
        Its valid values (the likelihood's normaliser).
    bounds : dict
        The physical bounds of the parameters (``crossfit.physical_bounds``).
    """

    def __init__(self, groups: list, nvalid: int, bounds: dict):
        env = dict(os.environ)
        # the child imports the clblur this process runs, wherever that was found
        here = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (here, env.get("PYTHONPATH")) if p)
        self._proc = subprocess.Popen([sys.executable, "-m", "clblur.study.fold_worker"],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        self._path: str | None = None
        self._send_fold((groups, nvalid, bounds))

    def _send(self, obj) -> None:
        pickle.dump(obj, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self._proc.stdin.flush()

    def _send_fold(self, fold) -> None:
        """The fold, its arrays through a file where they are large (module Conventions)."""
        buffers: list[pickle.PickleBuffer] = []
        head = pickle.dumps(fold, protocol=5, buffer_callback=buffers.append)
        raws = [b.raw() for b in buffers]
        total = sum(_aligned(r.nbytes) for r in raws)
        folder = _scratch_folder(total) if total >= OUT_OF_BAND_BYTES else None
        if folder is not None:
            fd, path = tempfile.mkstemp(prefix="clblur-fold-", suffix=".bin", dir=folder)
            try:
                with os.fdopen(fd, "wb") as f:
                    for r in raws:
                        f.write(r)
                        f.write(bytes(_aligned(r.nbytes) - r.nbytes))
            except OSError:  # out of room after all: in band
                Path(path).unlink(missing_ok=True)
            else:
                self._path = path
                self._send((path, [r.nbytes for r in raws]))
                self._proc.stdin.write(head)
                self._proc.stdin.flush()
                return
        del head, raws, buffers
        self._send((None, []))
        self._send(fold)

    def submit(self, free: list[str], start: dict, warm: dict | None,
               shape_search: bool, search: bool = True) -> None:
        """Start a fit (``crossfit.fit`` on the held fold); ``result`` returns it."""
        self._send((free, start, warm, shape_search, search))

    def result(self) -> dict:
        """The parameters of the fit last submitted."""
        try:
            status, value = pickle.load(self._proc.stdout)
        except EOFError:
            raise RuntimeError(f"the study's fold worker ended (exit code "
                               f"{self._proc.wait()}); see its message above") from None
        if status != "ok":
            raise RuntimeError(f"a fit in the study's fold worker failed:\n{value}")
        return value

    def close(self) -> None:
        """End the child (it stops at the end of its input); remove the fold's file if the
        child did not (it removes it once mapped)."""
        if self._proc.poll() is None:
            try:
                self._proc.stdin.close()
                self._proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
        if self._path is not None:
            Path(self._path).unlink(missing_ok=True)
            self._path = None


def _receive_fold(source):
    """The fold ``FoldWorker._send_fold`` sent."""
    path, sizes = pickle.load(source)
    if path is None:
        return pickle.load(source)
    import numpy as np

    # copy-on-write: the arrays are writable as the in-band ones are, and share the file's
    # pages until written; the name goes at once, the mapping keeps the pages
    data = np.memmap(path, mode="c") if sum(sizes) else np.empty(0, np.uint8)
    try:
        os.unlink(path)
    except OSError:  # a system that keeps a mapped file's name: the parent removes it
        pass
    views, at = [], 0
    for n in sizes:
        views.append(data[at:at + n])
        at += _aligned(n)
    return pickle.load(source, buffers=views)


def main() -> None:
    from clblur.blas import one_blas_thread
    from clblur.study.crossfit import fit

    source, sink = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing else may write to the answers' stream
    one_blas_thread()  # for the worker's life
    try:
        groups, nvalid, bounds = _receive_fold(source)
        while True:
            try:
                free, start, warm, shape_search, search = pickle.load(source)
            except EOFError:
                return
            try:
                answer = ("ok", fit(groups, free, start, nvalid, bounds, warm, shape_search,
                                    search))
            except Exception:  # the parent raises it, with this traceback
                import traceback

                answer = ("error", traceback.format_exc())
            pickle.dump(answer, sink, protocol=pickle.HIGHEST_PROTOCOL)
            sink.flush()
    except (KeyboardInterrupt, BrokenPipeError):  # the parent was interrupted or ended
        return


if __name__ == "__main__":
    main()
