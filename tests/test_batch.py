"""``clblur batch``: results, resuming, bad files, manifests, and a 2-worker LocalCluster."""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import clblur
from clblur import batch, batch_state
from clblur.cli import batch as batch_cli
from clblur.io import read_image, write_flow, write_image


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("CLBLUR_QUIET", "1")


def run_cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    batch_cli.register(parser.add_subparsers())
    args = parser.parse_args(["batch", *argv])
    return args.func(args)


@pytest.fixture
def folder(tmp_path, rng):
    """in/ with three good images, one corrupt; flows/ named like the images."""
    (tmp_path / "in").mkdir()
    (tmp_path / "flows").mkdir()
    images = {}
    for i, shape in enumerate([(20, 30, 3), (25, 18, 3), (16, 16)]):
        name = f"im{i}.png"
        images[name] = rng.integers(0, 256, shape, dtype=np.uint8)
        write_image(tmp_path / "in" / name, images[name])
        write_flow(tmp_path / "flows" / f"im{i}.npy", rng.normal(0, 3, shape[:2] + (2,)))
    (tmp_path / "in" / "broken.png").write_bytes(b"not a png at all")
    write_flow(tmp_path / "flows" / "broken.npy", np.zeros((4, 4, 2)))
    (tmp_path / "in" / "notes.txt").write_text("not an image; ignored")
    return tmp_path, images


def _expected(tmp_path, images, name, **kw):
    flow = np.load(tmp_path / "flows" / (Path(name).stem + ".npy"))
    return clblur.blur(images[name], flow, backend="numpy", **kw)


def test_batch_blurs_reports_bad_file_and_resumes(folder, capsys):
    tmp_path, images = folder
    out = tmp_path / "out"
    argv = [str(tmp_path / "in"), str(out), "--flow-dir", str(tmp_path / "flows"),
            "--backend", "numpy", "--quiet"]
    assert run_cli(*argv) == 1  # broken.png failed
    text = capsys.readouterr().out
    assert "3 blurred, 0 already finished, 1 failed" in text
    assert "broken.png" in text
    for name in images:
        np.testing.assert_array_equal(read_image(out / name), _expected(tmp_path, images, name))
    assert not (out / "broken.png").exists()

    # resume: finished images are skipped, only the bad one is tried again
    stamp = (out / "im0.png").stat().st_mtime_ns
    assert run_cli(*argv) == 1
    assert "0 blurred, 3 already finished, 1 failed" in capsys.readouterr().out
    assert (out / "im0.png").stat().st_mtime_ns == stamp

    # partial work is redone: a missing marker, a truncated output, a stray temp file
    (out / batch_state.MARKER_DIR / "im0.png.json").unlink()
    (out / "im1.png").write_bytes((out / "im1.png").read_bytes()[:50])
    (out / ".im2.png.abc12_45.part.png").write_bytes(b"half")
    # hidden files of the user's that merely contain ".part" are not ours: they were deleted
    theirs = [out / ".thesis.part2.tex", out / ".env.particle", out / ".im2.png.part.png"]
    for p in theirs:
        p.write_text("keep")
    (tmp_path / "in" / "broken.png").unlink()
    assert run_cli(*argv) == 0
    assert "2 blurred, 1 already finished, 0 failed" in capsys.readouterr().out
    assert sorted(out.glob(".*.part*")) == sorted(theirs)
    assert all(p.read_text() == "keep" for p in theirs)
    for name in images:
        np.testing.assert_array_equal(read_image(out / name), _expected(tmp_path, images, name))


