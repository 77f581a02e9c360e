"""End-to-end timings: simulate, calibrate, process (not part of the test run).

    python benchmarks/pipeline.py [--size small|full] [--repeats N] [--keep DIR]
    python benchmarks/pipeline.py --reuse DIR/sim0    # the captures of a kept folder

Prints one row per stage with the median wall time over the repeats and the
issue targets beside them: simulate (3 x 4, 480 x 360 views, calibration folder
+ 3 scenes) < 60 s; calibrate (same camera) < 60 s; process one capture, depth
only (full size: <= 2 s); the peak memory of one capture processed in a fresh
interpreter (<= 2 GB); and each capture's depth accuracy against the simulator's
truth. The full-size simulation and calibration take tens of minutes: keep the
folder with ``--keep`` and time the processing again with ``--reuse``. The machine
is shared and noisy: quote medians.
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
from typing import Any

import tifffile

import lfcam
from lfcam.calibration.calibrate import run_calibration
from lfcam.pipeline import process_capture
from lfcam.sim import SimConfig, depth_accuracy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=("small", "full"), default="small")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--keep", type=Path, help="keep the simulated folder here")
    ap.add_argument(
        "--reuse",
        type=Path,
        help="process the captures of a folder kept by --keep (its calibration/bench.lfcal"
        " included) instead of simulating and calibrating again",
    )
    args = ap.parse_args()
    cfg = SimConfig() if args.size == "small" else SimConfig.full_size()
    rows: dict[str, list[float]] = {"simulate": [], "calibrate": [], "process (1 capture)": []}
    extra: dict[str, str] = {}
    accuracy: list[tuple[str, float, float, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for k in range(args.repeats):
            if args.reuse:
                sim_root = args.reuse
                cal = lfcam.Calibration.load(sim_root / "calibration" / "bench.lfcal")
                captures = {p.stem: p for p in sorted((sim_root / "captures").iterdir())}
            else:
                t0 = time.perf_counter()
                sim = lfcam.simulate(root / f"sim{k}", cfg, overwrite=True)
                rows["simulate"].append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                cal = run_calibration(sim.calibration_dir).calibration
                rows["calibrate"].append(time.perf_counter() - t0)
                sim_root, captures = sim.root, sim.captures
                cal.save(sim_root / "calibration" / "bench.lfcal")
            for name, path in captures.items():
                t0 = time.perf_counter()
                res = process_capture(path, cal)
                rows["process (1 capture)"].append(time.perf_counter() - t0)
                extra = {s: f"{v:.2f}" for s, v in res.timings.items()}
                if k == 0 or not args.reuse:  # reused captures: the same numbers again
                    label = name if args.reuse or args.repeats == 1 else f"{name} #{k + 1}"
                    accuracy.append((label, *_accuracy(res, cal, sim_root / "truth" / name)))
            peak_mb = _process_peak_rss(path, sim_root / "calibration" / "bench.lfcal")
    targets = {
        "simulate": "< 60 s (small)",
        "calibrate": "< 60 s (small)",
        "process (1 capture)": "<= 2 s (full size)",
    }
    print(
        f"lfcam {lfcam.__version__}, {cal.grid[0]}x{cal.grid[1]} views, rectified"
        f" {cal.masks.shape[2]}x{cal.masks.shape[1]} px, {os.cpu_count()} cores"
    )
    print(f"{'stage':22} {'median s':>9} {'runs':>5}  target")
    for stage, times in rows.items():
        if times:
            print(f"{stage:22} {statistics.median(times):9.2f} {len(times):5d}  {targets[stage]}")
    print("last capture's stages (s): " + ", ".join(f"{k} {v}" for k, v in extra.items()))
    print(f"peak memory of a process run on its own: {peak_mb:.0f} MB (target <= 2048 MB)")
    print("accuracy against the simulator's truth (targets: median <= 1%, <= 5% off by > 5%,")
    print("coverage >= 95%; all pixels the reference sees, occlusion bands included):")
    for name, med, bad, cov in accuracy:
        print(
            f"  {name:12} median |dZ|/Z {100 * med:6.2f}%  off by > 5% {100 * bad:6.2f}%"
            f"  coverage {100 * cov:5.1f}%"
        )


def _accuracy(res: Any, cal: lfcam.Calibration, truth_dir: Path) -> tuple[float, float, float]:
    """Median relative depth error, share off by > 5% and coverage, as ``lfcam demo``."""
    truth = tifffile.imread(truth_dir / "depth.tiff")
    return depth_accuracy(res.depth.depth, truth, cal.masks[cal.reference])


def _process_peak_rss(capture: Path, calf: Path) -> float:
    """Peak resident memory (MB) of one capture processed in a fresh interpreter.

    The child reports its own peak, ``VmHWM`` of ``/proc/self/status`` (Linux): not
    ``ru_maxrss``, which Linux carries over ``execve`` from the forked copy of this
    parent (after a simulation, a gigabyte that the child never used), nor the
    parent's ``RUSAGE_CHILDREN`` (the maximum over every child ever waited for).
    """
    code = (
        "import lfcam; from lfcam.pipeline import process_capture;"
        f"process_capture({str(capture)!r}, lfcam.Calibration.load({str(calf)!r}));"
        "print([l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')][0])"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return int(out.stdout.split()[-1]) / 1024.0  # Linux: kB


if __name__ == "__main__":
    main()
