"""Blur every image of a folder, resumably, locally or on Dask distributed (``clblur batch``).

Conventions
-----------
* Inputs: the image files directly in IN_DIR (``IMAGE_SUFFIXES``), in name order.  Output:
  ``OUT_DIR/<same file name>``, written through ``clblur.tiling.blur_file`` (large TIFFs in
  bounded memory, atomic rename).
* Motion per image, first found: the manifest row's ``dx``/``dy``, ``flow`` or ``psf``; else
  ``--motion``, the flow named like the image in ``--flow-dir`` (``<stem>.npy`` or
  ``<stem>.flo``), or ``--psf``.  Flows are read window by window (``.npy``).
* Manifest (``--manifest CSV``): a header row, then one row per image to override; columns
  ``image`` (a path inside IN_DIR, required) and any of ``output`` (a file name in OUT_DIR),
  ``dx``, ``dy``, ``flow``, ``psf``, ``response``, ``anchor``, ``samples``, ``saturation``,
  ``exposure``.
  Empty cells keep the command line's value; ``flow``/``psf``/response-file paths are relative
  to the manifest's folder.  A row naming a missing image is reported as a failure.
* Where paths may point: every path from the manifest, the flow folder or the IN_DIR listing
  is resolved (symlinks followed) and must lie inside its root -- images inside IN_DIR, flows,
  PSFs and response files inside the manifest's folder, IN_DIR or the flow folder, outputs
  inside OUT_DIR -- or the whole batch is refused before anything is written
  (``clblur.io.resolve_inside``).
* Resuming (state in ``clblur.batch_state``): an image is finished when its output exists
  *and* its completion marker ``OUT_DIR/.clblur-batch/<output name>.json`` records the same
  job key and output size.  The key is a SHA-256 over everything that changes the result:
  the content (and size and mtime) of the input, flow, PSF and response document, every
  option that changes pixels, and the clblur version -- so editing a response JSON redoes
  exactly the outputs that use it.
* Claims: a worker claims an image by creating ``.clblur-batch/<output name>.lock`` with
  ``O_EXCL`` and refreshes its mtime while it works, so two batches into one OUT_DIR never
  blur the same image.  A lock is stale when its process is gone (same host) or it has not
  been refreshed for ``STALE_LOCK_S`` seconds; a stale lock is taken over.  A batch waits at
  the end for images another batch holds, and takes them over if that batch dies.
* Partial files (``.*.part*``) left by interrupted runs are removed, except those of images
  another live batch holds.
* A failing image is reported and skipped; the exit code is 0 when every image is finished,
  1 when any failed (2: bad command line, as for every command).
"""

from __future__ import annotations

import csv
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

from clblur.batch_state import (
    Job,
    Result,
    claim,
    is_finished,
    job_key,
    marker_path,
    response_file,
)
from clblur.errors import InputError
from clblur.io import IMAGE_FORMATS, atomic_write_text, resolve_inside

__all__ = ["IMAGE_SUFFIXES", "MANIFEST_COLUMNS", "list_images", "plan_jobs", "read_manifest",
           "run_batch", "run_job", "summary"]

IMAGE_SUFFIXES = tuple(IMAGE_FORMATS)
MANIFEST_COLUMNS = ("image", "output", "dx", "dy", "flow", "psf", "response", "anchor",
                    "samples", "saturation", "exposure")


# --------------------------------------------------------------------------- one job
def run_job(job: Job) -> Result:
    """Claim, blur one image and write its completion marker; never raises for a bad image."""
    from clblur.io import read_psf
    from clblur.tiling import blur_file

    start = time.perf_counter()
    held = None
    try:
        if job.problem:
            raise InputError(job.problem)
        held = claim(job)
        if held is None:
            return Result(job.name, True, status="busy")
        if is_finished(job):  # another batch finished it between our check and our claim
            return Result(job.name, True, status="finished")
        key = job_key(job)
        motion = job.motion if job.motion is not None else \
            job.flow if job.flow is not None else read_psf(job.psf)
        run = blur_file(job.src, job.dst, motion, response=job.response, anchor=job.anchor,
                        samples=job.samples, backend=job.backend, saturation=job.saturation,
                        device=job.device, memory_budget=job.memory_budget,
                        exposure=job.exposure)
        atomic_write_text(marker_path(job), json.dumps(
            {"key": key, "output_bytes": Path(job.dst).stat().st_size,
             "backend": run.backend, "tiles": run.tiles}, indent=1) + "\n")
        return Result(job.name, True, time.perf_counter() - start, run.backend)
    except Exception as e:  # one bad image must not stop the batch
        msg = " ".join(str(e).split())
        return Result(job.name, False, time.perf_counter() - start,
                      error=msg if isinstance(e, InputError) else f"{type(e).__name__}: {msg}",
                      status="failed")
    finally:
        if held is not None:
            held.release()


