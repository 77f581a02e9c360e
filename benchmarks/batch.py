"""Batch throughput: captures per second locally (--jobs) and on Dask (not part of the
test run).

    python benchmarks/batch.py [--size tiny|small] [--captures N] [--repeats R]
    python benchmarks/batch.py --calibration CAM.lfcal --inputs DIR   # your captures

Rows: captures per second of ``lfcam.process_folder`` with ``--jobs 1`` and ``--jobs 2``
and on a Dask ``LocalCluster`` of 1 and 2 worker processes (cores split among them, as
``--cluster local:N`` does; the cluster's start-up is not counted, its own row says
what it costs); Dask's overhead per task, as a share of a capture's processing time
(target: under 5%): the batch's wall time on one single-threaded worker less the time
the captures themselves took, per task, less the same for ``--jobs 1`` (lfcam's own
per-batch work: the calibration's checksum, the sweep for stale temporaries), and the
round trip of an empty task; and the
peak memory (maximum resident set) of a worker (target: <= 2 GB for full-size
captures; run it with a full-size calibration and its captures for that). The
captures are simulated (``tiny``: 2 x 3 views of 200 x 150 px; ``small``: the
reference camera, 3 x 4 views of 480 x 360 px) and copied to make ``--captures``. The
machine is shared and noisy: medians and ranges over the repeats.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lfcam
from lfcam.calibration.calibrate import run_calibration
from lfcam.sim import SimConfig

TARGET_MB = "target <= 2048 MB (full size)"
SIZES = {
    "tiny": SimConfig(view_size=(200, 150), grid=(2, 3), captures_per_distance=2, seed=5),
    "small": SimConfig(captures_per_distance=2, seed=5),
}


def _prepare(size: str, n: int, root: Path) -> tuple[Path, Path]:
    cfg = SIZES[size]
    sim = lfcam.simulate(root / "sim", cfg, truth=False)
    cal = root / "camera.lfcal"
    run_calibration(sim.calibration_dir).save(cal)
    inp = root / "in"
    inp.mkdir()
    scenes = list(sim.captures.values())
    for k in range(n):
        shutil.copy(scenes[k % len(scenes)], inp / f"c{k:03d}.png")
    return cal, inp


def _peak_mb(pid: int | str = "self") -> float:
    """A process's peak resident memory, MB (VmHWM: of its own address space, unlike
    ru_maxrss, which a spawned child inherits from the parent it was forked from)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