def test_changed_options_or_input_redo_the_image(folder, capsys):
    tmp_path, images = folder
    (tmp_path / "in" / "broken.png").unlink()
    base = [str(tmp_path / "in"), str(tmp_path / "out"), "--flow-dir",
            str(tmp_path / "flows"), "--backend", "numpy", "--quiet"]
    assert run_cli(*base) == 0
    capsys.readouterr()
    assert run_cli(*base, "--response", "srgb") == 0
    assert "3 blurred, 0 already finished" in capsys.readouterr().out
    np.testing.assert_array_equal(read_image(tmp_path / "out" / "im1.png"),
                                  _expected(tmp_path, images, "im1.png", response="srgb"))
    os.utime(tmp_path / "in" / "im2.png", ns=(1, 1))  # touched, the same content: kept
    assert run_cli(*base, "--response", "srgb") == 0
    assert "0 blurred, 3 already finished" in capsys.readouterr().out
    write_image(tmp_path / "in" / "im2.png", 255 - images["im2.png"])  # an input changed
    assert run_cli(*base, "--response", "srgb") == 0
    assert "1 blurred, 2 already finished" in capsys.readouterr().out


def run_manifest(tmp_path, capsys, manifest: str, *options: str) -> tuple[int, str]:
    """``clblur batch in out --manifest m.csv OPTIONS`` on numpy, the CSV written first:
    (exit code, what it printed)."""
    (tmp_path / "m.csv").write_text(manifest)
    rc = run_cli(str(tmp_path / "in"), str(tmp_path / "out"), "--manifest",
                 str(tmp_path / "m.csv"), *options, "--backend", "numpy", "--quiet")
    return rc, capsys.readouterr().out


def test_manifest_overrides_per_image(folder, capsys):
    tmp_path, images = folder
    (tmp_path / "in" / "broken.png").unlink()
    psf = np.ones((1, 7))
    np.save(tmp_path / "k.npy", psf)
    rc, text = run_manifest(tmp_path, capsys, "image,dx,dy,psf,response,anchor,output\n"
                                              "im0.png,6,-2,,linear,start,\n"
                                              "im1.png,,,k.npy,,,renamed.png\n",
                            "--motion", "3,0")
    assert rc == 0 and "3 blurred, 0 already finished, 0 failed" in text
    out = tmp_path / "out"
    np.testing.assert_array_equal(
        read_image(out / "im0.png"),
        clblur.blur(images["im0.png"], (6, -2), "linear", anchor="start", backend="numpy"))
    np.testing.assert_array_equal(read_image(out / "renamed.png"),
                                  clblur.blur(images["im1.png"], psf, backend="numpy"))
    np.testing.assert_array_equal(read_image(out / "im2.png"),  # not in the manifest
                                  clblur.blur(images["im2.png"], (3, 0), backend="numpy"))


def test_manifest_exposure_column(folder, capsys):
    """``exposure`` per image: a continuous exposure's output, keyed apart from the default
    (whose keys are those of batches run before the column existed)."""
    from clblur.batch_state import Job, job_key

    tmp_path, images = folder
    (tmp_path / "in" / "broken.png").unlink()
    rc, text = run_manifest(tmp_path, capsys, "image,exposure\nim0.png,continuous\n"
                                              "im1.png,frames\n", "--motion", "5,2")
    assert rc == 0 and "3 blurred, 0 already finished, 0 failed" in text
    out = tmp_path / "out"
    np.testing.assert_array_equal(
        read_image(out / "im0.png"),
        clblur.blur(images["im0.png"], (5, 2), backend="numpy", exposure="continuous"))
    np.testing.assert_array_equal(read_image(out / "im1.png"),
                                  clblur.blur(images["im1.png"], (5, 2), backend="numpy"))
    job = Job(src=str(tmp_path / "in" / "im0.png"), dst="x.png", motion=(5.0, 2.0))
    assert job_key(replace(job, exposure="continuous")) != job_key(job)


@pytest.mark.parametrize("manifest, match", [
    ("name,dx\na.png,1\n", "needs an 'image' column"),
    ("image,speed\na.png,1\n", "unknown: speed"),
    ("image,dx\na.png,1\na.png,2\n", "listed twice"),
])
def test_bad_manifest_is_a_usage_error(folder, manifest, match):
    tmp_path, _ = folder
    (tmp_path / "m.csv").write_text(manifest)
    with pytest.raises(ValueError, match=match):
        run_cli(str(tmp_path / "in"), str(tmp_path / "out"), "--manifest",
                str(tmp_path / "m.csv"))