# --------------------------------------------------------------------------- planning
def list_images(in_dir: Path) -> list[Path]:
    """The image files directly in ``in_dir``, by name; a symlink must point inside it."""
    found = []
    for p in sorted(in_dir.iterdir()):
        if p.name.startswith(".") or p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        if p.is_symlink():
            resolve_inside(in_dir, p.name, f"{in_dir}: image symlink")
        if p.is_file():
            found.append(p)
    return found


def read_manifest(path: Path) -> dict[str, dict[str, str]]:
    """Manifest rows keyed by image name (see module conventions)."""
    if not path.is_file():
        raise InputError(f"manifest not found: {path}")
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            columns = [c.strip() for c in reader.fieldnames or []]
            unknown = sorted(set(columns) - set(MANIFEST_COLUMNS))
            if "image" not in columns or unknown:
                raise InputError(f"manifest {path}: needs an 'image' column and only "
                                 f"{', '.join(MANIFEST_COLUMNS)}; unknown: {', '.join(unknown)}")
            rows: dict[str, dict[str, str]] = {}
            for n, row in enumerate(reader, start=2):
                if None in row:
                    raise InputError(f"manifest {path} line {n}: more cells than columns")
                row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
                if not row.get("image"):
                    raise InputError(f"manifest {path} line {n}: empty image name")
                if row["image"] in rows:
                    raise InputError(f"manifest {path} line {n}: {row['image']} listed twice")
                rows[row["image"]] = {k: v for k, v in row.items() if v}
    except (UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"manifest {path}: not a UTF-8 CSV file ({e})") from None
    return rows


def _row_job(job: Job, row: dict[str, str], roots: list[Path], out_dir: Path) -> Job:
    """Apply one manifest row's overrides.  A path outside its root raises ``InputError``
    (the batch is refused); a malformed value becomes the job's problem."""
    where = f"manifest row for {row['image']}"
    changes: dict = {}
    if "output" in row:
        name = row["output"]
        if Path(name).name != name or name in (".", ".."):
            raise InputError(f"{where}: output {name!r} must be a file name in OUT_DIR")
        changes["dst"] = str(resolve_inside(out_dir, name, f"{where}: output"))
    for key in ("flow", "psf"):
        if key in row:
            changes[key] = str(resolve_inside(roots, row[key], f"{where}: {key}"))
    if "response" in row and response_file(row["response"]) is not None:
        changes["response"] = str(resolve_inside(roots, row["response"], f"{where}: response"))
    try:
        given = [k for k in ("dx", "flow", "psf") if k in row] + \
            (["dy"] if "dy" in row and "dx" not in row else [])
        if len(given) > 1 or ("dx" in row) != ("dy" in row):
            raise ValueError("give dx and dy together, or flow, or psf (one motion)")
        if "dx" in row:
            changes.update(motion=(float(row["dx"]), float(row["dy"])), flow=None, psf=None)
        for key in ("flow", "psf"):
            if key in row:
                changes.update(motion=None, **{k: None for k in ("flow", "psf") if k != key})
        for key, cast in (("response", str), ("anchor", str), ("samples", int),
                          ("saturation", float), ("exposure", str)):
            if key in row and key not in changes:
                changes[key] = cast(row[key])
        return replace(job, **changes)
    except ValueError as e:
        return replace(job, **{k: v for k, v in changes.items() if k == "dst"},
                       problem=f"{where}: {e}")