class _ChildPeaks(threading.Thread):
    """Samples the peak memory of this process's children while a batch runs."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.peaks: dict[int, float] = {}
        self.stop = threading.Event()

    def run(self) -> None:
        me = str(os.getpid())
        while not self.stop.wait(0.2):
            for d in Path("/proc").iterdir():
                try:
                    parent = (d / "stat").read_text().rsplit(")", 1)[1].split()[1]
                    # The pool's workers, not multiprocessing's resource tracker.
                    if parent == me and b"spawn_main" in (d / "cmdline").read_bytes():
                        pid = int(d.name)
                        self.peaks[pid] = max(self.peaks.get(pid, 0.0), _peak_mb(pid))
                except (OSError, IndexError):
                    continue


def _timed(run: Callable[[Path], lfcam.BatchSummary], out: Path) -> tuple[float, Any]:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    summary = run(out)
    wall = time.perf_counter() - t0
    if summary.failed or len(summary.done) != len(summary.outcomes):
        raise SystemExit(f"the batch did not complete: {summary.failed}")
    return wall, summary


def _row(label: str, values: list[float], unit: str, note: str = "") -> None:
    med = statistics.median(values)
    print(f"  {label:34} {med:9.3f} {unit:12} [{min(values):.3f} .. {max(values):.3f}]  {note}")


def _noop() -> None:
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=sorted(SIZES), default="tiny")
    ap.add_argument("--captures", type=int, default=12)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--calibration", type=Path, help="with --inputs: your own captures")
    ap.add_argument("--inputs", type=Path)
    ap.add_argument("--no-dask", action="store_true", help="only the --jobs rows")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        if args.calibration is not None and args.inputs is not None:
            cal, inp = args.calibration, args.inputs
            what = f"{args.inputs}"
        else:
            t0 = time.perf_counter()
            cal, inp = _prepare(args.size, args.captures, root)
            what = (
                f"{args.captures} simulated {args.size} captures ({time.perf_counter() - t0:.0f} s)"
            )
        n = len(lfcam.batch.find_captures(inp, root / "x"))
        c = lfcam.Calibration.load(cal)
        print(
            f"batch of {n} captures: {what}; {c.grid[0]}x{c.grid[1]} views of "
            f"{c.rect_shape[1]}x{c.rect_shape[0]} px; {os.cpu_count()} cores, "
            f"load {os.getloadavg()[0]:.1f}"
        )
        print(f"  {'row':34} {'median':>9} {'unit':12} [range over {args.repeats} runs]")
        out = root / "out"
        per_capture: list[float] = []
        local_over: list[float] = []
        for jobs in (1, 2):
            rates = []
            watch = _ChildPeaks()
            watch.start()
            for _ in range(args.repeats):
                wall, s = _timed(lambda o, j=jobs: lfcam.process_folder(inp, cal, o, jobs=j), out)
                rates.append(len(s.done) / wall)
                if jobs == 1:
                    per_capture += [o.seconds for o in s.outcomes]
                    local_over.append((wall - sum(o.seconds for o in s.outcomes)) / n)
            watch.stop.set()
            watch.join()
            _row(f"--jobs {jobs}", rates, "captures/s")
            if jobs > 1:
                peaks = [v for v in watch.peaks.values() if v > 0]
                _row("  peak memory of a worker", peaks or [float("nan")], "MB", TARGET_MB)
        _row("  one capture (--jobs 1)", per_capture, "s")
        _row("  batch overhead per task, --jobs 1", local_over, "s", "(lfcam's own)")
        if not args.no_dask:
            _dask_rows(inp, cal, out, args.repeats, statistics.median(per_capture), local_over)
        print(f"  load after: {os.getloadavg()[0]:.1f}")


def _dask_rows(
    inp: Path, cal: Path, out: Path, repeats: int, capture_s: float, local_over: list[float]
) -> None:
    import distributed

    from lfcam.batch.cluster import cluster_client

    for workers in (1, 2):
        t0 = time.perf_counter()
        with cluster_client(f"local:{workers}") as client:
            start = time.perf_counter() - t0
            client.wait_for_workers(workers)
            rates = []
            for _ in range(repeats):
                wall, s = _timed(lambda o: lfcam.process_folder(inp, cal, o, client=client), out)
                rates.append(len(s.done) / wall)
            _row(f"--cluster local:{workers}", rates, "captures/s", f"start-up {start:.1f} s")
            peaks = client.run(_peak_mb)
            _row(
                "  peak memory of a worker",
                list(peaks.values()),
                "MB",
                TARGET_MB,
            )
    # Overhead: one worker, one thread, so the tasks run one after another.
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        over = []
        for _ in range(repeats):
            wall, s = _timed(lambda o: lfcam.process_folder(inp, cal, o, client=client), out)
            over.append((wall - sum(o.seconds for o in s.outcomes)) / len(s.outcomes))
        _row("  batch overhead per task, Dask", over, "s")
        dask_over = statistics.median(over) - statistics.median(local_over)
        print(
            f"  {'Dask overhead per task':34} {dask_over:9.3f} {'s':12} (the two medians' "
            f"difference) {100 * dask_over / capture_s:.1f}% of a capture; target < 5%"
        )
        trips = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            distributed.wait([client.submit(_noop, pure=False) for _ in range(100)])
            trips.append((time.perf_counter() - t0) / 100)
        _row("empty task, per task", trips, "s")


if __name__ == "__main__":
    main()
