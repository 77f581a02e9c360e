"""Writing one capture's products: depth (TIFF + preview), confidence, point cloud, JSON.

Every capture's folder is assembled under a temporary name and renamed when
complete, so an interrupted run never leaves a half-written result; a folder
with ``result.json`` is complete.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from .calibration import Calibration
from .errors import InputError
from .io import _file_mode, write_image, write_pfm
from .pipeline import CaptureResult

if TYPE_CHECKING:
    from .depth import DepthResult
    from .lightfield import LightField
    from .render import NovelViewOptions

__all__ = [
    "colour_depth",
    "points_from_depth",
    "points_from_lightfield",
    "write_capture",
    "write_lightfield",
    "write_ply",
]


def colour_depth(
    depth: np.ndarray,
    lo: float | None = None,
    hi: float | None = None,
    *,
    unit: str = "m",
    near_high: bool = False,
) -> np.ndarray:
    """Depth (m) -> RGB preview with a labelled colour bar (TURBO, near = red).

    ``unit`` labels the bar; ``near_high`` says larger values are nearer (disparity),
    so they are the red ones.
    """
    finite = np.isfinite(depth)
    if lo is None or hi is None:
        if finite.any():
            lo, hi = (float(v) for v in np.percentile(depth[finite], [1, 99]))
        else:
            lo, hi = 0.0, 1.0
    hi = max(hi, lo + 1e-6)
    t = np.clip((np.nan_to_num(depth, nan=hi) - lo) / (hi - lo), 0, 1)
    if near_high:
        t = 1 - t
    bgr = cv2.applyColorMap(np.round((1 - t) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~finite] = 0
    H = depth.shape[0]
    bar_w, pad, text_w = max(12, H // 30), 8, 90
    bar = np.full((H, bar_w + pad + text_w, 3), 255, np.uint8)
    ramp = np.linspace(0, 1, H)[:, None]  # top = near (lo)
    col = cv2.applyColorMap(np.round((1 - ramp) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bar[:, pad : pad + bar_w] = np.repeat(col, bar_w, axis=1)
    for k in range(6):
        y = round(k / 5 * (H - 1))
        z = hi - (hi - lo) * k / 5 if near_high else lo + (hi - lo) * k / 5
        yt = min(max(y + 5, 12), H - 3)
        cv2.putText(
            bar,
            f"{z:.3g} {unit}",
            (pad + bar_w + 4, yt),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return np.concatenate([bgr, bar], axis=1)[..., ::-1].copy()


def points_from_depth(depth: np.ndarray, cal: Calibration) -> tuple[np.ndarray, np.ndarray, str]:
    """3-D points (metres, front-lens frame: X right, Y down, Z forward) of finite depths.

    The reference view's object-space centre is ``(b_ref, Z_c)``; its ray through
    rectified pixel p passes the board point ``B(p)`` at ``Z_b``, so the point at
    depth Z is ``C + (B - C)(Z - Z_c)/(Z_b - Z_c)``. Lateral positions need the
    pattern pitch; the lenslet array is taken as centred on the lens axis
    (``sum_i b_i = 0``). Without a pitch, X and Y are in rectified pixels at
    ``Z_b`` (units ``"board px"``).

    Returns
    -------
    points : (M, 3) float32
    index : (M, 2) int64
        Row and column of each point in the rectified frame.
    units : str
        ``"m"`` or ``"board px"`` for X and Y.
    """
    vv, uu = np.nonzero(np.isfinite(depth))
    Z = depth[vv, uu].astype(np.float64)
    sx, sy = cal.pattern_shape[1] / cal.rect_shape[1], cal.pattern_shape[0] / cal.rect_shape[0]
    xp = (uu + 0.5) * sx - 0.5 - (cal.pattern_shape[1] - 1) / 2.0
    yp = (vv + 0.5) * sy - 0.5 - (cal.pattern_shape[0] - 1) / 2.0
    metric_xy = np.isfinite(cal.pattern_pitch)
    if metric_xy:
        pitch_rect = cal.pattern_pitch * sx
        B = np.stack([xp * cal.pattern_pitch, yp * cal.pattern_pitch], 1)
    else:
        pitch_rect = 1.0
        B = np.stack([uu, vv], 1).astype(np.float64)
    if cal.metric:
        b_ref = -cal.offsets.mean(axis=0) * pitch_rect
        f = (Z - cal.z_c) / (cal.z_b - cal.z_c)
        XY = b_ref + (B - b_ref) * f[:, None]
    else:
        XY = B
    pts = np.column_stack([XY, Z]).astype(np.float32)
    return pts, np.stack([vv, uu], 1), "m" if metric_xy else "board px"


def write_ply(path: str | os.PathLike[str], points: np.ndarray, colours: np.ndarray) -> None:
    """Binary little-endian PLY: float32 x, y, z and uint8 red, green, blue per vertex."""
    n = len(points)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by lfcam\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    ).encode("ascii")
    rec = np.empty(n, dtype=[("p", "<f4", 3), ("c", "u1", 3)])
    rec["p"] = points
    rec["c"] = colours
    with open(path, "wb") as fh:
        fh.write(header)
        fh.write(rec.tobytes())


def _to_u8(img: np.ndarray) -> np.ndarray:
    x = np.nan_to_num(img, nan=0.0)
    return np.round(np.clip(x, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)


def _to_u16(img: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> 16-bit with the same display gamma (1/2.2) as the previews."""
    x = np.nan_to_num(img, nan=0.0)
    out: np.ndarray = np.round(np.clip(x, 0, 1) ** (1 / 2.2) * 65535).astype(np.uint16)
    return out