def test_usage_errors(folder):
    tmp_path, _ = folder
    with pytest.raises(ValueError, match="must differ"):
        run_cli(str(tmp_path / "in"), str(tmp_path / "in"), "--motion", "1,0")
    with pytest.raises(ValueError, match="input folder not found"):
        run_cli(str(tmp_path / "nope"), str(tmp_path / "out"), "--motion", "1,0")
    with pytest.raises(ValueError, match="local:N"):
        run_cli(str(tmp_path / "in"), str(tmp_path / "out"), "--motion", "1,0",
                "--scheduler", "local:zero")
    with pytest.raises(ValueError, match="memory budget"):
        run_cli(str(tmp_path / "in"), str(tmp_path / "out"), "--motion", "1,0",
                "--memory-budget", "plenty")


def _worker_state() -> tuple[int, str | None, int | None]:
    """(pid, POCL_CACHE_DIR if it is a folder, OpenCL runtimes in this process or None if the
    backend was never imported)."""
    import sys

    cl = sys.modules.get("clblur.opencl")
    cache = os.environ.get("POCL_CACHE_DIR")
    return os.getpid(), cache if cache and Path(cache).is_dir() else None, \
        None if cl is None else len(cl.runtimes())


def test_two_worker_local_cluster(folder, capsys):
    pytest.importorskip("distributed")
    tmp_path, images = folder
    rc = run_cli(str(tmp_path / "in"), str(tmp_path / "out"), "--flow-dir",
                 str(tmp_path / "flows"), "--backend", "numpy", "--scheduler", "local:2",
                 "--quiet")
    assert rc == 1
    assert "3 blurred, 0 already finished, 1 failed" in capsys.readouterr().out
    for name in images:
        np.testing.assert_array_equal(read_image(tmp_path / "out" / name),
                                      _expected(tmp_path, images, name))


def test_workers_get_own_pocl_cache_and_lazy_opencl(folder):
    pytest.importorskip("distributed")
    from clblur.distributed import client_for

    tmp_path, _ = folder
    job = batch_state.Job(src=str(tmp_path / "in" / "im0.png"), dst=str(tmp_path / "im0.png"),
                    motion=(2.0, 1.0), backend="numpy")
    with client_for("local:2") as client:
        assert client.submit(batch.run_job, job, pure=False).result().ok
        states = list(client.run(_worker_state).values())
    pids, caches, runtimes = zip(*states, strict=True)
    assert len(set(pids)) == 2 and os.getpid() not in pids  # separate processes
    assert len(set(caches)) == 2 and None not in caches
    assert all(r in (None, 0) for r in runtimes)  # numpy jobs never create an OpenCL context


def test_workers_create_one_opencl_context_each(opencl, folder):
    pytest.importorskip("distributed")
    from clblur.distributed import client_for

    tmp_path, images = folder
    jobs = [batch_state.Job(src=str(tmp_path / "in" / n), dst=str(tmp_path / f"cl_{n}"),
                      motion=(4.0, -1.0), backend="opencl") for n in images]
    with client_for("local:2") as client:
        results = client.gather([client.submit(batch.run_job, j, pure=False) for j in jobs])
        states = list(client.run(_worker_state).values())
    assert all(r.ok and r.backend == "opencl" for r in results)
    assert all(rt in (None, 1) for _, _, rt in states)
    assert any(rt == 1 for _, _, rt in states)
    for n, img in images.items():
        np.testing.assert_array_equal(read_image(tmp_path / f"cl_{n}"),
                                      clblur.blur(img, (4.0, -1.0), backend="opencl"))


def test_existing_scheduler_address(folder, capsys):
    distributed = pytest.importorskip("distributed")
    tmp_path, images = folder
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster:
        rc = run_cli(str(tmp_path / "in"), str(tmp_path / "out"), "--motion", "0,5",
                     "--backend", "numpy", "--scheduler", cluster.scheduler_address,
                     "--quiet")
    assert rc == 1 and "3 blurred, 0 already finished, 1 failed" in capsys.readouterr().out
    np.testing.assert_array_equal(read_image(tmp_path / "out" / "im2.png"),
                                  clblur.blur(images["im2.png"], (0, 5), backend="numpy"))


