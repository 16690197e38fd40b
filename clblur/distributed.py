"""Dask distributed set-up for batches: a LocalCluster or an existing scheduler.

Conventions
-----------
* ``local`` / ``local:N``: a LocalCluster of N single-threaded worker *processes* (default: one
  per CPU), so each worker owns one OpenCL context; any other text is a scheduler address
  (``tcp://host:8786``) of a running cluster (``dask scheduler`` + ``dask worker``).
* Workers create their OpenCL context lazily, on their first OpenCL blur (``clblur.opencl``
  keeps one per process and device); tasks carry only paths and options, never OpenCL objects.
* Each worker gets its own PoCL kernel cache, ``POCL_CACHE_DIR=<base>/clblur-<worker name>``,
  with ``<base>`` the worker's inherited ``POCL_CACHE_DIR`` or else its local directory, so
  concurrent workers never race on one cache.  Set before any OpenCL use in that process.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from distributed import WorkerPlugin

from clblur.errors import InputError

__all__ = ["PoclCachePerWorker", "client_for", "parse_scheduler"]


def parse_scheduler(text: str) -> tuple[str, int | None]:
    """``"local"``/``"local:N"`` -> ("local", N or None); an address -> (address, None)."""
    text = text.strip()
    if text == "local" or text.startswith("local:"):
        if text == "local":
            return "local", None
        try:
            n = int(text.split(":", 1)[1])
        except ValueError:
            n = 0
        if n < 1:
            raise InputError(f"--scheduler local:N needs a positive worker count, got {text!r}")
        return "local", n
    if not text:
        raise InputError("--scheduler needs 'local', 'local:N' or a scheduler address")
    return text, None


class PoclCachePerWorker(WorkerPlugin):
    """Worker plugin: a private PoCL kernel cache for every worker process."""

    name = "clblur-pocl-cache"

    def setup(self, worker) -> None:
        base = os.environ.get("POCL_CACHE_DIR") or worker.local_directory
        label = re.sub(r"[^A-Za-z0-9_.-]", "_", str(worker.name))
        path = Path(base) / f"clblur-{label}"
        path.mkdir(parents=True, exist_ok=True)
        os.environ["POCL_CACHE_DIR"] = str(path)


@contextmanager
def client_for(scheduler: str, timeout: str = "20s") -> Iterator[object]:
    """A ``distributed.Client`` for ``scheduler`` (see ``parse_scheduler``), closed on exit
    (with its LocalCluster, if it made one); ``timeout`` to reach an existing scheduler."""
    from distributed import Client, LocalCluster

    where, n = parse_scheduler(scheduler)
    if where == "local":
        cluster = LocalCluster(n_workers=n or os.cpu_count() or 1, threads_per_worker=1,
                               processes=True, dashboard_address=":0",
                               silence_logs=logging.ERROR)
        try:
            with Client(cluster) as client:
                client.register_plugin(PoclCachePerWorker())
                yield client
        finally:
            cluster.close()
        return
    try:
        client = Client(where, timeout=timeout)
    except OSError as e:
        raise InputError(f"cannot reach the Dask scheduler at {where}: {e}") from None
    try:
        client.register_plugin(PoclCachePerWorker())
        yield client
    finally:
        client.close()
