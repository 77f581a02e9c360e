"""lfcam's depth chain on every HCI light field in the shared data (not part of the test run).

    python benchmarks/hci.py [--data DIR] [--repeats N] [--quick] [--ablation]
                             [--with NAME:KEY=VALUE,...] [SCENE ...]

Scenes (default all whose data is present): ``antinous-3x4``, ``antinous-9x9``,
``backgammon-3x4``, ``backgammon-9x9`` (HCI 4D, centre view (4, 4); "3 x 4" is
rows 3-5 x cols 3-6, the paper's reference position) and ``stilllife-3x3`` (old
HCI, 3 x 3 views at about 10 px per step, ground truth from ``depth.bin`` by its
README's formula). ``--quick``: the three small ones (3 x 4 and 3 x 3) once.

Each row scores the disparity of the centre view over the full image with the
benchmark's metrics, BadPix0.07 and BadPix0.3 (% of pixels off by more than 0.07 /
0.3 px; a missing estimate counts as bad) and MSE x 100, beside the naive way in
the same run: OpenCV DIS (MEDIUM preset) from the reference to each view and plain
least squares of the flows onto the offsets. Times are medians over the repeats
(flows included). ``--ablation`` adds lfcam without the parallax fill and without
the backward flows; ``--with name:key=value,...`` adds lfcam with those
:class:`lfcam.DepthParams` fields (values as Python literals; ``refine={...}`` gives
a :class:`lfcam.RefineParams` of those fields, ``refine={}`` its defaults).

Targets (docs/tuning.md, "Depth"): antinous 3 x 4 BadPix0.07 <= 5%, MSE x 100 <= 2;
9 x 9 no worse than 3 x 4; stilllife BadPix0.07 <= 30%, BadPix0.3 <= 6%,
MSE x 100 <= 20; 3 x 4 depth <= 1 s on 2 cores. The data is read in place from
``$LFCAM_DATA``, else ``../shared/data`` (its licence forbids bundling it).
"""

from __future__ import annotations

import argparse
import ast
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

import lfcam
from lfcam.sim.metrics import disparity_metrics

DATA = Path(os.environ.get("LFCAM_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")
GRIDS = {"3x4": "3:6,3:7", "9x9": "0:9,0:9"}
SCENES = ("antinous-3x4", "antinous-9x9", "backgammon-3x4", "backgammon-9x9", "stilllife-3x3")
QUICK = ("antinous-3x4", "backgammon-3x4", "stilllife-3x3")
STILLLIFE = "hci_old_stilllife_3x3"


def load(data: Path, scene: str) -> tuple[lfcam.LightField, np.ndarray] | None:
    """The light field and its ground-truth disparity; None when the data is absent."""
    name, grid = scene.split("-")
    if name == "stilllife":
        folder = data / STILLLIFE
        if not (folder / "depth.bin").is_file():
            return None
        lf = lfcam.LightField.from_folder(folder / "lf")
        # The folder's README: d = dH * focalLength / depth - shift, float32 raster order.
        depth = np.fromfile(folder / "depth.bin", "<f4").reshape(lf.image_shape)
        return lf, (614.4 * 9.375 / depth.astype(np.float64) - 288.0).astype(np.float32)
    folder = data / f"hci4d_{name}"
    if not (folder / "gt_disp_lowres.pfm").is_file():
        return None
    lf = lfcam.LightField.from_folder(folder, views=GRIDS[grid], reference=(4, 4))
    assert lf.ground_truth is not None
    return lf, lf.ground_truth


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


def variant(spec: str) -> tuple[str, dict[str, object]]:
    """``name:key=value,key=value`` -> (name, DepthParams keywords); commas inside
    brackets belong to the value."""
    name, _, fields = spec.partition(":")
    items, depth, start = [], 0, 0
    for k, ch in enumerate(fields + ","):
        depth += ch in "([{"
        depth -= ch in ")]}"
        if ch == "," and depth == 0:
            items.append(fields[start:k])
            start = k + 1
    kw: dict[str, object] = {}
    for item in filter(None, (i.strip() for i in items)):
        key, _, value = item.partition("=")
        val = ast.literal_eval(value.strip())
        # refine={...}: the fields of a RefineParams.
        kw[key.strip()] = lfcam.RefineParams(**val) if key.strip() == "refine" else val
    return name, kw


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help=f"of {', '.join(SCENES)} (default all)")
    ap.add_argument("--data", type=Path, default=DATA, help="the shared data folder")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help=f"{', '.join(QUICK)}, one repeat")
    ap.add_argument("--ablation", action="store_true", help="also lfcam without fill / backward")
    ap.add_argument(
        "--with",
        dest="variants",
        action="append",
        default=[],
        metavar="NAME:KEY=VALUE,...",
        help="also lfcam with these DepthParams fields",
    )
    ap.add_argument("--no-naive", action="store_true", help="leave out the naive rows")
    args = ap.parse_args()
    scenes = args.scenes or (QUICK if args.quick else SCENES)
    repeats = 1 if args.quick else args.repeats
    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        ap.error(f"unknown scene(s) {unknown}; known: {', '.join(SCENES)}")
    variants: dict[str, dict[str, object]] = {"lfcam": {}}
    if args.ablation:
        variants["lfcam, no fill"] = {"fill": False}
        variants["lfcam, no backward"] = {"backward": False}
    for spec in args.variants:
        name, kw = variant(spec)
        variants[f"lfcam, {name}"] = kw
    print(f"lfcam threads {lfcam.get_num_threads()}; repeats {repeats}; full image")
    cols = ("BadPix0.07", "BadPix0.3", "MSE*100", "time s")
    head = f"{'scene':15} {'method':24} " + " ".join(f"{c:>10}" for c in cols)
    print(head)
    print("-" * len(head))
    for scene in scenes:
        loaded = load(args.data, scene)
        if loaded is None:
            print(f"{scene:15} skipped: its data is not under {args.data}", file=sys.stderr)
            continue
        lf, gt = loaded
        methods: dict[str, Callable[[], np.ndarray]] = {}
        if not args.no_naive:
            methods["naive DIS + LSQ"] = lambda lf=lf: naive(lf)
        for name, kw in variants.items():
            params = lfcam.DepthParams(**kw)  # type: ignore[arg-type]
            methods[name] = lambda lf=lf, p=params: lf.estimate_depth(p).parallax
        for name, fn in methods.items():
            d, t = timed(fn, repeats)
            m07 = disparity_metrics(d, gt)
            m3 = disparity_metrics(d, gt, threshold=0.3)
            print(
                f"{scene:15} {name:24} {m07['badpix_percent']:9.1f}% {m3['badpix_percent']:9.1f}%"
                f" {m07['mse_x100']:10.2f} {t:10.2f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