def test_unreachable_scheduler_is_a_usage_error():
    pytest.importorskip("distributed")
    from clblur.distributed import client_for

    with pytest.raises(ValueError, match="cannot reach"), \
            client_for("tcp://127.0.0.1:9", timeout="1s"):
        pass


def test_editing_the_response_document_redoes_exactly_its_outputs(folder, capsys):
    """The resume key covers the response document's content (issue 10, item 2)."""
    tmp_path, images = folder
    (tmp_path / "in" / "broken.png").unlink()
    clblur.Gamma(1.8).save(tmp_path / "r.json")
    clblur.Gamma(2.4).save(tmp_path / "other.json")
    (tmp_path / "m.csv").write_text("image,response\nim0.png,r.json\nim1.png,other.json\n")
    argv = [str(tmp_path / "in"), str(tmp_path / "out"), "--manifest", str(tmp_path / "m.csv"),
            "--motion", "4,1", "--backend", "numpy", "--quiet"]
    assert run_cli(*argv) == 0
    assert "3 blurred, 0 already finished" in capsys.readouterr().out
    stamps = {n: (tmp_path / "out" / n).stat().st_mtime_ns for n in images}
    clblur.Gamma(1.3).save(tmp_path / "r.json")  # same path, new content
    assert run_cli(*argv) == 0
    assert "1 blurred, 2 already finished" in capsys.readouterr().out
    np.testing.assert_array_equal(
        read_image(tmp_path / "out" / "im0.png"),
        clblur.blur(images["im0.png"], (4, 1), "gamma:1.3", backend="numpy"))
    for n in ("im1.png", "im2.png"):
        assert (tmp_path / "out" / n).stat().st_mtime_ns == stamps[n]


def test_same_content_same_key_and_version_in_key(folder, monkeypatch):
    tmp_path, _ = folder
    job = batch_state.Job(src=str(tmp_path / "in" / "im0.png"), dst=str(tmp_path / "o.png"),
                    motion=(1.0, 0.0))
    key = batch_state.job_key(job)
    assert batch_state.job_key(job) == key
    assert batch_state.job_key(replace(job, samples=7)) != key
    assert batch_state.job_key(replace(job, backend="opencl")) == key  # same pixels
    monkeypatch.setattr(clblur, "__version__", "0.0.0-other")
    assert batch_state.job_key(job) != key


def test_claims_are_exclusive_and_stale_ones_are_taken_over(folder, monkeypatch):
    tmp_path, _ = folder
    (tmp_path / "out").mkdir()
    job = batch_state.Job(src=str(tmp_path / "in" / "im0.png"),
                          dst=str(tmp_path / "out" / "im0.png"), motion=(3.0, 0.0),
                          backend="numpy")
    held = batch_state.claim(job)
    assert held is not None and batch_state.claim(job) is None  # a second claimant is refused
    assert batch.run_job(job).status == "busy" and not Path(job.dst).exists()
    held.release()
    # a lock left by a dead process on this host is stale
    import socket

    batch_state.lock_path(job).write_text(json.dumps({"host": socket.gethostname(),
                                                "pid": 2**22 + 12345, "time": 0}))
    assert batch.run_job(job).ok and batch_state.is_finished(job)
    assert not batch_state.lock_path(job).exists()

    def refused_until_older_than(text: str, age: float) -> None:
        batch_state.lock_path(job).write_text(text)
        assert batch_state.claim(job) is None
        old = time.time() - age - 5
        os.utime(batch_state.lock_path(job), (old, old))
        held = batch_state.claim(job)
        assert held is not None
        held.release()

    # a lock from another host is stale only when its heartbeat stopped
    refused_until_older_than(json.dumps({"host": "elsewhere", "pid": 1, "time": 0}),
                             batch_state.STALE_LOCK_S)
    # an empty lock is one whose creator has not written it yet (a concurrent batch taking it
    # over would blur the image twice), or a crash's: stale only once older than a heartbeat
    refused_until_older_than("", batch_state.HEARTBEAT_S)


