"""The optical flow alone: DIS settings against Middlebury's ground truth.

    python benchmarks/flow_tuning.py [--data DIR] [--repeats N]

lfcam computes flow with OpenCV's DIS on locally contrast-normalised 8-bit images
(:func:`lfcam.kernels.flow.prepare`). This scores candidate settings by the average
end-point error (EPE, px) against the ground truth of the Middlebury "other"
sequences (``../shared/data/middlebury_flow_other``, read in place), beside
OpenCV's presets on plain grey images, with the median time per flow. The
depth-level effect of the same settings is in ``benchmarks/hci.py``.

Chosen for depth (``lfcam.processing.depth.DEPTH_FLOW``): finest scale 0, 8 px patches,
stride 3, 25 gradient-descent and 5 variational iterations. Sub-pixel precision is
what depth needs (0.07 px BadPix on HCI); the finest scale is what buys it: the
same settings at finest scale 1 (OpenCV's MEDIUM) are 4x faster but give 24% BadPix
on HCI antinous 3 x 4 instead of 9.5%, and variational refinement at full
resolution after a scale-1 DIS recovers only part of it (18-19%). Views much
larger than HCI's (the full-size camera's 1200 x 900) are sampled finely enough for
half resolution: ``lfcam.DepthParams.flow_for`` picks the finest scale by the flow
window's size (``FLOW_MAX_PIXELS``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from lfcam.io import read_flo
from lfcam.kernels.flow import FlowParams, dis_flow, end_point_error, prepare
from lfcam.processing.depth import DEPTH_FLOW

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "middlebury_flow_other"
SEQUENCES = ("RubberWhale", "Hydrangea", "Dimetrodon", "Urban2", "Venus")

CANDIDATES = {
    "lfcam DEPTH_FLOW": DEPTH_FLOW,
    "stride 4, 12 gd": FlowParams(patch_stride=4, gradient_descent_iterations=12),
    "patch 12, stride 4": FlowParams(patch_size=12, patch_stride=4),
    "16 gd": replace(DEPTH_FLOW, gradient_descent_iterations=16),
    "20 gd": replace(DEPTH_FLOW, gradient_descent_iterations=20),
    "3 variational": FlowParams(variational_iterations=3),
    "4 variational": FlowParams(variational_iterations=4),
    "5 variational": FlowParams(variational_iterations=5),
    "no variational": FlowParams(variational_iterations=0),
    "10 variational": FlowParams(variational_iterations=10),
    "finest scale 1": FlowParams(finest_scale=1),
}
PRESETS = {
    "OpenCV ULTRAFAST (grey)": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "OpenCV FAST (grey)": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "OpenCV MEDIUM (grey)": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def load(data: Path, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = cv2.imread(str(data / "other-data" / name / "frame10.png"))[..., ::-1]
    b = cv2.imread(str(data / "other-data" / name / "frame11.png"))[..., ::-1]
    gt = read_flo(data / "other-gt-flow" / name / "flow10.flo")
    return a, b, gt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if not args.data.is_dir():
        print(
            f"skipped: {args.data} not found (the Middlebury data is not bundled)", file=sys.stderr
        )
        return 0
    cv2.setNumThreads(1)
    seqs = {n: load(args.data, n) for n in SEQUENCES}
    print("EPE (px) per sequence, mean, and median ms per flow (one thread)")
    print(
        f"{'settings':26}" + "".join(f"{n[:11]:>12}" for n in SEQUENCES) + f"{'mean':>8}{'ms':>8}"
    )

    def run(name: str, fn) -> None:  # type: ignore[no-untyped-def]
        errs, times = [], []
        for a, b, gt in seqs.values():
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                flow = fn(a, b)
                times.append(time.perf_counter() - t0)
            errs.append(end_point_error(flow, gt))
        cells = "".join(f"{e:12.3f}" for e in errs)
        ms = 1000 * statistics.median(times)
        print(f"{name:26}{cells}{np.mean(errs):8.3f}{ms:8.1f}", flush=True)

    for name, preset in PRESETS.items():
        dis = cv2.DISOpticalFlow_create(preset)
        run(
            name,
            lambda a, b, dis=dis: dis.calc(
                cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY),
                cv2.cvtColor(np.ascontiguousarray(b), cv2.COLOR_RGB2GRAY),
                None,
            ),
        )
    for name, params in CANDIDATES.items():
        fn = lambda a, b, p=params: dis_flow(  # noqa: E731
            prepare(a.astype(np.float32)), prepare(b.astype(np.float32)), p
        )
        run(name, fn)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
