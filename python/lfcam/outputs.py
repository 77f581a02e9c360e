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

__all__ = [
    "FRAMES",
    "MIN_COVERAGE",
    "NovelViewOptions",
    "degenerate_message",
    "output_frame",
    "reference_box",
    "write_capture",
    "write_lightfield",
    "write_novel_views",
]

#: A result whose depth covers less than this fraction of the pixels the reference view
#: sees is degenerate (an all-NaN, black or featureless capture, views too small):
#: ``result.json`` says ``"degenerate": true`` and the command line warns.
MIN_COVERAGE = 0.05


def degenerate_message(info: dict[str, Any]) -> str | None:
    """The console warning for a ``result.json`` marked degenerate, else None."""
    if not info.get("degenerate"):
        return None
    cov = info["statistics"]["coverage"]
    return (
        f"depth covers {100 * cov:.1f} % of the reference view, below "
        f"{100 * MIN_COVERAGE:g} %: a degenerate capture (blank, all NaN or too small?)"
    )


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
    folder: Any,
    result: CaptureResult,
    cal: Calibration,
    options: NovelViewOptions,
    frame: str = "valid",
) -> dict[str, Any]:
    """Write the mesh and novel views of one processed capture into ``folder``.

    Called by :func:`write_capture` inside its atomic folder. The novel cameras have
    the reference view's rectified-frame intrinsics; their images are cut to ``frame``
    (:func:`output_frame`) like the other products, so a novel view's pixel
    ``(x, y)`` is pixel ``(x + x0, y + y0)`` of the whole frame's render. PNGs are
    sRGB-encoded like the other previews; holes (nothing seen) are black. The mesh
    (metres) does not depend on the frame.

    Returns
    -------
    dict
        What was written, for ``result.json``.
    """
    out = Path(folder)
    depth = result.depth.depth
    if depth is None:
        raise InputError("result: meshes and novel views need metric depth")
    fr = output_frame(cal, frame)
    t0 = time.perf_counter()
    mesh = mesh_from_depth(depth, cal, result.views[cal.reference])
    info: dict[str, Any] = {
        "mesh_max_ratio": DEFAULT_MAX_RATIO,
        "mesh_vertices": len(mesh.vertices),
        "mesh_faces": len(mesh.faces),
    }

    def render(pose: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # The whole frame's render, cut: the same pixels as --frame full, exactly.
        r = render_mesh(mesh, cal, pose)
        return _crop(r.image, fr), _crop(r.depth, fr), _crop(r.mask, fr)

    if options.mesh:
        write_mesh_ply(out / "mesh.ply", mesh)
    if options.pose is not None:
        image, z, mask = render(options.pose)
        write_image(out / "novel_view.png", encode_u8(image), srgb=True)
        write_image(
            out / "novel_view_depth.tiff",
            z,
            description={
                "quantity": "depth Z along the novel camera's axis",
                "unit": "m",
                "nan": "NaN: nothing seen",
                "frame": {
                    **{k: fr[k] for k in ("name", "offset_xy", "rectified_shape")},
                    "camera": "the novel camera (pose in result.json) with the reference"
                    " view's rectified-frame intrinsics",
                },
                "software": f"lfcam {_version()}",
            },
        )
        info["novel_view_pose"] = options.pose.tolist()
        info["novel_view_coverage"] = float(mask.mean())
    if options.orbit > 0:
        (out / "orbit").mkdir()
        h, w = fr["shape"]
        # MPEG-4 frames have even sizes (an odd one loses its last row or column):
        # the video's frames are padded with black at the bottom and right.
        hv, wv = h + h % 2, w + w % 2
        video = cv2.VideoWriter(
            str(out / "orbit.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), 12, (wv, hv)
        )
        try:
            for k, pose in enumerate(orbit_poses(cal, options.orbit)):
                rgb = encode_u8(render(pose)[0])
                if rgb.ndim == 2:
                    rgb = np.repeat(rgb[..., None], 3, 2)
                write_image(out / "orbit" / f"frame_{k:03d}.png", rgb, srgb=True)
                padded = np.zeros((hv, wv, 3), np.uint8)
                padded[:h, :w] = rgb[..., ::-1]
                video.write(padded)
        finally:
            video.release()
        info["orbit_frames"] = options.orbit
    info["frame"] = {k: fr[k] for k in ("name", "offset_xy", "shape")}
    info["novel_views_s"] = time.perf_counter() - t0
    return info


#: ``lfcam process --frame`` choices: crop to the reference view's data, or not.
FRAMES = ("valid", "full")


def reference_box(cal: Calibration) -> tuple[int, int, int, int]:
    """``(x0, y0, w, h)``: the bounding box of the reference view's valid pixels
    (``cal.masks[cal.reference]``) in the rectified frame; the whole frame if none."""
    mask = np.asarray(cal.masks[cal.reference], bool)
    rows = np.flatnonzero(mask.any(1))
    cols = np.flatnonzero(mask.any(0))
    if rows.size == 0:
        H, W = (int(v) for v in cal.rect_shape)
        return 0, 0, W, H
    y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    return x0, y0, x1 - x0, y1 - y0


def output_frame(cal: Calibration, frame: str = "valid") -> dict[str, Any]:
    """The pixel frame of a capture's image outputs, as ``result.json`` records it.

    Parameters
    ----------
    cal : Calibration
        The camera.
    frame : {'valid', 'full'}
        ``valid``: the bounding box of the reference view's valid pixels
        (:func:`reference_box`); ``full``: the calibration's whole rectified frame.

    Returns
    -------
    dict
        ``name``, ``offset_xy`` (pixel ``(x, y)`` of an output is ``(x + x0, y + y0)``
        in the calibration's rectified frame; ``(F (x + x0) + ..., ...)`` scaled for a
        super-resolved image, see ``superres``), ``shape`` ``[H, W]`` and
        ``rectified_shape``.
    """
    if frame not in FRAMES:
        raise InputError(f"frame: expected one of {', '.join(FRAMES)}, got {frame!r}")
    H, W = (int(v) for v in cal.rect_shape)
    x0, y0, w, h = reference_box(cal) if frame == "valid" else (0, 0, W, H)
    return {
        "name": frame,
        "offset_xy": [x0, y0],
        "shape": [h, w],
        "rectified_shape": [H, W],
        "description": (
            "the reference view's rectified frame"
            + (
                ", cropped to the bounding box of the pixels the reference view sees:"
                f" output pixel (x, y) is rectified pixel (x + {x0}, y + {y0})"
                if frame == "valid"
                else ", whole"
            )
        ),
    }


def _crop(img: np.ndarray, frame: dict[str, Any], factor: int = 1) -> np.ndarray:
    """``img`` (the rectified frame, or ``factor`` times it) cut to ``frame``."""
    x0, y0 = frame["offset_xy"]
    h, w = frame["shape"]
    return np.ascontiguousarray(
        img[factor * y0 : factor * (y0 + h), factor * x0 : factor * (x0 + w)]
    )


def write_capture(
    out_dir: str | os.PathLike[str],
    result: CaptureResult,
    cal: Calibration,
    *,
    extra: dict[str, Any] | None = None,
    save_views: bool = False,
    novel: NovelViewOptions | None = None,
    frame: str = "valid",
) -> Path:
    """Write one capture's folder atomically; returns its path.

    Files: ``depth.tiff`` (float32 m, NaN unknown), ``depth.png`` (preview with
    a colour bar), ``confidence.tiff``, ``points.ply`` (coloured), ``result.json``
    and, with ``save_views``, ``views/view_R_C.png``; ``superres.tiff`` (float32,
    linear, the rectified views' scale) and ``superres.png``, ``refocus_<Z>m.tiff``
    and ``.png`` when the result has them; with ``novel``, the mesh and novel views
    it asks for (:func:`write_novel_views`).

    Images, the novel views among them, are cut to ``frame`` (:func:`output_frame`;
    ``result.json`` records the crop offset, and ``calibration_setting`` the zoom
    setting ``result`` used, which ``cal`` must be); points keep their positions. PNGs
    are sRGB-encoded and say so; each TIFF's ImageDescription is JSON: quantity, unit,
    frame and the calibration's SHA-256 (``extra["calibration_sha256"]``, when given).
    """
    out = Path(out_dir)
    fr = output_frame(cal, frame)
    sha = (extra or {}).get("calibration_sha256")
    meta_frame = {k: fr[k] for k in ("name", "offset_xy", "rectified_shape")}

    def meta(quantity: str, unit: str | None, **more: Any) -> dict[str, Any]:
        return {
            "quantity": quantity,
            "unit": unit,
            "frame": {**meta_frame, **more.pop("frame", {})},
            "calibration_sha256": sha,
            "software": f"lfcam {_version()}",
            **more,
        }

    with atomic_folder(out) as tmp:
        d = result.depth
        ref_view = result.views[cal.reference]
        depth = d.depth if d.depth is not None else d.relative
        assert depth is not None
        z_unit = "m" if d.depth is not None else "relative (t = s Z_c / Z_b)"
        nan = "NaN: unknown"
        write_image(
            tmp / "depth.tiff",
            _crop(depth.astype(np.float32), fr),
            description=meta("depth Z along the lens axis", z_unit, nan=nan),
        )
        write_image(tmp / "depth.png", colour_depth(_crop(depth, fr)), srgb=True)
        write_image(
            tmp / "confidence.tiff",
            _crop(d.confidence.astype(np.float32), fr),
            description=meta("depth confidence, 0 (none) to 1", None, nan=nan),
        )
        pts, idx, units = points_from_depth(depth, cal)
        write_ply(
            tmp / "points.ply",
            pts,
            rgb_u8(ref_view[idx[:, 0], idx[:, 1]]),
            comments=[
                f"units X, Y {units}; Z {z_unit}",
                "frame front lens: X right, Y down, Z forward (docs/design.md, 'Frames')",
                "colour sRGB-encoded reference view",
            ],
        )
        linear = "linear, the rectified views' scale (white = 1)"
        if result.superres is not None:
            r = result.superres.shape[0] // int(cal.rect_shape[0])
            sr = _crop(result.superres, fr, r).astype(np.float32)
            sr_frame = {
                "scale": r,
                "note": f"fine pixel (X, Y) is rectified pixel ((X + 0.5) / {r} - 0.5"
                f" + x0, (Y + 0.5) / {r} - 0.5 + y0), (x0, y0) = offset_xy",
            }
            write_image(
                tmp / "superres.tiff",
                sr,
                description=meta("super-resolved reference view", linear, frame=sr_frame),
            )
            write_image(tmp / "superres.png", encode_u16(sr), srgb=True)
        for z, img in result.refocused.items():
            rf = _crop(img, fr).astype(np.float32)
            write_image(
                tmp / f"refocus_{z:g}m.tiff",
                rf,
                description=meta(f"refocused at {z:g} m", linear),
            )
            write_image(tmp / f"refocus_{z:g}m.png", encode_u16(rf), srgb=True)
        if save_views:
            (tmp / "views").mkdir()
            C = cal.grid[1]
            for i, v in enumerate(result.views):
                r, c = divmod(i, C)
                write_image(tmp / "views" / f"view_{r}_{c}.png", encode_u8(_crop(v, fr)), srgb=True)
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
            novel_info = {"novel_views": write_novel_views(tmp, result, cal, novel, frame)}
        info = {
            "source": result.source,
            "capture": result.metadata.to_dict(),
            **(
                {"calibration_setting": result.setting.to_dict()}
                if result.setting is not None
                else {}
            ),
            "depth_units": z_unit,
            "xy_units": units,
            "points_frame": "front lens: X right, Y down, Z forward",
            "frame": fr,
            "rect_shape": list(cal.rect_shape),
            "reference": list(cal.reference_rc),
            "timings_s": result.timings,
            "statistics": stats,
            "degenerate": stats["coverage"] < MIN_COVERAGE,
            **novel_info,
            **(extra or {}),
        }
        (tmp / "result.json").write_text(json.dumps(info, indent=2, default=str))
    return out


def _version() -> str:
    from . import __version__

    return str(__version__)


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
    frame = "the reference view's image, whole"

    def meta(quantity: str, unit: str | None) -> dict[str, Any]:
        return {
            "quantity": quantity,
            "unit": unit,
            "nan": "NaN: unknown",
            "frame": frame,
            "reference": list(lf.reference_rc),
            "software": f"lfcam {_version()}",
        }

    with atomic_folder(out) as tmp:
        write_image(
            tmp / "disparity.tiff",
            disp,
            description=meta(
                "disparity, HCI sign (positive nearer than the zero-parallax plane)",
                "px per grid step",
            ),
        )
        write_pfm(tmp / "disparity.pfm", disp)
        write_image(tmp / "disparity.png", colour_depth(disp, unit="px", near_high=True), srgb=True)
        write_image(
            tmp / "confidence.tiff",
            result.confidence.astype(np.float32),
            description=meta("disparity confidence, 0 (none) to 1", None),
        )
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
            "frame": frame,
        }
        if lf.metric and lf.parameters is not None:
            depth = lf.disparity_to_depth(disp)
            write_image(
                tmp / "depth.tiff",
                depth,
                description=meta("depth Z along the reference camera's axis", "m"),
            )
            write_image(tmp / "depth.png", colour_depth(depth), srgb=True)
            pts, idx = points_from_lightfield(depth, lf)
            ref = lf.to_float()[lf.reference]
            write_ply(
                tmp / "points.ply",
                pts,
                rgb_u8(ref[idx[:, 0], idx[:, 1]]),
                comments=[
                    "units X, Y, Z m",
                    "frame reference camera: X right, Y down, Z along the optical axis",
                    "colour sRGB-encoded reference view",
                ],
            )
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
        info["degenerate"] = stats["coverage"] < MIN_COVERAGE
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