def write_capture(
    out_dir: str | os.PathLike[str],
    result: CaptureResult,
    cal: Calibration,
    *,
    extra: dict[str, Any] | None = None,
    save_views: bool = False,
    novel: NovelViewOptions | None = None,
) -> Path:
    """Write one capture's folder atomically; returns its path.

    Files: ``depth.tiff`` (float32 m, NaN unknown), ``depth.png`` (preview with
    a colour bar), ``confidence.tiff``, ``points.ply`` (coloured), ``result.json``
    and, with ``save_views``, ``views/view_RR_CC.png``; ``superres.png`` and
    ``refocus_<Z>m.png`` (16-bit RGB, display gamma 1/2.2) when the result has them;
    with ``novel``, the mesh and novel views it asks for
    (:func:`lfcam.render.write_novel_views`).
    """
    out = Path(out_dir)
    with _atomic_folder(out) as tmp:
        d = result.depth
        ref_view = result.views[cal.reference]
        depth = d.depth if d.depth is not None else d.relative
        assert depth is not None
        write_image(tmp / "depth.tiff", depth.astype(np.float32))
        write_image(tmp / "depth.png", colour_depth(depth))
        write_image(tmp / "confidence.tiff", d.confidence.astype(np.float32))
        pts, idx, units = points_from_depth(depth, cal)
        colours = _to_u8(ref_view[idx[:, 0], idx[:, 1]])
        if colours.ndim == 1:
            colours = np.repeat(colours[:, None], 3, 1)
        write_ply(tmp / "points.ply", pts, colours)
        if result.superres is not None:
            write_image(tmp / "superres.png", _to_u16(result.superres))
        for z, img in result.refocused.items():
            write_image(tmp / f"refocus_{z:g}m.png", _to_u16(img))
        if save_views:
            (tmp / "views").mkdir()
            C = cal.grid[1]
            for i, v in enumerate(result.views):
                r, c = divmod(i, C)
                write_image(tmp / "views" / f"view_{r}_{c}.png", _to_u8(v))
        finite = np.isfinite(depth)
        seen = cal.masks[cal.reference]
        stats = {
            "coverage": float(finite[seen].mean()) if seen.any() else 0.0,
            "depth_median": float(np.median(depth[finite])) if finite.any() else None,
            "depth_p1_p99": [float(v) for v in np.percentile(depth[finite], [1, 99])]
            if finite.any()
            else None,
            "confidence_median": float(np.median(d.confidence[finite])) if finite.any() else None,
            "flow_residual_median_px": float(np.nanmedian(d.residual[finite]))
            if finite.any()
            else None,
            "perpendicular_median_px": float(np.nanmedian(d.perpendicular[finite]))
            if finite.any()
            else None,
            "points": len(pts),
        }
        novel_info: dict[str, Any] = {}
        if novel is not None and novel.any:
            from .render import write_novel_views

            novel_info = {"novel_views": write_novel_views(tmp, result, cal, novel)}
        info = {
            "source": result.source,
            "depth_units": "m" if d.depth is not None else "relative (t = s Z_c / Z_b)",
            "xy_units": units,
            "rect_shape": list(cal.rect_shape),
            "reference": list(cal.reference_rc),
            "timings_s": result.timings,
            "statistics": stats,
            **novel_info,
            **(extra or {}),
        }
        (tmp / "result.json").write_text(json.dumps(info, indent=2, default=str))
    return out


