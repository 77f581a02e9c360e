"""End-to-end timings: simulate, calibrate, process (not part of the test run).

    python benchmarks/pipeline.py [--size small|full] [--repeats N] [--keep DIR]

Prints one row per stage with the median wall time over the repeats and the
issue targets beside them: simulate (3 x 4, 480 x 360 views, calibration folder
+ 3 scenes) < 60 s; calibrate (same camera) < 60 s; process one capture, depth
only (full size: <= 2 s). The machine is shared and noisy: quote medians.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import lfcam
from lfcam.calibrate import run_calibration
from lfcam.pipeline import process_capture
from lfcam.simulator import SimConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=("small", "full"), default="small")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--keep", type=Path, help="keep the simulated folder here")
    args = ap.parse_args()
    cfg = SimConfig() if args.size == "small" else SimConfig.full_size()
    rows: dict[str, list[float]] = {"simulate": [], "calibrate": [], "process (1 capture)": []}
    extra: dict[str, str] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for k in range(args.repeats):
            out = root / f"sim{k}"
            t0 = time.perf_counter()
            sim = lfcam.simulate(out, cfg, overwrite=True)
            rows["simulate"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            cal = run_calibration(sim.calibration_dir).calibration
            rows["calibrate"].append(time.perf_counter() - t0)
            for path in sim.captures.values():
                t0 = time.perf_counter()
                res = process_capture(path, cal)
                rows["process (1 capture)"].append(time.perf_counter() - t0)
                extra = {s: f"{v:.2f}" for s, v in res.timings.items()}
            peak_mb = _process_peak_rss(path, sim.calibration_dir, cal)
    targets = {
        "simulate": "< 60 s (small)",
        "calibrate": "< 60 s (small)",
        "process (1 capture)": "<= 2 s (full size)",
    }
    print(
        f"lfcam {lfcam.__version__}, {cfg.grid[0]}x{cfg.grid[1]} views of "
        f"{cfg.view_size[0]}x{cfg.view_size[1]} px, {os.cpu_count()} cores"
    )
    print(f"{'stage':22} {'median s':>9} {'runs':>5}  target")
    for stage, times in rows.items():
        print(f"{stage:22} {statistics.median(times):9.2f} {len(times):5d}  {targets[stage]}")
    print("last capture's stages (s): " + ", ".join(f"{k} {v}" for k, v in extra.items()))
    print(f"peak memory of a process run on its own: {peak_mb:.0f} MB (target <= 2048 MB)")


def _process_peak_rss(capture: Path, workdir: Path, cal: lfcam.Calibration) -> float:
    """Peak resident memory (MB) of one capture processed in a fresh interpreter.

    The child reports its own peak (``ru_maxrss`` of ``RUSAGE_SELF``): the parent's
    ``RUSAGE_CHILDREN`` figure is the maximum over every child it ever waited for,
    which includes the simulator's and calibration's workers.
    """
    calf = workdir / "bench.lfcal"
    cal.save(calf)
    code = (
        "import resource, lfcam; from lfcam.pipeline import process_capture;"
        f"process_capture({str(capture)!r}, lfcam.Calibration.load({str(calf)!r}));"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return int(out.stdout.split()[-1]) / 1024.0  # Linux: kB


if __name__ == "__main__":
    main()
