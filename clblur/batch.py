"""``clblur batch``: blur every image of a folder, resumably, locally or on Dask distributed.

Conventions
-----------
* Inputs: the image files directly in IN_DIR (``IMAGE_SUFFIXES``), in name order.  Output:
  ``OUT_DIR/<same file name>``, written through ``clblur.tiling.blur_file`` (large TIFFs in
  bounded memory, atomic rename).
* Motion per image, first found: the manifest row's ``dx``/``dy``, ``flow`` or ``psf``; else
  ``--motion``, the flow named like the image in ``--flow-dir`` (``<stem>.npy`` or
  ``<stem>.flo``), or ``--psf``.  Flows are read window by window (``.npy``).
* Manifest (``--manifest CSV``): a header row, then one row per image to override; columns
  ``image`` (file name in IN_DIR, required) and any of ``output``, ``dx``, ``dy``, ``flow``,
  ``psf``, ``response``, ``anchor``, ``samples``, ``saturation``.  Empty cells keep the command
  line's value; ``flow``/``psf`` paths are relative to the manifest's folder.  A row naming a
  missing image is reported as a failure.
* Resuming: an image is finished when its output exists *and* its completion marker
  ``OUT_DIR/.clblur-batch/<output name>.json`` records the same job (input size and mtime,
  motion files, options) and output size.  Anything else -- no marker, a changed input or
  option, an output left from a crash -- is redone; stray temporary ``.*.part*`` files from
  interrupted runs are removed first.  Run one batch per OUT_DIR at a time.
* A failing image is reported and skipped; the exit code is 0 when every image is finished,
  1 when any failed (2: bad command line, as for every command).
"""

from __future__ import annotations

import csv
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from clblur.io import atomic_write_text

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".webp")
MARKER_DIR = ".clblur-batch"
MANIFEST_COLUMNS = ("image", "output", "dx", "dy", "flow", "psf", "response", "anchor",
                    "samples", "saturation")


@dataclass(frozen=True)
class Job:
    """One image to blur: only paths and plain options, so it pickles to any worker."""

    src: str
    dst: str
    motion: tuple[float, float] | None = None
    flow: str | None = None
    psf: str | None = None
    response: str = "exp"
    anchor: str = "center"
    samples: int | None = None
    saturation: float = 1.0
    backend: str = "auto"
    device: str | None = None
    memory_budget: str | None = None
    problem: str | None = None  # known before running (e.g. no motion): reported as failed

    @property
    def name(self) -> str:
        return Path(self.src).name

    def identity(self) -> dict:
        """What decides whether an existing output is this job's result."""
        d = asdict(self)
        for key in ("backend", "device", "memory_budget", "problem"):  # same pixels either way
            d.pop(key)
        d["inputs"] = {p: _stat(p) for p in (self.src, self.flow, self.psf) if p}
        return json.loads(json.dumps(d))  # as read back from a marker (tuples -> lists)


@dataclass(frozen=True)
class Result:
    name: str
    ok: bool
    seconds: float = 0.0
    backend: str | None = None
    error: str | None = None


