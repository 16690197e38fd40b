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
Pickles on the child's stdin and stdout.  First ``(groups, nvalid, bounds)``, the fold the
child keeps; then one ``(free, start, warm, shape_search)`` per fit, answered by ``("ok",
params)`` or ``("error", traceback text)``.  The child's stdout carries nothing else (what
the fits might print goes to stderr).  It ends at the end of its input, so it ends with
its parent too.  It runs the same code on the same values as the parent would, with BLAS on
one thread as ``clblur.study.select`` keeps it: its fits are the sequential ones, bit for bit.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

__all__ = ["FoldWorker"]


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
        self._send((groups, nvalid, bounds))

    def _send(self, obj) -> None:
        pickle.dump(obj, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self._proc.stdin.flush()

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
        """End the child (it stops at the end of its input)."""
        if self._proc.poll() is None:
            try:
                self._proc.stdin.close()
                self._proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()


def main() -> None:
    from clblur.blas import one_blas_thread
    from clblur.study.crossfit import fit

    source, sink = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing else may write to the answers' stream
    one_blas_thread()  # for the worker's life
    try:
        groups, nvalid, bounds = pickle.load(source)
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