def plan_jobs(in_dir: Path, out_dir: Path, defaults: Job, flow_dir: Path | None = None,
              manifest: Path | None = None) -> list[Job]:
    """One job per image (and per manifest row naming a missing image); ``InputError`` for
    a path outside its allowed folder (see the module conventions)."""
    in_dir, out_dir = Path(in_dir).resolve(), Path(out_dir).resolve()
    if not in_dir.is_dir():
        raise InputError(f"input folder not found: {in_dir}")
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"OUT_DIR {out_dir} exists and is not a folder")
    if in_dir == out_dir:
        raise InputError("OUT_DIR must differ from IN_DIR (inputs are never overwritten)")
    if flow_dir is not None:
        if not Path(flow_dir).is_dir():
            raise InputError(f"flow folder not found: {flow_dir}")
        flow_dir = Path(flow_dir).resolve()
    rows = read_manifest(Path(manifest)) if manifest is not None else {}
    roots = [Path(manifest).resolve().parent] if manifest is not None else []
    roots += [in_dir] + ([flow_dir] if flow_dir is not None else [])
    srcs = {p.name: p for p in list_images(in_dir)}
    for name in sorted(rows):  # a manifest image must be a path inside IN_DIR
        path = resolve_inside(in_dir, name, f"manifest {manifest}: image")
        srcs.setdefault(name, path)  # missing ones are reported when run
    jobs = []
    for name, src in srcs.items():
        job = replace(defaults, src=str(src), dst=str(out_dir / src.name))
        missing = "no motion given (use --motion, --flow-dir, --psf or the manifest)"
        if flow_dir is not None:
            found = [f for f in (flow_dir / (src.stem + s) for s in (".npy", ".flo"))
                     if f.is_file()]
            if found:
                flow = resolve_inside(flow_dir, found[0].name, f"flow for {name}")
                job = replace(job, flow=str(flow))
            else:
                missing = f"no flow {src.stem}.npy or .flo in {flow_dir}"
        if name in rows:
            job = _row_job(job, rows[name], roots, out_dir)
        if job.problem is None and job.motion is None and job.flow is None and job.psf is None:
            job = replace(job, problem=missing)
        jobs.append(job)
    dsts = [j.dst for j in jobs]
    if len(set(dsts)) != len(dsts):
        raise InputError("two images would be written to the same output name")
    return jobs


# --------------------------------------------------------------------------- running
def run_batch(jobs: list[Job], scheduler: str | None = None, progress: bool = True,
              force: bool = False, wait_s: float = 0.5) -> tuple[list[Result], int]:
    """Run the unfinished jobs; returns (results of the jobs run, number already finished).

    Jobs another live batch holds are waited for at the end (polling every ``wait_s``), and
    run here if that batch dies before finishing them."""
    from tqdm import tqdm

    todo = [j for j in jobs if force or not is_finished(j)]
    skipped = len(jobs) - len(todo)
    bar = tqdm(total=len(todo), unit="img", disable=None if progress else True, desc="batch",
               file=sys.stderr)
    results: list[Result] = []
    try:
        if scheduler is None:
            for job in todo:
                results.append(run_job(job))
                _advance(bar, results[-1])
        else:
            results = _run_distributed(todo, scheduler, bar)
        busy = {r.name for r in results if r.status == "busy"}
        results = [r for r in results if r.status != "busy"]
        waiting = [j for j in todo if j.name in busy]
        while waiting:  # images another batch holds: wait for it, or take over if it died
            left = []
            for job in waiting:
                if is_finished(job):
                    results.append(Result(job.name, True, status="finished"))
                    _advance(bar, results[-1])
                    continue
                r = run_job(job)
                if r.status == "busy":
                    left.append(job)
                else:
                    results.append(r)
                    _advance(bar, r)
            waiting = left
            if waiting:
                time.sleep(wait_s)
    finally:
        bar.close()
    skipped += sum(r.status == "finished" for r in results)
    return [r for r in results if r.status != "finished"], skipped


def _advance(bar, result: Result) -> None:
    if result.status == "busy":
        return
    if not result.ok:
        bar.write(f"FAILED {result.name}: {result.error}")
    bar.update(1)


def _run_distributed(todo: list[Job], scheduler: str, bar) -> list[Result]:
    from distributed import as_completed

    from clblur.distributed import client_for

    results = []
    with client_for(scheduler) as client:
        futures = {client.submit(run_job, job, pure=False, key=f"clblur-{i}-{job.name}"): job
                   for i, job in enumerate(todo)}
        for fut in as_completed(futures):
            try:
                result = fut.result()
            except Exception as e:  # the worker died or could not run the task at all
                result = Result(futures[fut].name, False, error=f"{type(e).__name__}: {e}",
                                status="failed")
            results.append(result)
            _advance(bar, result)
    return results


def summary(results: list[Result], skipped: int) -> str:
    """The batch's report: counts, then one line per failed image."""
    done = [r for r in results if r.ok]
    failed = [r for r in results if not r.ok]
    backends = sorted({r.backend for r in done if r.backend})
    lines = [f"{len(done)} blurred, {skipped} already finished, {len(failed)} failed"
             + (f" (backend: {', '.join(backends)}; {sum(r.seconds for r in done):.1f} s)"
                if done else "")]
    lines += [f"  failed: {r.name}: {r.error}" for r in sorted(failed, key=lambda r: r.name)]
    return "\n".join(lines)