def test_a_stale_claim_is_taken_over_by_one_batch_only(folder):
    # two batches finding one stale lock both took it over now and then: the slower renamed
    # aside the claim the faster had just made (a reviewer measured 2 in 300 trials).  A
    # takeover now holds a guard file; one taker wins, the other is refused
    import socket

    tmp_path, _ = folder
    (tmp_path / "out").mkdir()
    job = batch_state.Job(src=str(tmp_path / "in" / "im0.png"),
                          dst=str(tmp_path / "out" / "im0.png"), motion=(3.0, 0.0))
    lock = batch_state.lock_path(job)
    lock.parent.mkdir()
    dead = json.dumps({"host": socket.gethostname(), "pid": 2**22 + 12345, "time": 0})
    guard = lock.with_name(lock.name + ".takeover")
    lock.write_text(dead)
    guard.write_text("")  # another batch is taking it over this instant
    assert batch_state.claim(job) is None and lock.read_text() == dead
    old = time.time() - batch_state.HEARTBEAT_S - 5
    os.utime(guard, (old, old))  # a guard left by a crash is cleared, and the next try wins
    assert batch_state.claim(job) is None and not guard.exists()
    first = batch_state.claim(job)
    assert first is not None and json.loads(lock.read_text())["pid"] == os.getpid()
    assert not guard.exists()
    assert batch_state.claim(job) is None  # the fresh claim is not taken over again
    first.release()
    # many threads at one stale lock: exactly one holds it
    lock.write_text(dead)
    barrier = threading.Barrier(8)

    def take():
        barrier.wait()
        return batch_state.claim(job)

    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        held = [c for c in pool.map(lambda _: take(), range(8)) if c is not None]
    assert len(held) == 1
    held[0].release()


def test_outputs_never_overwrite_an_input_of_the_batch(folder, capfd):
    # a PSF or a manifest kept in OUT_DIR under an output's name was overwritten (exit 0),
    # and an image listed inside OUT_DIR was refused only when its turn came, after other
    # outputs had been written: each is refused before anything is written
    tmp_path, images = folder
    (tmp_path / "in" / "broken.png").unlink()
    out = tmp_path / "out"
    out.mkdir()
    kernel = np.zeros((9, 9), np.uint8)
    kernel[4] = 255
    write_image(out / "im0.png", kernel)
    before = (out / "im0.png").read_bytes()
    code, err = cli_main(capfd, "batch", str(tmp_path / "in"), str(out), "--psf",
                         str(out / "im0.png"), "--backend", "numpy", "--quiet")
    assert code == 2 and len(err) == 1 and "would overwrite im0.png's PSF" in err[0]
    assert (out / "im0.png").read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == ["im0.png"]
    (out / "im0.png").unlink()
    (out / "im1.png").write_text("image,dx,dy\nim0.png,2,0\n")  # the manifest
    code, err = cli_main(capfd, "batch", str(tmp_path / "in"), str(out), "--manifest",
                         str(out / "im1.png"), "--motion=1,0", "--backend", "numpy", "--quiet")
    assert code == 2 and len(err) == 1 and "would overwrite the manifest" in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["im1.png"]
    (out / "im1.png").unlink()
    inner = tmp_path / "in" / "sub"  # OUT_DIR inside IN_DIR, an image listed from it
    inner.mkdir()
    write_image(inner / "x.png", images["im0.png"])
    (tmp_path / "m.csv").write_text("image,dx,dy\nsub/x.png,2,0\n")
    code, err = cli_main(capfd, "batch", str(tmp_path / "in"), str(inner), "--manifest",
                         str(tmp_path / "m.csv"), "--motion=1,0", "--backend", "numpy",
                         "--quiet")
    assert code == 2 and len(err) == 1 and "would overwrite x.png's image" in err[0]
    assert sorted(p.name for p in inner.iterdir()) == ["x.png"]