@contextlib.contextmanager
def _atomic_folder(out: Path) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; when the block succeeds, it becomes ``out``.

    An existing ``out`` is replaced only then; on any error the temporary folder is
    removed and ``out`` is left as it was.
    """
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        yield tmp
        mode = _file_mode()
        for p in tmp.rglob("*"):
            os.chmod(p, (mode | 0o111) if p.is_dir() else mode)
        os.chmod(tmp, mode | 0o111)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def points_from_lightfield(depth: np.ndarray, lf: LightField) -> tuple[np.ndarray, np.ndarray]:
    """3-D points (metres) of finite depths, in the reference camera's frame.

    Pinhole model of the HCI rig: X right, Y down, Z along the optical axis, origin at
    the reference camera; focal length ``f_px`` from the rig parameters. The views
    converge (shifted sensors): the principal point of view i is the image centre
    moved by ``-offset * o_i'``, with ``o_i'`` its parallax vector relative to the
    grid's centre (infinity, at disparity ``-offset``, appears there).

    Returns
    -------
    points : (M, 3) float32
    index : (M, 2) int64
        Row and column of each point in the reference view.
    """
    p = lf.parameters
    if p is None:
        raise InputError("lf: the light field has no rig parameters; no metric points")
    H, W = depth.shape
    f = p.focal_px(W)
    offset = p.offset_for(W)
    if p.grid is not None:
        r_mid, c_mid = (p.grid[0] - 1) / 2.0, (p.grid[1] - 1) / 2.0
    else:
        r_mid = (min(lf.rows) + max(lf.rows)) / 2.0
        c_mid = (min(lf.cols) + max(lf.cols)) / 2.0
    sx = -1.0 if "x" in lf.flip else 1.0
    sy = -1.0 if "y" in lf.flip else 1.0
    r_ref, c_ref = lf.reference_rc
    cx = (W - 1) / 2.0 + offset * sx * (c_ref - c_mid)
    cy = (H - 1) / 2.0 + offset * sy * (r_ref - r_mid)
    vv, uu = np.nonzero(np.isfinite(depth))
    Z = depth[vv, uu].astype(np.float64)
    X = (uu - cx) * Z / f
    Y = (vv - cy) * Z / f
    return np.column_stack([X, Y, Z]).astype(np.float32), np.stack([vv, uu], 1)


def _finite_or_none(obj: Any) -> Any:
    """``obj`` with NaN and infinite floats replaced by None (strict JSON)."""
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _median(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else None


def _p1_p99(x: np.ndarray) -> list[float] | None:
    x = x[np.isfinite(x)]
    return [float(v) for v in np.percentile(x, [1, 99])] if x.size else None


def write_lightfield(
    out_dir: str | os.PathLike[str],
    lf: LightField,
    result: DepthResult,
    *,
    timings: dict[str, float] | None = None,
    extra: dict[str, Any] | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Write the depth of a :class:`~lfcam.LightField` to a folder, atomically.

    Files: ``disparity.tiff`` (float32, px per grid step, HCI sign, NaN unknown),
    ``disparity.pfm`` (the same, as the HCI benchmark reads it), ``disparity.png``
    (preview, near = red), ``confidence.tiff`` and ``result.json``; with rig
    parameters (``lf.metric``) also ``depth.tiff`` (float32 m), ``depth.png`` and
    ``points.ply`` (the reference camera's frame, metres), as ``lfcam process``
    writes them. Without, no depth is made up: ``result.json`` says so. With ground
    truth for the reference view, ``result.json`` has the HCI benchmark's BadPix0.07
    and MSE x 100 over the full image and without a 15 px border.

    Returns
    -------
    path : Path
        The folder.
    info : dict
        What ``result.json`` holds.
    """
    from .lightfield import BADPIX_THRESHOLD, HCI_BORDER, disparity_metrics

    out = Path(out_dir)
    disp = result.parallax.astype(np.float32)
    finite = np.isfinite(disp)
    with _atomic_folder(out) as tmp:
        write_image(tmp / "disparity.tiff", disp)
        write_pfm(tmp / "disparity.pfm", disp)
        write_image(tmp / "disparity.png", colour_depth(disp, unit="px", near_high=True))
        write_image(tmp / "confidence.tiff", result.confidence.astype(np.float32))
        stats: dict[str, Any] = {
            "coverage": float(finite.mean()),
            "disparity_median_px": _median(disp),
            "disparity_p1_p99_px": _p1_p99(disp),
        }
        info: dict[str, Any] = {
            "source": lf.source,
            "layout": lf.layout,
            "rows": lf.rows,
            "cols": lf.cols,
            "reference": list(lf.reference_rc),
            "n_views": lf.n_views,
            "image_shape": list(lf.image_shape),
            "flip": lf.flip,
            "offsets": "o_i = (-(c - c_ref), -(r - r_ref)) px per unit disparity"
            + (f", axes flipped: {lf.flip!r}" if lf.flip else ""),
            "disparity_units": "px per grid step; positive nearer than the zero-parallax plane"
            " (HCI convention: centre pixel (x, y) appears in view (r, c) at"
            " (x - d (c - c_ref), y - d (r - r_ref)))",
            "metric": lf.metric,
        }
        if lf.metric and lf.parameters is not None:
            depth = lf.disparity_to_depth(disp)
            write_image(tmp / "depth.tiff", depth)
            write_image(tmp / "depth.png", colour_depth(depth))
            pts, idx = points_from_lightfield(depth, lf)
            ref = _to_u8(lf.to_float()[lf.reference])
            colours = ref[idx[:, 0], idx[:, 1]]
            if colours.ndim == 1:
                colours = np.repeat(colours[:, None], 3, 1)
            write_ply(tmp / "points.ply", pts, colours)
            info["depth_units"] = "m"
            info["xy_units"] = "m"
            info["points_frame"] = (
                "reference camera: X right, Y down, Z along the optical axis, metres"
            )
            info["parameters"] = dataclasses.asdict(lf.parameters)
            stats["depth_median_m"] = _median(depth)
            stats["depth_p1_p99_m"] = _p1_p99(depth)
            stats["points"] = len(pts)
        else:
            info["depth_units"] = None
            info["note"] = (
                "no metric rig parameters (parameters.cfg with baseline_mm, focal_length_mm,"
                " sensor_size_mm, image_resolution_x_px and offset or focus_distance_m):"
                " disparity only, no depth or point cloud"
            )
        stats["confidence_median"] = _median(np.where(finite, result.confidence, np.nan))
        stats["flow_residual_median_px"] = _median(result.residual)
        stats["perpendicular_median_px"] = _median(result.perpendicular)
        info["statistics"] = stats
        if lf.ground_truth is not None:
            gt_info: dict[str, Any] = {"view": list(lf.ground_truth_view or lf.reference_rc)}
            if lf.ground_truth_view == lf.reference_rc:
                gt_info["badpix_threshold_px"] = BADPIX_THRESHOLD
                gt_info["full"] = disparity_metrics(disp, lf.ground_truth)
                gt_info[f"without_{HCI_BORDER}px_border"] = disparity_metrics(
                    disp, lf.ground_truth, border=HCI_BORDER
                )
                gt_info["note"] = (
                    "BadPix: % of pixels with |d - gt| > threshold, a missing estimate"
                    " counts as bad; MSE x 100 over the pixels with an estimate"
                )
            else:
                gt_info["note"] = (
                    "the ground truth belongs to another view than the reference: not scored"
                )
            info["ground_truth"] = gt_info
        info["timings_s"] = {**result.timings, **(timings or {})}
        info.update(extra or {})
        info["files"] = [*sorted(p.name for p in tmp.iterdir()), "result.json"]
        info = _finite_or_none(info)
        (tmp / "result.json").write_text(json.dumps(info, indent=2, default=str, allow_nan=False))
    return out, info
