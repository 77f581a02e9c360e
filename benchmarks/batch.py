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
import resource
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lfcam
from lfcam.calibration.calibrate import run_calibration
from lfcam.sim import SimConfig

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


def _peak_mb_self() -> float:
    # Linux reports kilobytes, macOS bytes.
    scale = 1 if sys.platform == "darwin" else 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale / 2**20


def _peak_mb_children() -> float:
    scale = 1 if sys.platform == "darwin" else 1024
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * scale / 2**20


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
            for _ in range(args.repeats):
                wall, s = _timed(lambda o, j=jobs: lfcam.process_folder(inp, cal, o, jobs=j), out)
                rates.append(len(s.done) / wall)
                if jobs == 1:
                    per_capture += [o.seconds for o in s.outcomes]
                    local_over.append((wall - sum(o.seconds for o in s.outcomes)) / n)
            _row(f"--jobs {jobs}", rates, "captures/s")
        _row("  one capture (--jobs 1)", per_capture, "s")
        _row("  batch overhead per task, --jobs 1", local_over, "s", "(lfcam's own)")
        peak = _peak_mb_children()
        _row("peak memory of a --jobs 2 worker", [peak], "MB", "target <= 2048 MB (full size)")
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
            peaks = client.run(_peak_mb_self)
            _row(
                f"peak memory of a local:{workers} worker",
                list(peaks.values()),
                "MB",
                "target <= 2048 MB (full size)",
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
