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
  to the manifest's folder.
* Response per image: the manifest cell, else ``--response``, else the file's own
  (``clblur.io.response_for_file``: ``linear`` for an EXR, which holds scene-linear light,
  ``exp`` for the rest), as ``clblur blur`` chooses it.
* Checked before any work (``plan_jobs``; ``InputError``, nothing written): the options, every
  manifest cell (the error names the manifest, its line and the column), the manifest's CSV
  itself (a quote left open), that each image has a motion, and that each image, flow file and
  PSF a row or option names exists (PSFs are read and validated once).  The cells pass the
  library's own checks (``check_field``), the same ones ``run_job`` and the blur apply.
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
* An image that fails while it is processed (a corrupt file, a flow of the wrong shape) is
  reported and skipped; the exit code is 0 when every image is finished, 1 when any failed
  (2: bad input found before any work, as for every command).
"""

from __future__ import annotations

import csv
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

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
from clblur.io import (
    IMAGE_FORMATS,
    atomic_write_text,
    read_psf,
    require_file,
    resolve_inside,
    response_for_file,
)
from clblur.motion import anchor_value, check_exposure, parse_motion, psf, time_weights
from clblur.pixels import validate_saturation
from clblur.responses import check_spec

__all__ = ["IMAGE_SUFFIXES", "MANIFEST_COLUMNS", "ManifestRow", "check_field", "check_job",
           "list_images", "plan_jobs", "read_manifest", "run_batch", "run_job", "summary"]

IMAGE_SUFFIXES = tuple(IMAGE_FORMATS)
MANIFEST_COLUMNS = ("image", "output", "dx", "dy", "flow", "psf", "response", "anchor",
                    "samples", "saturation", "exposure")


# --------------------------------------------------------------------------- one job
def run_job(job: Job) -> Result:
    """Claim, blur one image and write its completion marker; never raises for a bad image."""
    from clblur.tiling import blur_file

    start = time.perf_counter()
    held = None
    try:
        check_job(job)  # planned jobs passed it already; a job built by hand may not have
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


class ManifestRow(NamedTuple):
    """One manifest row: its line in the CSV file and its non-empty cells by column."""

    line: int
    cells: dict[str, str]


def read_manifest(path: Path) -> dict[str, ManifestRow]:
    """Manifest rows keyed by image name (see module conventions); ``InputError`` for a file
    that is not a well-formed UTF-8 CSV with the allowed columns."""
    if not path.is_file():
        raise InputError(f"manifest not found: {path}")
    start = 1  # the line the record being read starts on
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f, strict=True)  # strict: a quote left open is an error
            columns = [c.strip() for c in reader.fieldnames or []]
            unknown = sorted(set(columns) - set(MANIFEST_COLUMNS))
            if "image" not in columns or unknown:
                found = f"unknown: {', '.join(unknown)}" if unknown else (
                    f"columns found: {', '.join(columns)}" if columns else "the file is empty")
                raise InputError(f"manifest {path}: needs an 'image' column and only "
                                 f"{', '.join(MANIFEST_COLUMNS)}; {found}")
            rows: dict[str, ManifestRow] = {}
            start = reader.line_num + 1
            for row in reader:
                n, start = start, reader.line_num + 1
                where = f"manifest {path} line {n}"
                if None in row:
                    raise InputError(f"{where}: more cells than columns")
                if any("\n" in v or "\r" in v for v in row.values() if v):
                    raise InputError(f"{where}: malformed CSV, a cell spans lines (a quote "
                                     "left open?)")
                row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
                if not row.get("image"):
                    raise InputError(f"{where}: empty image name")
                if row["image"] in rows:
                    raise InputError(f"{where}: {row['image']} listed twice")
                rows[row["image"]] = ManifestRow(n, {k: v for k, v in row.items() if v})
    except UnicodeDecodeError as e:
        raise InputError(f"manifest {path}: not a UTF-8 CSV file ({e})") from None
    except csv.Error as e:
        hint = " (a quote left open?)" if "end of data" in str(e) else ""
        raise InputError(f"manifest {path} line {start}: malformed CSV: {e}{hint}") from None
    return rows


# ---------------------------------------------------------------- what a job may hold
# field of ``Job`` -> the library's own check of its value (the one the blur applies)
_CHECKS = {"motion": lambda v: parse_motion(v, (1, 1)),
           "flow": lambda v: require_file(v, "flow"),
           "psf": lambda v: psf(read_psf(require_file(v, "PSF"))),
           "response": check_spec,
           "anchor": anchor_value,
           "samples": lambda v: time_weights(v, None),
           "saturation": validate_saturation,
           "exposure": check_exposure}


def check_field(field: str, value) -> None:
    """Refuse (``InputError``, one line) a value of the ``Job`` field ``field`` that the blur
    would refuse: the one check of each field, applied by ``plan_jobs`` to the options and to
    every manifest cell before any work, and by ``run_job``.  Content read window by window
    while blurring (the image, a flow's values) is checked then."""
    if value is None:
        return
    try:
        _CHECKS[field](value)
    except (ValueError, TypeError) as e:  # InputError too: its message, without a class name
        raise InputError(" ".join(str(e).split())) from None


def check_job(job: Job) -> None:
    """``check_field`` for every field of ``job``, and exactly one motion."""
    given = [k for k in ("motion", "flow", "psf") if getattr(job, k) is not None]
    if len(given) != 1:
        raise InputError(f"{job.name}: needs exactly one of motion, flow, psf, got "
                         f"{', '.join(given) or 'none'}")
    for field in _CHECKS:
        check_field(field, getattr(job, field))


# option of ``clblur batch`` -> the job field it sets (named in errors about the options)
_OPTIONS = {"motion": "--motion", "flow": "flow", "psf": "--psf", "response": "--response",
            "anchor": "--anchor", "samples": "--samples", "saturation": "--saturation",
            "exposure": "--exposure"}
# manifest column -> how its text becomes the job field's value
_CASTS = {"anchor": str, "exposure": str, "samples": int, "saturation": float}


def _row_job(job: Job, row: ManifestRow, where: str, roots: list[Path], out_dir: Path) -> Job:
    """Apply one manifest row's cells, each checked (``InputError`` naming ``where``, the row's
    line, and the column)."""
    cells = row.cells
    changes: dict = {}

    def bad(columns: str, message: str) -> InputError:
        label = "columns" if ", " in columns.split(" (")[0] else "column"
        return InputError(f"{where} line {row.line}, {label} {columns}: {message}")

    def check(field: str, value, columns: str) -> None:
        try:
            check_field(field, value)
        except InputError as e:
            raise bad(columns, str(e)) from None

    def pixels(column: str) -> float:
        try:
            return float(cells[column])
        except ValueError:
            raise bad(column, f"must be a number of pixels, got {cells[column]!r}") from None

    def inside(folders, column: str) -> str:
        """The column's path resolved inside ``folders`` (``resolve_inside``)."""
        try:
            return str(resolve_inside(folders, cells[column], column))
        except InputError as e:
            raise bad(column, str(e)) from None

    if "output" in cells:
        name = cells["output"]
        if Path(name).name != name or name in (".", ".."):
            raise bad("output", f"{name!r} must be a file name in OUT_DIR")
        if Path(name).suffix.lower() not in IMAGE_SUFFIXES:
            raise bad("output", f"{name!r}: unknown extension; use one of "
                                f"{', '.join(IMAGE_SUFFIXES)}")
        changes["dst"] = inside(out_dir, "output")
    forms = [k for k in ("dx", "flow", "psf") if k in cells] + \
        (["dy"] if "dy" in cells and "dx" not in cells else [])
    if len(forms) > 1 or ("dx" in cells) != ("dy" in cells):
        raise bad(", ".join(forms), "give dx and dy together, or flow, or psf (one motion)")
    if "dx" in cells:
        motion = (pixels("dx"), pixels("dy"))
        check("motion", motion, f"dx, dy ({cells['dx']}, {cells['dy']})")
        changes.update(motion=motion, flow=None, psf=None)
    for key in ("flow", "psf"):
        if key in cells:
            path = inside(roots, key)
            check(key, path, key)
            changes.update(motion=None, flow=None, psf=None)
            changes[key] = path
    if "response" in cells:
        spec = cells["response"]
        if response_file(spec) is not None:
            spec = inside(roots, "response")
        check("response", spec, "response")
        changes["response"] = spec
    for key, cast in _CASTS.items():
        if key in cells:
            try:
                value = cast(cells[key])
            except ValueError:
                kind = "an integer" if cast is int else "a number"
                raise bad(key, f"must be {kind}, got {cells[key]!r}") from None
            check(key, value, key)
            changes[key] = value
    return replace(job, **changes)


def plan_jobs(in_dir: Path, out_dir: Path, defaults: Job, flow_dir: Path | None = None,
              manifest: Path | None = None) -> list[Job]:
    """One checked job per image in IN_DIR and per manifest row; ``InputError`` for anything
    wrong that is knowable before reading the images (see the module conventions).  Writes
    nothing."""
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
    for field, option in _OPTIONS.items():  # the options: once, not once per image
        try:
            check_field(field, getattr(defaults, field))
        except InputError as e:
            raise InputError(f"{option}: {e}") from None
    rows = read_manifest(Path(manifest)) if manifest is not None else {}
    roots = [Path(manifest).resolve().parent] if manifest is not None else []
    roots += [in_dir] + ([flow_dir] if flow_dir is not None else [])
    srcs = {p.name: p for p in list_images(in_dir)}
    for name in sorted(rows):  # a manifest image must be an image file inside IN_DIR
        where = f"manifest {manifest} line {rows[name].line}, column image"
        path = resolve_inside(in_dir, name, f"manifest {manifest}: image")
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            raise InputError(f"{where}: {name!r} is not an image file name (expected one of "
                             f"{', '.join(IMAGE_SUFFIXES)})")
        srcs.setdefault(name, require_file(path, f"{where}: image"))
    jobs = []
    for name, src in srcs.items():
        job = replace(defaults, src=str(src), dst=str(out_dir / src.name))
        if flow_dir is not None:
            found = [f for f in (flow_dir / (src.stem + s) for s in (".npy", ".flo"))
                     if f.is_file()]
            if found:
                flow = resolve_inside(flow_dir, found[0].name, f"flow for {name}")
                job = replace(job, flow=str(flow))
        if name in rows:
            job = _row_job(job, rows[name], f"manifest {manifest}", roots, out_dir)
        if job.response is None:  # neither a cell nor --response: the file's own
            job = replace(job, response=response_for_file(src))
        if job.motion is None and job.flow is None and job.psf is None:
            if flow_dir is not None:
                raise InputError(f"no flow for {name}: {flow_dir / src.stem}.npy or .flo not "
                                 "found" + (", and its manifest row gives no dx, dy, flow or "
                                            "psf" if name in rows else ""))
            if manifest is not None:
                why = f"its row of {manifest} gives no dx, dy, flow or psf" if name in rows \
                    else f"{manifest} has no row for it"
                raise InputError(f"no motion for {name}: {why}, and no --motion, --flow-dir "
                                 "or --psf is given")
            raise InputError("no motion given: use --motion, --flow-dir, --psf or --manifest")
        jobs.append(job)
    dsts = [j.dst for j in jobs]
    if len(set(dsts)) != len(dsts):
        raise InputError("two images would be written to the same output name")
    _refuse_outputs_over_inputs(jobs, manifest)
    return jobs


def _refuse_outputs_over_inputs(jobs: list[Job], manifest: Path | None) -> None:
    """An output that is one of the batch's inputs (an image, flow, PSF or response file of
    any job, or the manifest), however spelled, is refused before anything is written: the
    check inside each blur came only when that image's turn came (other outputs were written
    by then), and a PSF or manifest kept in OUT_DIR was not checked at all (overwritten)."""
    inputs: dict[Path, str] = {}
    if manifest is not None:
        inputs[Path(manifest).resolve()] = "the manifest"
    for job in jobs:
        for what, path in (("image", job.src), ("flow", job.flow), ("PSF", job.psf),
                           ("response", response_file(job.response))):
            if path is not None:
                inputs.setdefault(Path(path).resolve(), f"{job.name}'s {what}")
    for job in jobs:
        which = inputs.get(Path(job.dst).resolve())
        if which is not None:
            raise InputError(f"the output {job.dst} would overwrite {which} (inputs are never "
                             "overwritten); keep inputs out of OUT_DIR or name another output")


# --------------------------------------------------------------------------- running
def run_batch(jobs: list[Job], scheduler: str | None = None, progress: bool = True,
              force: bool = False, wait_s: float = 0.5,
              client=None) -> tuple[list[Result], int]:
    """Run the unfinished jobs; returns (results of the jobs run, number already finished).

    ``scheduler`` (``clblur.distributed.client_for``) or an open ``distributed.Client``
    (``client``) runs them on Dask distributed.  Jobs another live batch holds are waited
    for at the end (polling every ``wait_s``), and run here if that batch dies before
    finishing them."""
    from tqdm import tqdm

    todo = [j for j in jobs if force or not is_finished(j)]
    skipped = len(jobs) - len(todo)
    bar = tqdm(total=len(todo), unit="img", disable=None if progress else True, desc="batch",
               file=sys.stderr)
    results: list[Result] = []
    try:
        if client is not None:
            results = _run_on(client, todo, bar)
        elif scheduler is not None:
            from clblur.distributed import client_for

            with client_for(scheduler) as opened:
                results = _run_on(opened, todo, bar)
        else:
            for job in todo:
                results.append(run_job(job))
                _advance(bar, results[-1])
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


def _run_on(client, todo: list[Job], bar) -> list[Result]:
    """Run ``todo`` on a ``distributed.Client``."""
    from distributed import as_completed

    results = []
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
