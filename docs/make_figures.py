"""Make the documentation's pictures from the simulator.

``python docs/make_figures.py`` writes ``docs/images/overview.png``: a simulated raw
frame (12 views behind one front lens) beside the reference view's ground-truth depth.
``python docs/make_figures.py calibration`` writes the calibration guide's pictures
(:func:`calibration_figures`).
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




def _small(img: np.ndarray, h: int) -> np.ndarray:
    return cv2.resize(img, (img.shape[1] * h // img.shape[0], h), interpolation=cv2.INTER_AREA)


def _to_u8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    return img if img.ndim == 3 else np.repeat(img[..., None], 3, 2)


def calibration_figures(images: Path) -> None:
    """The calibration guide's pictures, from a small simulated camera:

    - ``calibration_captures.png``: a white capture beside a board capture;
    - ``calibration_report.png``: the report picture of a good calibration;
    - ``sensor_layout.svg``: the report page's sensor layout with the ``o_i`` arrows;
    - ``bad_calibration_report.png``: the report picture when the top half of one
      lenslet was covered in every board capture, and ``bad_calibration_verdicts.txt``
      the verdicts its report page gives.
    """
    from lfcam.calibration import run_calibration
    from lfcam.calibration.report import calibration_figure
    from lfcam.calibration.report_page import _layout_svg, report_verdicts

    with tempfile.TemporaryDirectory() as tmp:
        cfg = lfcam.SimConfig(view_size=(320, 240), scenes=(), captures_per_distance=3)
        sim = lfcam.simulate(Path(tmp) / "sim", cfg, truth=False)
        cal_dir = sim.calibration_dir
        white = lfcam.read_image(sorted((cal_dir / "white").iterdir())[0])
        board = lfcam.read_image(sorted((cal_dir / "board_1.00m").iterdir())[0])
        gap = np.full((300, 12, 3), 255, np.uint8)
        pair = [_small(_to_u8(white), 300), gap, _small(_to_u8(board), 300)]
        cv2.imwrite(
            str(images / "calibration_captures.png"),
            np.concatenate(pair, 1)[..., ::-1],
            [cv2.IMWRITE_PNG_COMPRESSION, 9],
        )
        run = run_calibration(cal_dir)
        fig = calibration_figure(run.calibration, run.white, run.residuals, width=800)
        cv2.imwrite(
            str(images / "calibration_report.png"), fig[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9]
        )
        (images / "sensor_layout.svg").write_text(_layout_svg(run.calibration, 700) + "\n")
        # A bad calibration: the top half of view (1, 2) covered in every board capture.
        x0, y0, w, h = (int(v) for v in run.calibration.crops[6])
        for folder in cal_dir.glob("board_*m"):
            for p in folder.iterdir():
                img = lfcam.read_image(p)
                img[y0 : y0 + h // 2, x0 : x0 + w] = img[y0 : y0 + h // 2, x0 : x0 + w].mean()
                lfcam.io.write_image(p, img)
        bad = run_calibration(cal_dir)
        fig = calibration_figure(bad.calibration, bad.white, bad.residuals, width=800)
        cv2.imwrite(
            str(images / "bad_calibration_report.png"),
            fig[..., ::-1],
            [cv2.IMWRITE_PNG_COMPRESSION, 9],
        )
        v = report_verdicts(bad.calibration.report)
        lines = [f"overall {v['overall']}"]
        for view, d in zip(bad.calibration.report["views"], v["views"]):
            lines.append(
                f"view {tuple(view['row_col'])}: residual {view['photometric_residual_rms']:.3f}"
                f" {d['residual']}, coverage {100 * view['coverage']:.1f} % {d['coverage']},"
                f" last flow update {view['last_flow_update_px']:.4f} px {d['flow']}"
            )
        s = bad.calibration.report["summary"]
        lines.append(
            f"parallax fit {s['parallax_fit_rms_px']:.4f} px {v['parallax_fit']},"
            f" perpendicular {s['perpendicular_parallax_rms_px']:.4f} px {v['perpendicular']}"
        )
        (images / "bad_calibration_verdicts.txt").write_text("\n".join(lines) + "\n")
    print(f"wrote the calibration guide's pictures to {images}")


if __name__ == "__main__":
    if sys.argv[1:] == ["calibration"]:
        calibration_figures(Path(__file__).parent / "images")
    else:
        main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "images" / "overview.png")
