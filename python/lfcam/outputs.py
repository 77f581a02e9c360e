"""Writing one capture's products: depth (TIFF + preview), confidence, point cloud, JSON,
and the mesh and novel views asked for.

Every capture's folder is assembled under a temporary name and renamed when
complete (:func:`lfcam.io.atomic_folder`), so an interrupted run never leaves a
half-written result; a folder with ``result.json`` is complete.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .calibration import Calibration
from .errors import InputError
from .io import (
    atomic_folder,
    colour_depth,
    encode_u8,
    encode_u16,
    rgb_u8,
    write_image,
    write_pfm,
    write_ply,
)
from .pipeline import CaptureResult
from .processing import DepthResult
from .products.geometry import orbit_poses, points_from_depth
from .products.mesh import DEFAULT_MAX_RATIO, mesh_from_depth, write_mesh_ply
from .products.render import render_mesh
from .sim import BADPIX_THRESHOLD, HCI_BORDER, LightField, disparity_metrics
from .sim.lightfield import points_from_lightfield

__all__ = ["NovelViewOptions", "write_capture", "write_lightfield", "write_novel_views"]


@dataclass
class NovelViewOptions:
    """What ``lfcam process`` renders besides depth (see :func:`write_novel_views`).

    Attributes
    ----------
    mesh : bool
        Write ``mesh.ply``.
    pose : (4, 4) array or None
        Write ``novel_view.png`` (and ``novel_view_depth.tiff``) from this pose.
    orbit : int
        Write this many orbit frames (``orbit/frame_NNN.png``) and ``orbit.mp4``; 0: none.
    """

    mesh: bool = False
    pose: np.ndarray | None = None
    orbit: int = 0

    @property
    def any(self) -> bool:
        """Whether anything is asked for."""
        return self.mesh or self.pose is not None or self.orbit > 0


def write_novel_views(
    folder: Any, result: CaptureResult, cal: Calibration, options: NovelViewOptions
) -> dict[str, Any]:
    """Write the mesh and novel views of one processed capture into ``folder``.

    Called by :func:`write_capture` inside its atomic folder. PNGs are
    gamma-encoded like the other previews; holes (nothing seen) are black.

    Returns
    -------
    dict
        What was written, for ``result.json``.
    """
    out = Path(folder)
    depth = result.depth.depth
    if depth is None:
        raise InputError("result: meshes and novel views need metric depth")
    t0 = time.perf_counter()
    mesh = mesh_from_depth(depth, cal, result.views[cal.reference])
    info: dict[str, Any] = {
        "mesh_max_ratio": DEFAULT_MAX_RATIO,
        "mesh_vertices": len(mesh.vertices),
        "mesh_faces": len(mesh.faces),
    }
    if options.mesh:
        write_mesh_ply(out / "mesh.ply", mesh)
    if options.pose is not None:
        r = render_mesh(mesh, cal, options.pose)
        write_image(out / "novel_view.png", encode_u8(r.image))
        write_image(out / "novel_view_depth.tiff", r.depth)
        info["novel_view_pose"] = options.pose.tolist()
        info["novel_view_coverage"] = float(r.mask.mean())
    if options.orbit > 0:
        (out / "orbit").mkdir()
        H, W = cal.rect_shape
        video = cv2.VideoWriter(str(out / "orbit.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), 12, (W, H))
        try:
            for k, pose in enumerate(orbit_poses(cal, options.orbit)):
                rgb = encode_u8(render_mesh(mesh, cal, pose).image)
                if rgb.ndim == 2:
                    rgb = np.repeat(rgb[..., None], 3, 2)
                write_image(out / "orbit" / f"frame_{k:03d}.png", rgb)
                video.write(np.ascontiguousarray(rgb[..., ::-1]))
        finally:
            video.release()
        info["orbit_frames"] = options.orbit
    info["novel_views_s"] = time.perf_counter() - t0
    return info


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
    (:func:`write_novel_views`).
    """
    out = Path(out_dir)
    with atomic_folder(out) as tmp:
        d = result.depth
        ref_view = result.views[cal.reference]
        depth = d.depth if d.depth is not None else d.relative
        assert depth is not None
        write_image(tmp / "depth.tiff", depth.astype(np.float32))
        write_image(tmp / "depth.png", colour_depth(depth))
        write_image(tmp / "confidence.tiff", d.confidence.astype(np.float32))
        pts, idx, units = points_from_depth(depth, cal)
        write_ply(tmp / "points.ply", pts, rgb_u8(ref_view[idx[:, 0], idx[:, 1]]))
        if result.superres is not None:
            write_image(tmp / "superres.png", encode_u16(result.superres))
        for z, img in result.refocused.items():
            write_image(tmp / f"refocus_{z:g}m.png", encode_u16(img))
        if save_views:
            (tmp / "views").mkdir()
            C = cal.grid[1]
            for i, v in enumerate(result.views):
                r, c = divmod(i, C)
                write_image(tmp / "views" / f"view_{r}_{c}.png", encode_u8(v))
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
            novel_info = {"novel_views": write_novel_views(tmp, result, cal, novel)}
        info = {
            "source": result.source,
            "capture": result.metadata.to_dict(),
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
    out = Path(out_dir)
    disp = result.parallax.astype(np.float32)
    finite = np.isfinite(disp)
    with atomic_folder(out) as tmp:
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
            ref = lf.to_float()[lf.reference]
            write_ply(tmp / "points.ply", pts, rgb_u8(ref[idx[:, 0], idx[:, 1]]))
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
