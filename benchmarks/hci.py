"""lfcam's depth chain on the HCI 4D light-field benchmark (not part of the test run).

    python benchmarks/hci.py [--data DIR] [--scene antinous] [--grids 3x4,9x9]
                             [--repeats N] [--ablation]

Scores the disparity of the centre view (4, 4) with the benchmark's own metrics,
BadPix0.07 (% of pixels with |d - gt| > 0.07 px) and MSE x 100, over the full
image and without a 15 px border, for the 3 x 4 subset rows 3-5 x cols 3-6 (the
paper's reference position) and the full 9 x 9 grid, beside the naive way in the
same run: OpenCV DIS (MEDIUM preset) from the reference to each view and plain
least squares of the flows onto the offsets. Times are medians over the repeats
(flows included). ``--ablation`` adds lfcam without the parallax fill and without
the backward flows, to show what each step pays.

Targets, antinous 3 x 4: BadPix0.07 <= 10%, MSE x 100 <= 5, <= 1 s on
2 cores; 9 x 9 at least as good as 3 x 4. The data is read in place from
``../shared/data`` (its licence forbids bundling it).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

import lfcam
from lfcam.sim.metrics import disparity_metrics

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
GRIDS = {"3x4": "3:6,3:7", "9x9": "0:9,0:9", "3x3": "3:6,3:6", "5x5": "2:7,2:7"}


def naive(lf: lfcam.LightField) -> np.ndarray:
    """DIS MEDIUM reference -> each view, plain least squares onto the offsets."""
    grey = [cv2.cvtColor(np.ascontiguousarray(v), cv2.COLOR_RGB2GRAY) for v in lf.views]
    ref = lf.reference
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    num = np.zeros(lf.image_shape, np.float64)
    den = 0.0
    for i, o in enumerate(lf.offsets):
        if i == ref:
            continue
        f = dis.calc(grey[ref], grey[i], None)
        num += f[..., 0] * o[0] + f[..., 1] * o[1]
        den += float(o @ o)
    return (num / den).astype(np.float32)


def timed(fn: Callable[[], np.ndarray], repeats: int) -> tuple[np.ndarray, float]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    assert out is not None
    return out, statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA, help="the shared data folder")
    ap.add_argument("--scene", default="antinous", help="hci4d_<scene> under --data")
    ap.add_argument("--grids", default="3x4,9x9", help=f"comma-separated, of {sorted(GRIDS)}")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ablation", action="store_true", help="also lfcam without fill / backward")
    args = ap.parse_args()
    folder = args.data / f"hci4d_{args.scene}"
    if not folder.is_dir():
        print(f"skipped: {folder} not found (the HCI data is not bundled)", file=sys.stderr)
        return 0
    print(f"scene {args.scene}; lfcam threads {lfcam.get_num_threads()}; repeats {args.repeats}")
    cols = ("BadPix0.07", "(b15)", "MSE*100", "(b15)", "time s")
    head = f"{'grid':5} {'method':22} " + " ".join(
        f"{c:>{n}}" for c, n in zip(cols, (10, 7, 8, 7, 7))
    )
    print(head)
    print("-" * len(head))
    for grid in args.grids.split(","):
        lf = lfcam.LightField.from_folder(folder, views=GRIDS[grid], reference=(4, 4))
        gt = lf.ground_truth
        assert gt is not None, f"{folder}: no gt_disp_lowres.pfm"
        methods: dict[str, Callable[[], np.ndarray]] = {
            "naive DIS + LSQ": lambda lf=lf: naive(lf),
            "lfcam": lambda lf=lf: lf.estimate_depth().parallax,
        }
        if args.ablation:
            methods["lfcam, no fill"] = lambda lf=lf: (
                lf.estimate_depth(lfcam.DepthParams(fill=False)).parallax
            )
            methods["lfcam, no backward"] = lambda lf=lf: (
                lf.estimate_depth(lfcam.DepthParams(backward=False)).parallax
            )
        for name, fn in methods.items():
            d, t = timed(fn, args.repeats)
            full = disparity_metrics(d, gt)
            b15 = disparity_metrics(d, gt, border=15)
            print(
                f"{grid:5} {name:22} {full['badpix_percent']:9.1f}% {b15['badpix_percent']:6.1f}%"
                f" {full['mse_x100']:8.2f} {b15['mse_x100']:7.2f} {t:7.2f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