def _stat(path: str) -> list[int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def marker_path(job: Job) -> Path:
    dst = Path(job.dst)
    return dst.parent / MARKER_DIR / f"{dst.name}.json"


def is_finished(job: Job) -> bool:
    """Output present and its marker records this very job (see module conventions)."""
    dst = Path(job.dst)
    try:
        marker = json.loads(marker_path(job).read_text())
        return dst.is_file() and marker["job"] == job.identity() and \
            marker["output_bytes"] == dst.stat().st_size
    except (OSError, ValueError, KeyError, TypeError):
        return False


def run_job(job: Job) -> Result:
    """Blur one image and write its completion marker; never raises for a bad image."""
    from clblur.io import read_psf
    from clblur.tiling import blur_file

    start = time.perf_counter()
    try:
        if job.problem:
            raise ValueError(job.problem)
        motion = job.motion if job.motion is not None else \
            job.flow if job.flow is not None else read_psf(job.psf)
        run = blur_file(job.src, job.dst, motion, response=job.response, anchor=job.anchor,
                        samples=job.samples, backend=job.backend, saturation=job.saturation,
                        device=job.device, memory_budget=job.memory_budget)
        marker_path(job).parent.mkdir(exist_ok=True)
        atomic_write_text(marker_path(job), json.dumps(
            {"job": job.identity(), "output_bytes": Path(job.dst).stat().st_size,
             "backend": run.backend, "tiles": run.tiles}, indent=1) + "\n")
        return Result(job.name, True, time.perf_counter() - start, run.backend)
    except Exception as e:  # one bad image must not stop the batch
        return Result(job.name, False, time.perf_counter() - start,
                      error=f"{type(e).__name__}: {e}")


# --------------------------------------------------------------------------- planning
def list_images(in_dir: Path) -> list[Path]:
    return sorted(p for p in in_dir.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and
                  not p.name.startswith("."))


def read_manifest(path: Path) -> dict[str, dict[str, str]]:
    """Manifest rows keyed by image name (see module conventions)."""
    if not path.is_file():
        raise ValueError(f"manifest not found: {path}")
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        columns = [c.strip() for c in reader.fieldnames or []]
        unknown = sorted(set(columns) - set(MANIFEST_COLUMNS))
        if "image" not in columns or unknown:
            raise ValueError(f"manifest {path}: needs an 'image' column and only "
                             f"{', '.join(MANIFEST_COLUMNS)}; unknown: {', '.join(unknown)}")
        rows: dict[str, dict[str, str]] = {}
        for n, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
            if not row.get("image"):
                raise ValueError(f"manifest {path} line {n}: empty image name")
            if row["image"] in rows:
                raise ValueError(f"manifest {path} line {n}: {row['image']} listed twice")
            rows[row["image"]] = {k: v for k, v in row.items() if v}
    return rows


def _row_job(job: Job, row: dict[str, str], base: Path, out_dir: Path) -> Job:
    """Apply one manifest row's overrides; a malformed cell becomes the job's problem."""
    try:
        changes: dict = {}
        if "output" in row:
            changes["dst"] = str(out_dir / Path(row["output"]).name)
        given = [k for k in ("dx", "flow", "psf") if k in row] + \
            (["dy"] if "dy" in row and "dx" not in row else [])
        if len(given) > 1 or ("dx" in row) != ("dy" in row):
            raise ValueError("give dx and dy together, or flow, or psf (one motion)")
        if "dx" in row:
            changes.update(motion=(float(row["dx"]), float(row["dy"])), flow=None, psf=None)
        for key in ("flow", "psf"):
            if key in row:
                changes.update(motion=None, flow=None, psf=None)
                changes[key] = str((base / row[key]).resolve())
        for key, cast in (("response", str), ("anchor", str), ("samples", int),
                          ("saturation", float)):
            if key in row:
                changes[key] = cast(row[key])
        return replace(job, **changes)
    except ValueError as e:
        return replace(job, problem=f"manifest row for {row['image']}: {e}")


def plan_jobs(in_dir: Path, out_dir: Path, defaults: Job, flow_dir: Path | None = None,
              manifest: Path | None = None) -> list[Job]:
    """One job per image (and per manifest row naming a missing image)."""
    in_dir, out_dir = in_dir.resolve(), out_dir.resolve()
    if not in_dir.is_dir():
        raise ValueError(f"input folder not found: {in_dir}")
    if in_dir == out_dir:
        raise ValueError("OUT_DIR must differ from IN_DIR (inputs are never overwritten)")
    if flow_dir is not None and not flow_dir.is_dir():
        raise ValueError(f"flow folder not found: {flow_dir}")
    rows = read_manifest(manifest) if manifest is not None else {}
    names = [p.name for p in list_images(in_dir)]
    names += sorted(set(rows) - set(names))  # missing ones: reported when run
    jobs = []
    for name in names:
        job = replace(defaults, src=str(in_dir / name), dst=str(out_dir / name))
        missing = "no motion given (use --motion, --flow-dir, --psf or the manifest)"
        if flow_dir is not None:
            found = [f for f in (flow_dir / (Path(name).stem + s) for s in (".npy", ".flo"))
                     if f.is_file()]
            if found:
                job = replace(job, flow=str(found[0].resolve()))
            else:
                missing = f"no flow {Path(name).stem}.npy or .flo in {flow_dir}"
        if name in rows:
            job = _row_job(job, rows[name], manifest.parent, out_dir)
        if job.problem is None and job.motion is None and job.flow is None and job.psf is None:
            job = replace(job, problem=missing)
        jobs.append(job)
    dsts = [j.dst for j in jobs]
    if len(set(dsts)) != len(dsts):
        raise ValueError("two images would be written to the same output name")
    return jobs


def remove_partials(out_dir: Path) -> int:
    """Delete temporary files that interrupted runs left (``atomic_write`` names)."""
    stale = [p for d in (out_dir, out_dir / MARKER_DIR) if d.is_dir()
             for p in d.glob(".*.part*") if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)


# --------------------------------------------------------------------------- running
def run_batch(jobs: list[Job], scheduler: str | None = None, progress: bool = True,
              force: bool = False) -> tuple[list[Result], int]:
    """Run the unfinished jobs; returns (results of the jobs run, number already finished)."""
    from tqdm import tqdm

    todo = [j for j in jobs if force or not is_finished(j)]
    skipped = len(jobs) - len(todo)
    bar = tqdm(total=len(todo), unit="img", disable=not progress, desc="batch",
               file=sys.stderr)
    results = []
    try:
        if scheduler is None:
            for job in todo:
                results.append(run_job(job))
                _advance(bar, results[-1])
        else:
            results = _run_distributed(todo, scheduler, bar)
    finally:
        bar.close()
    return results, skipped


def _advance(bar, result: Result) -> None:
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
                result = Result(futures[fut].name, False, error=f"{type(e).__name__}: {e}")
            results.append(result)
            _advance(bar, result)
    return results


def summary(results: list[Result], skipped: int) -> str:
    done = [r for r in results if r.ok]
    failed = [r for r in results if not r.ok]
    backends = sorted({r.backend for r in done if r.backend})
    lines = [f"{len(done)} blurred, {skipped} already finished, {len(failed)} failed"
             + (f" (backend: {', '.join(backends)}; {sum(r.seconds for r in done):.1f} s)"
                if done else "")]
    lines += [f"  failed: {r.name}: {r.error}" for r in sorted(failed, key=lambda r: r.name)]
    return "\n".join(lines)


# --------------------------------------------------------------------------- command line
def cmd_batch(args) -> int:
    from clblur.commands import parse_vector

    out_dir = Path(args.out_dir)
    defaults = Job(src="", dst="", motion=parse_vector(args.motion) if args.motion else None,
                   psf=str(Path(args.psf).resolve()) if args.psf else None,
                   response=args.response, anchor=args.anchor, samples=args.samples,
                   saturation=args.saturation, backend=args.backend, device=args.device,
                   memory_budget=args.memory_budget)
    if args.memory_budget is not None:
        from clblur.tiling import parse_size

        parse_size(args.memory_budget)  # fail now, not once per image
    jobs = plan_jobs(Path(args.in_dir), out_dir, defaults,
                     Path(args.flow_dir) if args.flow_dir else None,
                     Path(args.manifest) if args.manifest else None)
    if not jobs:
        raise ValueError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {args.in_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    stale = remove_partials(out_dir)
    if stale:
        print(f"removed {stale} partial file(s) left by an interrupted run", file=sys.stderr)
    results, skipped = run_batch(jobs, args.scheduler, progress=not args.quiet,
                                 force=args.force)
    print(summary(results, skipped))
    return 0 if all(r.ok for r in results) else 1


def register(sub) -> None:
    from clblur.commands import add_blur_options

    p = sub.add_parser(
        "batch", help="blur every image in a folder (resumable; local or Dask distributed)",
        description="Blur every image in IN_DIR into OUT_DIR. Finished outputs are skipped, "
                    "partial ones redone; a bad file is reported and skipped. Exit code 0 when "
                    "every image is finished, 1 when any failed.")
    p.add_argument("in_dir", metavar="IN_DIR")
    p.add_argument("out_dir", metavar="OUT_DIR")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--motion", metavar="DX,DY", help="one displacement for every image")
    g.add_argument("--flow-dir", metavar="DIR",
                   help="per-image flows named like the images: <stem>.npy or <stem>.flo")
    g.add_argument("--psf", metavar="FILE", help="one blur kernel for every image")
    p.add_argument("--manifest", metavar="CSV",
                   help="per-image overrides: columns image, output, dx, dy, flow, psf, "
                        "response, anchor, samples, saturation")
    add_blur_options(p)
    p.add_argument("--memory-budget", default=None, metavar="SIZE",
                   help="per-image working memory, e.g. 1G (large TIFFs are tiled)")
    p.add_argument("--scheduler", default=None, metavar="local[:N]|ADDRESS",
                   help="run on Dask distributed: a LocalCluster of N worker processes, or "
                        "the scheduler of a running cluster (tcp://host:8786)")
    p.add_argument("--force", action="store_true", help="redo finished images too")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_batch)