def test_two_concurrent_batches_do_not_duplicate_work(folder):
    """Two processes into one OUT_DIR: every image blurred exactly once, both exit 0."""
    tmp_path, _ = folder
    (tmp_path / "in" / "broken.png").unlink()
    for i in range(3, 9):
        write_image(tmp_path / "in" / f"im{i}.png",
                    np.random.default_rng(i).integers(0, 256, (40, 60, 3), dtype=np.uint8))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1]), "CLBLUR_QUIET": "1"}
    cmd = [sys.executable, "-m", "clblur.cli", "batch", str(tmp_path / "in"),
           str(tmp_path / "out"), "--motion", "30,5", "--backend", "numpy", "--quiet"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=env) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    blurred = [int(out.split(" blurred")[0].split()[-1]) for out, _ in outs]
    assert sum(blurred) == 9, outs  # each of the 9 images done by exactly one batch
    assert not list((tmp_path / "out" / batch_state.MARKER_DIR).glob("*.lock"))


# --------------------------------------------------------------------------- refused up front
def cli_main(capfd, *argv: str) -> tuple[int, list[str]]:
    """``clblur ARGV`` through the real entry point: (exit code, stderr lines)."""
    from clblur.cli import main

    capfd.readouterr()
    code = main(list(argv))
    return code, [line for line in capfd.readouterr().err.splitlines() if line.strip()]


def assert_refused(capfd, tmp_path, *argv: str, match: tuple[str, ...]) -> None:
    """Exit 2, one ``clblur batch: error:`` line holding every ``match``, no traceback or
    exception class name, and OUT_DIR (``tmp_path/out``) never created."""
    code, lines = cli_main(capfd, "batch", str(tmp_path / "in"), str(tmp_path / "out"),
                           "--backend", "numpy", "--quiet", *argv)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("clblur batch: error: "), lines
    assert "Error:" not in lines[0] and "Traceback" not in lines[0], lines
    for word in match:
        assert word in lines[0], (word, lines[0])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("cells, line, column, words", [
    ("im0.png,nan,1", 2, "dx, dy", ("NaN",)),
    ("im0.png,abc,1", 2, "column dx", ("'abc'",)),
    ("im0.png,1,inf", 2, "dx, dy", ("infinite",)),
    ("im0.png,,,middle", 2, "column anchor", ("'middle'",)),
    ("im0.png,,,,-1", 2, "column samples", (">= 1, got -1",)),
    ("im0.png,,,,2.5", 2, "column samples", ("integer", "'2.5'")),
    ("im0.png,,,,,0.5", 2, "column saturation", ("got 0.5",)),
    ("im0.png,,,,,,bogus", 2, "column exposure", ("'bogus'",)),
    ("im0.png,,,,,,,exp:-1", 2, "column response", ("exp:-1",)),
    ("im0.png,,,,,,,nope.json", 2, "column response", ("not found",)),
    ("im0.png,1,2\nim1.png,,,,0", 3, "column samples", ("got 0",)),
    ("ghost.png,1,1", 2, "column image", ("not found", "ghost.png")),
    ("notes.txt,1,1", 2, "column image", ("not an image",)),
    ("im0.png,,,,,,,,missing.npy", 2, "column psf", ("not found",)),
    ("im0.png,,,,,,,,,missing.npy", 2, "column flow", ("not found",)),
    ("im0.png,,,,,,,,k_neg.npy", 2, "column psf", ("non-negative",)),
    ("im0.png,1,1,,,,,,,k_neg.npy", 2, "columns dx, flow", ("one motion",)),
    ("im0.png,,,,,,,,,,x.txt", 2, "column output", ("extension",)),
])
def test_bad_manifest_cells_are_refused_before_any_work(folder, capfd, cells, line, column,
                                                        words):
    """Every row's cells pass the same checks as the blur, up front: exit 2, one line naming
    the manifest, the line and the column; nothing written (the broken image is never read)."""
    tmp_path, _ = folder
    np.save(tmp_path / "k_neg.npy", np.array([[0.5, -0.2], [0.3, 0.4]]))
    manifest = tmp_path / "m.csv"
    manifest.write_text("image,dx,dy,anchor,samples,saturation,exposure,response,psf,flow,"
                        f"output\n{cells}\n")
    assert_refused(capfd, tmp_path, "--motion", "1,0", "--manifest", str(manifest),
                   match=(str(manifest), f"line {line},", column, *words))


