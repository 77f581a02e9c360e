"""Make the README's pictures from the simulator: ``python docs/make_figures.py``.

Writes ``docs/images/overview.png``: a simulated raw frame (12 views behind one
front lens) beside the reference view's ground-truth depth.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import tifffile

import lfcam


def colourise_depth(depth: np.ndarray) -> np.ndarray:
    """Depth (metres) -> RGB uint8 with OpenCV's TURBO map, near = red."""
    lo, hi = np.nanpercentile(depth, [1, 99])
    t = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    bgr = cv2.applyColorMap(np.round((1 - t) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    return bgr[..., ::-1]


def main(out: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        res = lfcam.simulate(Path(tmp) / "sim", scenes=("layered",), captures_per_distance=1)
        raw = lfcam.read_image(res.captures["layered"])
        depth = tifffile.imread(res.truth_dir / "layered" / "depth.tiff")
    h = 360
    raw_small = cv2.resize(raw, (raw.shape[1] * h // raw.shape[0], h), interpolation=cv2.INTER_AREA)
    d = colourise_depth(depth)
    d_small = cv2.resize(d, (d.shape[1] * h // d.shape[0], h), interpolation=cv2.INTER_AREA)
    gap = np.full((h, 12, 3), 255, np.uint8)
    fig = np.concatenate([raw_small, gap, d_small], axis=1)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), fig[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "images" / "overview.png")
