"""Batches that survive: bad captures, dead workers, killed runs, concurrent runs.

A small simulated camera (2 x 3 views of 200 x 150 px, about 0.5 s per capture) keeps
these fast. "Bit-identical" compares every output file byte for byte, and
``result.json`` without its timings and its jobs/threads parameters.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import lfcam
from lfcam.batch.folder import find_captures
from lfcam.batch.pool import WorkerDied, run_pool
from lfcam.calibration.calibrate import run_calibration
from lfcam.errors import LfcamError
from lfcam.io.lock import LockBusy, lock_path, path_lock, remove_stale
from lfcam.sim import SimConfig

LINUX = sys.platform.startswith("linux") and os.path.isdir("/proc/self")
NAMES = ["board", "layered", "planes", "spheres", "sub/planes2", "sub/spheres2"]


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> dict[str, Path]:
    """A small camera's calibration, a folder of six captures and its reference output
    (an uninterrupted ``--jobs 1`` run)."""
    root = tmp_path_factory.mktemp("batch")
    cfg = SimConfig(
        view_size=(200, 150),
        grid=(2, 3),
        captures_per_distance=2,
        scenes=("planes", "spheres", "layered", "board"),
        seed=5,
    )
    sim = lfcam.simulate(root / "sim", cfg, truth=False)
    calf = root / "camera.lfcal"
    run_calibration(sim.calibration_dir).save(calf)
    inp = root / "in"
    (inp / "sub").mkdir(parents=True)
    for name, path in sim.captures.items():
        shutil.copy(path, inp / f"{name}.png")
    shutil.copy(sim.captures["planes"], inp / "sub" / "planes2.png")
    shutil.copy(sim.captures["spheres"], inp / "sub" / "spheres2.png")
    ref = root / "ref"
    summary = lfcam.process_folder(inp, calf, ref)
    assert summary.done == tuple(str(inp / f"{n}.png") for n in NAMES)
    return {"cal": calf, "in": inp, "ref": ref, "root": root}


def _files(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` (hidden ones too) by relative path; result.json
    without the run's timings and its jobs/threads."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_dir():
            continue
        data = p.read_bytes()
        if p.name == "result.json":
            info = json.loads(data)
            info.pop("timings_s")
            info["parameters"].pop("jobs")
            info["parameters"].pop("threads")
            data = json.dumps(info, sort_keys=True).encode()
        out[str(p.relative_to(folder))] = data
    return out


def _assert_same(out: Path, ref: Path) -> None:
    got, want = _files(out), _files(ref)
    assert sorted(got) == sorted(want)  # no temporaries or lock files left either
    assert [k for k in want if got[k] != want[k]] == []


# ---------------------------------------------------------------------------
# Locks and stale temporaries
# ---------------------------------------------------------------------------
def _hold(path: Path, held: threading.Event, release: threading.Event) -> None:
    with path_lock(path):
        held.set()
        release.wait(30)


def test_lock_excludes_other_holders_and_is_removed(tmp_path) -> None:
    target = tmp_path / "cap"
    held, release = threading.Event(), threading.Event()
    t = threading.Thread(target=_hold, args=(target, held, release))
    t.start()
    assert held.wait(10)
    assert lock_path(target).is_file()
    with pytest.raises(LockBusy, match=r"\.cap\.lfcam-lock"), path_lock(target, wait=False):
        pass
    release.set()
    t.join()
    assert not lock_path(target).exists()
    with path_lock(target, wait=False), path_lock(target, wait=False):  # re-entrant
        assert lock_path(target).is_file()
    assert list(tmp_path.iterdir()) == []


def test_remove_stale_only_what_no_run_holds(tmp_path) -> None:
    d = tmp_path
    (d / ".a.tmp-abcd1234").mkdir()  # a folder being written when its run died
    (d / ".a.tmp-abcd1234" / "depth.tiff").write_bytes(b"x")
    (d / ".a.lfcam-lock").write_bytes(b"")  # its lock file
    (d / ".b.old-k_9zzzzz" / "b").mkdir(parents=True)  # set aside by a dead --overwrite
    (d / ".b.old-k_9zzzzz" / "b" / "result.json").write_text("{}")
    (d / ".c.old-qqqqqqqq" / "c").mkdir(parents=True)  # set aside, replacement renamed in
    (d / "c").mkdir()
    (d / "c" / "result.json").write_text('{"new": 1}')
    (d / ".p.png.tmp-0a1b2c3d.png").write_bytes(b"half a file")
    (d / ".live.tmp-abcdefgh").mkdir()  # a live run's: its lock is held
    # Not lfcam's: ".q.lock" is another program's lock file, "c" a complete output.
    keep = [".other", ".x.tmp-short", "y.tmp-abcdefgh", ".z.tmp-ABCDEFGH", ".q.lock", "c"]
    for name in keep[:-1]:
        (d / name).write_bytes(b"not lfcam's")
    held, release = threading.Event(), threading.Event()
    t = threading.Thread(target=_hold, args=(d / "live", held, release))
    t.start()
    assert held.wait(10)
    try:
        removed = remove_stale(d)
    finally:
        release.set()
        t.join()
    assert sorted(p.name for p in removed) == [
        ".a.tmp-abcd1234",
        ".b.old-k_9zzzzz",
        ".c.old-qqqqqqqq",
        ".p.png.tmp-0a1b2c3d.png",
    ]
    assert sorted(p.name for p in d.iterdir()) == sorted([*keep, ".live.tmp-abcdefgh", "b"])
    assert (d / "b" / "result.json").read_text() == "{}"  # put back
    assert (d / "c" / "result.json").read_text() == '{"new": 1}'  # the new one stays
    assert remove_stale(d) == [d / ".live.tmp-abcdefgh"]  # no longer held


# ---------------------------------------------------------------------------
# The local pool
# ---------------------------------------------------------------------------
def _init(x: int) -> int:
    return x


def _work(state: int, task: int) -> int:
    if task == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    return state * task


def _bad_init() -> None:
    raise OSError("cannot start")


def _work_then_exit(state: int, task: int) -> int:
    if task == 1:  # dies just after sending its result, before the next task reaches it
        threading.Timer(0.1, os._exit, (0,)).start()
    return state * task


def test_pool_reports_a_dead_worker_and_goes_on() -> None:
    results = dict(run_pool(list(range(7)), 2, _init, (10,), _work))
    assert results.pop(2) == WorkerDied(-signal.SIGKILL)
    assert results == {k: 10 * k for k in (0, 1, 3, 4, 5, 6)}
    assert "SIGKILL" in str(WorkerDied(-signal.SIGKILL))
    with pytest.raises(LfcamError, match="could not start: OSError: cannot start"):
        list(run_pool([1, 2], 2, _bad_init, (), _work))


def _init_then_exit(x: int) -> int:
    threading.Timer(0.1, os._exit, (0,)).start()  # dies soon after it says it is ready
    return x


def test_pool_worker_dead_before_its_next_task(monkeypatch) -> None:
    """A task sent to a worker that has just died is run by its replacement."""
    from lfcam.batch import pool

    real = pool.wait

    def slow_wait(conns):  # type: ignore[no-untyped-def]
        ready = real(conns)
        time.sleep(0.4)  # long enough for the worker to have exited
        return ready

    monkeypatch.setattr(pool, "wait", slow_wait)
    results = dict(run_pool([0, 1, 2, 3], 1, _init, (10,), _work_then_exit))
    assert results == {k: 10 * k for k in range(4)}
    # Workers that never live to take a task: an error, not an endless restart.
    with pytest.raises(LfcamError, match="worker processes keep dying before they get a task"):
        list(run_pool([0, 1], 1, _init_then_exit, (10,), _work))


# ---------------------------------------------------------------------------
# process_folder
# ---------------------------------------------------------------------------
def test_nested_output_folders_refused(tmp_path) -> None:
    inp, out = tmp_path / "in", tmp_path / "out"
    (inp / "sub").mkdir(parents=True)
    for name in ("sub.png", "sub/x.png"):
        (inp / name).write_bytes(b"")
    with pytest.raises(lfcam.InputError) as e:
        find_captures(inp, out)
    assert str(e.value) == (
        f"{inp / 'sub/x.png'}: its output folder {out / 'sub/x'} is inside that of"
        f" {inp / 'sub.png'} ({out / 'sub'}), which writing it would replace"
    )
    # Also across inputs: a file and a folder.
    other = tmp_path / "other"
    (other / "sub").mkdir(parents=True)
    (other / "sub" / "y.png").write_bytes(b"")
    with pytest.raises(lfcam.InputError, match=r"/y\.png: its output folder .* is inside"):
        find_captures([inp / "sub.png", other], out)
    (inp / "sub.png").unlink()
    (inp / "sub" / "x.tif").write_bytes(b"")
    with pytest.raises(lfcam.InputError) as e:
        find_captures(inp, out)
    assert str(e.value) == (
        f"{inp / 'sub/x.tif'}: has the same output folder as {inp / 'sub/x.png'} ({out / 'sub/x'})"
    )
    (inp / "sub" / "x.tif").unlink()
    (inp / "subway.png").write_bytes(b"")  # a name that starts like another is fine
    assert [t.out for t in find_captures(inp, out)] == [str(out / "sub/x"), str(out / "subway")]


def test_jobs_2_identical_to_jobs_1_bad_capture_reported(small, tmp_path) -> None:
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    seen: list[tuple[str, int, int]] = []
    out = tmp_path / "out"
    inputs = [small["in"], bad]
    summary = lfcam.process_folder(
        inputs, small["cal"], out, jobs=2, progress=lambda o, k, n: seen.append((o.status, k, n))
    )
    assert [s for s, _ in summary.failed] == [str(bad)]
    assert summary.failed[0][1] == f"{bad}: not a readable PNG (no PNG header)"  # the reader's
    assert len(summary.done) == len(NAMES)
    assert (summary.workers, summary.threads) == (2, max(1, (os.cpu_count() or 1) // 2))
    assert [(k, n) for _, k, n in seen] == [(k, 7) for k in range(1, 8)]
    assert sorted(st for st, _, _ in seen) == ["done"] * 6 + ["failed"]
    _assert_same(out, small["ref"])
    # Run again: everything complete is skipped, the bad capture fails again.
    seen.clear()
    again = lfcam.process_folder(
        inputs, small["cal"], out, jobs=2, progress=lambda o, k, n: seen.append((o.status, k, n))
    )
    assert (again.done, len(again.skipped), len(again.failed)) == ((), len(NAMES), 1)
    assert [(k, n) for _, k, n in seen] == [(k, 7) for k in range(1, 8)]
    with pytest.raises(lfcam.InputError, match=r"^sav_views: not an option"):
        lfcam.process_folder(inputs, small["cal"], out, sav_views=True)


def _live_calibrations() -> int:
    import gc

    gc.collect()
    return sum(isinstance(o, lfcam.Calibration) for o in gc.get_objects())


def test_one_calibration_in_memory_while_captures_run(small, tmp_path, monkeypatch) -> None:
    """The command line's own copy (loaded to check its options) is gone before the
    batch runs, and with worker processes the caller keeps none: a full-size
    calibration is about half a gigabyte (benchmarks/NOTES.md, "Batches")."""
    from lfcam.batch import folder
    from lfcam.cli import main

    counts: dict[str, int] = {}

    def watch(name: str, fn):
        def wrapped(*args, **kwargs):
            counts[name] = _live_calibrations()
            return fn(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(folder, "_run_here", watch("here", folder._run_here))
    monkeypatch.setattr(folder, "run_pool", watch("pool", folder.run_pool))
    base = _live_calibrations()
    capture = small["in"] / "planes.png"
    assert main(["process", str(capture), "-c", str(small["cal"]), "-o", str(tmp_path / "a")]) == 0
    args = ["process", str(small["in"]), "-c", str(small["cal"]), "-o", str(tmp_path / "b")]
    assert main([*args, "--jobs", "2"]) == 0
    # --jobs 1 runs the captures here, with the batch's one copy; --jobs 2 in workers.
    assert counts == {"here": base + 1, "pool": base}


def test_options_checked_and_normalised(small, tmp_path, monkeypatch) -> None:
    cal = lfcam.Calibration.load(small["cal"])
    one = small["in"] / "board.png"
    out = tmp_path / "out"
    for name, value, message in [
        ("superres", True, "superres: expected a factor from 1 to 4, got True"),
        ("interp", "nearest", "interp: expected one of 'bilinear', "),
        ("interp", None, "interp: expected one of 'bilinear', "),
        ("refocus", 2.5, "refocus: expected a sequence of distances, got 2.5"),
        ("refocus", "3", "refocus: expected a sequence of distances, got '3'"),
        ("refocus", [float("inf")], "refocus: distances must be beyond Z_c"),
    ]:
        with pytest.raises(lfcam.InputError) as e:
            lfcam.process_folder(one, cal, out, **{name: value})
        assert str(e.value).startswith(message), (name, value)
    assert not out.exists()
    # Checked before the calibration is even loaded.
    with pytest.raises(lfcam.InputError, match=r"^interp: expected one of"):
        lfcam.process_folder(one, tmp_path / "missing.lfcal", out, interp="nearest")
    # A list of distances is stored as a tuple in the frozen options the workers get.
    from lfcam.batch import folder

    seen = []

    def record(task, cal, options, extra, **kw):  # type: ignore[no-untyped-def]
        seen.append(options)
        return lfcam.batch.CaptureOutcome(task.source, task.out, "done")

    monkeypatch.setattr(folder, "run_capture", record)
    z = cal.z_c + 1.0
    lfcam.process_folder(one, cal, out, refocus=[z, int(z) + 2])
    assert [o.refocus for o in seen] == [(z, float(int(z) + 2))]
    assert all(type(v) is float for v in seen[0].refocus)


def test_capture_read_once_and_unreadable_exif_only_warns(small, tmp_path, monkeypatch) -> None:
    """Pixels and EXIF come from one read of the file; EXIF that exifread cannot parse
    leaves the metadata unknown, and the capture is processed."""
    exifread = pytest.importorskip("exifread")
    from lfcam.io import images, raw, read_image, write_image

    tif = tmp_path / "board.tif"
    write_image(tif, read_image(small["in"] / "board.png"))

    def broken(*args, **kw):  # type: ignore[no-untyped-def]
        raise IndexError("list index out of range")

    def again(path, limit):  # type: ignore[no-untyped-def]
        raise AssertionError(f"{path} read a second time")

    monkeypatch.setattr(exifread, "process_file", broken)
    monkeypatch.setattr(images, "read_file_bytes", again)
    monkeypatch.setattr(raw, "read_file_bytes", again)
    with pytest.warns(lfcam.LfcamWarning, match=r"board\.tif: unreadable EXIF metadata"):
        summary = lfcam.process_folder(tif, small["cal"], tmp_path / "out")
    monkeypatch.undo()
    assert summary.failed == ()
    assert summary.done == (str(tif),)
    result = json.loads((tmp_path / "out" / "board" / "result.json").read_text())
    assert result["capture"]["focal_length_mm"] is None
    ref = read_image(small["ref"] / "board" / "depth.tiff")
    np.testing.assert_array_equal(read_image(tmp_path / "out" / "board" / "depth.tiff"), ref)


def test_worker_killed_mid_batch(small, tmp_path) -> None:
    """A worker SIGKILLed while it holds a capture's lock: that capture is reported,
    nothing half-written is left, the rest complete."""
    if not LINUX:
        pytest.skip("needs /proc/locks")
    out = tmp_path / "out"
    killed: list[str] = []
    t = threading.Thread(target=_kill_a_lock_holder, args=(out, killed))
    t.start()
    summary = lfcam.process_folder(small["in"], small["cal"], out, jobs=2)
    t.join()
    assert len(killed) == 1
    assert [(Path(s).stem, r) for s, r in summary.failed] == [
        (killed[0], "the worker process was killed by SIGKILL (the out-of-memory killer?)")
    ]
    assert len(summary.done) == len(NAMES) - 1
    failed_out = next(o.out for o in summary.outcomes if o.status == "failed")
    ref = _files(small["ref"])
    got = _files(out)
    rel = str(Path(failed_out).relative_to(out))
    assert sorted(got) == sorted(k for k in ref if not k.startswith(rel + "/"))
    assert all(got[k] == ref[k] for k in got)


def _kill_a_lock_holder(out: Path, killed: list[str]) -> None:
    """SIGKILL the first other process seen holding a capture's lock below ``out``;
    append the capture's name to ``killed``."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        for lock in out.rglob(".*.lfcam-lock") if out.is_dir() else []:
            pid = _lock_holder(lock)
            if pid is not None and pid != os.getpid():
                os.kill(pid, signal.SIGKILL)
                killed.append(lock.name[1 : -len(".lfcam-lock")])
                return
        time.sleep(0.002)