@pytest.mark.parametrize("text, line", [
    ('image,dx,dy\n"im0.png,3,1\n', 2),
    ('image,dx,dy\nim0.png,1,1\n"im1.png,3,1\nim2.png,1,1\n', 3),
    ('image,dx,dy\n"im0.png"x,3,1\n', 2),
    ('image,dx,dy\n"im0.png\nim1.png",3,1\n', 2),
])
def test_malformed_csv_is_refused(folder, capfd, text, line):
    """A quote left open swallows the rest of the file into one cell: refused, not read as
    an image named ``im0.png,3,1...``."""
    tmp_path, _ = folder
    (tmp_path / "m.csv").write_text(text)
    assert_refused(capfd, tmp_path, "--motion", "1,0", "--manifest", str(tmp_path / "m.csv"),
                   match=("malformed CSV", f"line {line}:"))


@pytest.mark.parametrize("argv, match", [
    ((), ("no motion given", "--motion")),  # no --motion, --flow-dir, --psf or manifest
    (("--flow-dir", "{tmp}/nodir"), ("flow folder not found", "nodir")),
    (("--flow-dir", "{tmp}/some_flows"), ("no flow for broken.png", "broken.npy")),
    (("--psf", "{tmp}/k_neg.npy"), ("--psf", "k_neg.npy", "non-negative")),
    (("--motion", "1,0", "--samples", "-1"), ("--samples", "got -1")),
    (("--motion", "1,0", "--saturation", "0.5"), ("--saturation", "got 0.5")),
    (("--motion", "1,0", "--scheduler", "bogus"), ("bogus",)),
])
def test_motion_flows_and_options_are_checked_once_up_front(folder, capfd, argv, match):
    """Whole-run problems: exit 2 before OUT_DIR exists, not one failure per image."""
    if "--scheduler" in argv:
        pytest.importorskip("distributed")
    tmp_path, _ = folder
    np.save(tmp_path / "k_neg.npy", np.array([[0.5, -0.2], [0.3, 0.4]]))
    (tmp_path / "some_flows").mkdir()
    write_flow(tmp_path / "some_flows" / "im0.npy", np.zeros((20, 30, 2)))
    assert_refused(capfd, tmp_path, *(a.format(tmp=tmp_path) for a in argv), match=match)


def test_a_manifest_row_without_motion_is_refused(folder, capfd):
    tmp_path, _ = folder
    (tmp_path / "m.csv").write_text("image,dx,dy\nim0.png,1,1\n")
    assert_refused(capfd, tmp_path, "--manifest", str(tmp_path / "m.csv"),
                   match=("no motion for broken.png", "m.csv has no row"))
    (tmp_path / "m.csv").write_text("image,dx,dy,samples\nim0.png,1,1,\nbroken.png,,,3\n")
    assert_refused(capfd, tmp_path, "--manifest", str(tmp_path / "m.csv"),
                   match=("no motion for broken.png", "its row of", "gives no dx"))
    (tmp_path / "m.csv").write_text("image,dx,dy\nim0.png,1,1\n")
    # a flow folder lacking a flow is fine for an image whose row gives its motion
    (tmp_path / "in" / "broken.png").unlink()
    (tmp_path / "flows" / "im0.npy").unlink()
    code, lines = cli_main(capfd, "batch", str(tmp_path / "in"), str(tmp_path / "out"),
                           "--flow-dir", str(tmp_path / "flows"), "--manifest",
                           str(tmp_path / "m.csv"), "--backend", "numpy", "--quiet")
    assert code == 0 and not lines


def test_run_job_applies_the_same_checks(folder):
    """A job built by hand meets the checks ``plan_jobs`` applies, as a failed image."""
    tmp_path, _ = folder
    job = batch_state.Job(src=str(tmp_path / "in" / "im0.png"), dst=str(tmp_path / "o.png"),
                          motion=(1.0, 0.0), samples=0, backend="numpy")
    result = batch.run_job(job)
    assert not result.ok and result.error == "samples must be >= 1, got 0"
    result = batch.run_job(replace(job, motion=None, samples=None))
    assert not result.ok and "exactly one of motion, flow, psf" in result.error
    assert not Path(job.dst).exists()