def _lock_holder(lock: Path) -> int | None:
    """The pid holding an flock on ``lock`` (from /proc/locks), if any."""
    try:
        ino = lock.stat().st_ino
        text = Path("/proc/locks").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        f = line.split()
        if len(f) >= 6 and f[1] == "FLOCK" and f[5].split(":")[-1] == str(ino):
            return int(f[4])
    return None


# ---------------------------------------------------------------------------
# The kill test: `lfcam process` SIGKILLed at several points, then rerun
# ---------------------------------------------------------------------------
def _lfcam(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "lfcam", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_for(cond, what: str, proc: subprocess.Popen[str], timeout: float = 120) -> object:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = cond()
        if got:
            return got
        assert proc.poll() is None, f"lfcam ended before {what}: {proc.communicate()}"
        time.sleep(0.002)
    raise AssertionError(f"timed out waiting for {what}")


def _children(pid: int) -> list[int]:
    kids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(d.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _kill(proc: subprocess.Popen[str]) -> None:
    proc.kill()
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL


def _temporaries(out: Path) -> list[str]:
    return [p.name for p in out.rglob(".*")]


def test_kill_and_rerun(small, tmp_path) -> None:
    if not LINUX:
        pytest.skip("needs /proc")
    cal, inp, out = str(small["cal"]), str(small["in"]), tmp_path / "out"
    args = ("process", inp, "-c", cal, "-o", str(out))
    # 1. while starting (before any capture).
    p = _lfcam(*args)
    time.sleep(0.3)
    _kill(p)
    # 2. in the middle of a capture (its lock is held), after another one completed.
    p = _lfcam(*args)
    _wait_for(
        lambda: (
            out.is_dir() and list(out.rglob("result.json")) and list(out.rglob(".*.lfcam-lock"))
        ),
        "a second capture",
        p,
    )
    _kill(p)
    # 3. while a capture's folder is being written.
    p = _lfcam(*args)
    _wait_for(lambda: out.is_dir() and list(out.rglob(".*.tmp-*")), "a temporary folder", p)
    _kill(p)
    assert _temporaries(out)  # something was left behind
    # 4. --jobs 2: one worker in the middle of a capture, then the parent.
    p = _lfcam(*args, "--jobs", "2")
    lock = _wait_for(
        lambda: [k for k in out.rglob(".*.lfcam-lock") if _lock_holder(k) not in (None, p.pid)],
        "a worker's capture",
        p,
    )
    workers = _children(p.pid)
    victim = _lock_holder(lock[0])
    assert victim in workers
    os.kill(victim, signal.SIGKILL)
    _wait_for(
        lambda: len([w for w in _children(p.pid) if _alive(w)]) >= len(workers), "a new worker", p
    )
    workers = _children(p.pid)
    _wait_for(lambda: [k for k in out.rglob(".*.lfcam-lock") if k != lock[0]], "another capture", p)
    _kill(p)
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.05)
    assert [w for w in workers if _alive(w)] == []  # workers died with their parent
    # The rerun completes what is missing and removes what the killed runs left.
    p = _lfcam(*args)
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 0, stderr
    assert "skipped" in stdout
    _assert_same(out, small["ref"])


def test_concurrent_runs_share_the_work(small, tmp_path) -> None:
    """Two runs on one output folder at once: each capture is processed once."""
    out = tmp_path / "out"
    args = ("process", str(small["in"]), "-c", str(small["cal"]), "-o", str(out))
    runs = [_lfcam(*args), _lfcam(*args)]
    texts = [p.communicate(timeout=300) for p in runs]
    assert [p.returncode for p in runs] == [0, 0], texts
    done = [int(t[0].split("processed ")[1].split()[0]) for t in texts]
    assert sum(done) == len(NAMES), texts
    _assert_same(out, small["ref"])


# ---------------------------------------------------------------------------
# On a Dask cluster (lfcam[dask])
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dask_client():
    """A LocalCluster of 2 worker processes (1 thread each) and its client."""
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client


def test_cluster_without_workers_is_an_input_error() -> None:
    """A fresh scheduler (dask-jobqueue jobs still queued): no worker joins in time."""
    distributed = pytest.importorskip("distributed")
    from lfcam.batch.cluster import cluster_shape

    with (
        distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as cluster,
        distributed.Client(cluster) as client,
    ):
        t0 = time.monotonic()
        with pytest.raises(lfcam.InputError) as e:
            cluster_shape(client, 1.0)
        assert time.monotonic() - t0 < 10
        assert str(e.value) == (
            f"cluster LocalCluster at {cluster.scheduler_address}: no Dask worker joined"
            " within 1 s (are its jobs still waiting in the queue?)"
        )
        cluster.scale(1)
        assert cluster_shape(client, 60.0) == (1, max(1, os.cpu_count() or 1))


def test_cluster_task_reason_worded_as_locally(tmp_path, monkeypatch) -> None:
    """A worker that cannot load the calibration says why as the local pool would."""
    from lfcam.batch import cluster
    from lfcam.batch.task import CaptureTask, ProcessOptions

    cal = tmp_path / "cam.lfcal"
    cal.write_bytes(b"not the batch's")
    monkeypatch.setattr(cluster, "_setup_worker", lambda: (1, 1))
    got = cluster._cluster_task(
        CaptureTask("a.png", str(tmp_path / "a")), str(cal), "0" * 64, ProcessOptions(), {}, False
    )
    assert got.status == "failed"
    assert got.reason == (
        f"{cal}: sha256 {lfcam.io.file_hash(cal)} differs from the expected {'0' * 64}"
    )


def test_cluster_identical_to_jobs_1_calibration_once(small, dask_client, tmp_path) -> None:
    from lfcam.batch.cluster import calibration_loads

    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    out = tmp_path / "out"
    seen: list[int] = []
    summary = lfcam.process_folder(
        [small["in"], bad],
        small["cal"],
        out,
        client=dask_client,
        progress=lambda o, k, n: seen.append(k),
    )
    assert [s for s, _ in summary.failed] == [str(bad)]
    assert len(summary.done) == len(NAMES)
    assert seen == list(range(1, len(NAMES) + 2))
    assert (summary.workers, summary.threads) == (2, 1)
    _assert_same(out, small["ref"])
    # Each worker loaded the calibration once, not once per task.
    sha = lfcam.io.file_hash(small["cal"])
    loads = dask_client.run(calibration_loads)
    assert sorted(loads.values(), key=str) == [{sha: 1}, {sha: 1}]
    # A calibration without a file is scattered to the workers.
    out2 = tmp_path / "out2"
    cal = lfcam.Calibration.load(small["cal"])
    summary = lfcam.process_folder(small["in"] / "sub", cal, out2, client=dask_client)
    assert len(summary.done) == 2
    for name in ("planes2", "spheres2"):
        # The TIFFs' metadata names the calibration file (none here): compare pixels.
        for f in ("depth.tiff", "confidence.tiff"):
            got = lfcam.read_image(out2 / name / f)
            want = lfcam.read_image(small["ref"] / "sub" / name / f)
            assert got.tobytes() == want.tobytes()
        ply = (out2 / name / "points.ply").read_bytes()
        assert ply == (small["ref"] / "sub" / name / "points.ply").read_bytes()


def test_cluster_worker_killed_mid_batch(small, dask_client, tmp_path) -> None:
    """A worker SIGKILLed in the middle of a capture: its nanny restarts it, Dask runs
    the capture again, and the batch completes with nothing half-written."""
    if not LINUX:
        pytest.skip("needs /proc/locks")
    out = tmp_path / "out"
    killed: list[str] = []
    t = threading.Thread(target=_kill_a_lock_holder, args=(out, killed))
    t.start()
    summary = lfcam.process_folder(small["in"], small["cal"], out, client=dask_client)
    t.join()
    assert len(killed) == 1
    assert (len(summary.done), summary.failed) == (len(NAMES), ())
    _assert_same(out, small["ref"])
    dask_client.wait_for_workers(2, timeout=60)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_cluster_command_line(small, tmp_path, capsys) -> None:
    pytest.importorskip("distributed")
    from lfcam.cli import main

    args = ["process", str(small["in"]), "-c", str(small["cal"])]
    out = tmp_path / "out"
    assert main([*args, "-o", str(out), "--cluster", "local:2"]) == 0
    text = capsys.readouterr().out
    assert "dask cluster local:2: dashboard http://" in text
    assert f"processed {len(NAMES)} capture(s)" in text
    _assert_same(out, small["ref"])
    # Nobody listening: exit 2 within the timeout (plus start-up), naming --cluster.
    t0 = time.monotonic()
    where = f"tcp://127.0.0.1:{_free_port()}"
    code = main([*args, "-o", str(tmp_path / "o2"), "--cluster", where, "--cluster-timeout", "2"])
    assert code == 2
    assert time.monotonic() - t0 < 2 + 20
    assert f"--cluster: no Dask scheduler answered at {where} within 2 s" in capsys.readouterr().err
    for bad, msg in (
        (["--cluster", "local:0"], "--cluster: expected local:N with N >= 1"),
        (["--cluster", "slurm:x"], "--cluster: expected slurm[:JOBS]"),
        (["--cluster", "local:2", "--jobs", "2"], "--jobs: not with --cluster"),
        (["--cluster", "local:1", "--cluster-timeout", "0"], "--cluster-timeout: must be > 0"),
    ):
        assert main([*args, "-o", str(tmp_path / "o3"), *bad]) == 2
        assert msg in capsys.readouterr().err


def test_cluster_needs_the_extra(small, tmp_path, capsys, monkeypatch) -> None:
    from lfcam.cli import main

    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    args = ["process", str(small["in"]), "-c", str(small["cal"]), "-o", str(tmp_path / "o")]
    assert main([*args, "--cluster", "local:2"]) == 2
    assert 'install the extra: pip install "lfcam[dask]"' in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


SLURM_YAML = """\
jobqueue:
  slurm:
    cores: 8            # per batch job
    processes: 2        # Dask workers per job, 4 threads each
    memory: 16GB
    walltime: "01:00:00"
    queue: normal
    account: mylab
    job-script-prologue:
      - source /opt/lfcam/venv/bin/activate
"""


def test_slurm_config(tmp_path) -> None:
    pytest.importorskip("dask_jobqueue")
    from lfcam.batch.cluster import make_jobqueue_cluster

    cfg = tmp_path / "slurm.yaml"
    cfg.write_text(SLURM_YAML)
    with make_jobqueue_cluster("slurm", cfg) as cluster:
        script = cluster.job_script()
    for line in (
        "#SBATCH -p normal",
        "#SBATCH -A mylab",
        "#SBATCH --cpus-per-task=8",
        "#SBATCH -t 01:00:00",
        "source /opt/lfcam/venv/bin/activate",
    ):
        assert line in script.splitlines()
    assert "--nthreads 4" in script
    assert "--nworkers 2" in script
    cfg.write_text("jobqueue:\n  slurm:\n    cores: 8\n")
    with pytest.raises(
        lfcam.InputError, match=r"slurm.yaml: cannot start a slurm cluster: .*memory"
    ):
        make_jobqueue_cluster("slurm", cfg)
    cfg.write_text("jobqueue: [")
    with pytest.raises(lfcam.InputError, match=r"slurm.yaml: not a readable YAML file"):
        make_jobqueue_cluster("slurm", cfg)
