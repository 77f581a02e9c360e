"""Zoom settings: a camera calibrated at several focal lengths of its front lens.

The calibration folder has one ``zoom_<f>mm/`` folder per setting (layout:
:mod:`lfcam.calibration.inputs`); each setting is calibrated on its own, then the warp
maps are compared. A parfocal zoom barely changes the lenslets' distortion (the
lenslets see the same intermediate-image plane at every setting), so one setting's
warp maps serve another's once its rectified frame is related to the first's by a
similarity ``p = k q + t`` (docs/design.md, "Calibration file"): each setting keeps its own
``o_i`` (scaled by ``k`` into the shared frame), ``Z_c`` and reference distance.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import lfcam._lfcam as _lfcam

from ..errors import CalibrationError, InputError
from ..io import write_image_atomic, write_text_atomic
from ..kernels.warp import remap
from .calibrate import CalibrationParams, CalibrationRun, run_calibration
from .file import Calibration, save_settings
from .inputs import find_settings
from .report import calibration_figure

__all__ = [
    "WARP_SAMPLE_STEP",
    "WARP_SHARE_MAX_PX",
    "ZoomRun",
    "run_zoom_calibration",
    "warp_difference",
]

#: Two settings share warp maps when, after the similarity between their rectified
#: frames, the maps differ by at most this (px RMS, in the first setting's frame).
WARP_SHARE_MAX_PX = 0.5
#: :func:`warp_difference` compares the maps on every WARP_SAMPLE_STEP-th rectified pixel.
WARP_SAMPLE_STEP = 8


def warp_difference(a: Calibration, b: Calibration) -> dict[str, Any]:
    """How much ``b``'s warp maps differ from ``a``'s beyond a change of frame.

    Each sampled rectified pixel ``q`` of ``b`` that view i sees lands on a raw pixel;
    ``a``'s inverse maps give the position ``p`` in ``a``'s frame that view i shows
    there. ``p = k q + t`` is fitted over all views by least squares (a zoom changes the
    magnification, not the lenslets); its residual is the difference.

    Returns
    -------
    dict
        ``rms_px``, ``p99_px`` (in ``a``'s frame), ``scale`` ``k``, ``shift`` ``t``,
        ``samples``.
    """
    if a.grid != b.grid or a.raw_shape != b.raw_shape:
        raise CalibrationError(
            f"zoom settings: grids {a.grid} and {b.grid} or raw frames {a.raw_shape} and"
            f" {b.raw_shape} differ: not one camera"
        )
    H, W = a.raw_shape
    inv, owner = _lfcam.invert_maps(
        np.ascontiguousarray(a.warps),
        np.ascontiguousarray(a.masks, np.uint8),
        np.ascontiguousarray(a.crops),
        H,
        W,
    )
    qs, ps = [], []
    hb, wb = b.rect_shape
    vv, uu = np.mgrid[0:hb:WARP_SAMPLE_STEP, 0:wb:WARP_SAMPLE_STEP]
    for i in range(b.n_views):
        seen = b.masks[i][vv, uu]
        q = np.stack([uu[seen], vv[seen]], -1).astype(np.float64)
        raw = b.warps[i][vv[seen], uu[seen]].astype(np.float64) + b.crops[i, :2]
        p = remap(inv, raw[None].astype(np.float32))[0].astype(np.float64)
        ri = np.clip(np.round(raw).astype(int), 0, [W - 1, H - 1])
        ok = np.isfinite(p).all(-1) & (owner[ri[:, 1], ri[:, 0]] == i)
        qs.append(q[ok])
        ps.append(p[ok])
    q = np.concatenate(qs)
    p = np.concatenate(ps)
    if len(q) < 10:
        raise CalibrationError("zoom settings: the views of two settings do not overlap")
    # p = k q + t: rows (qx, 1, 0) and (qy, 0, 1).
    A = np.zeros((2 * len(q), 3))
    A[0::2, 0], A[0::2, 1] = q[:, 0], 1.0
    A[1::2, 0], A[1::2, 2] = q[:, 1], 1.0
    sol, *_ = np.linalg.lstsq(A, p.reshape(-1), rcond=None)
    res = np.linalg.norm((A @ sol - p.reshape(-1)).reshape(-1, 2), axis=1)
    return {
        "rms_px": float(np.sqrt(np.mean(res**2))),
        "p99_px": float(np.percentile(res, 99)),
        "scale": float(sol[0]),
        "shift": [float(sol[1]), float(sol[2])],
        "samples": len(q),
    }


def _shared(a: Calibration, b: Calibration, k: float) -> Calibration:
    """``b`` in ``a``'s rectified frame, with ``a``'s warp maps and the crops they start
    from (``o_i`` scaled by ``k``)."""
    return dataclasses.replace(
        b,
        crops=a.crops,
        centres=a.centres,
        rect_shape=a.rect_shape,
        pattern_shape=a.pattern_shape,
        scale=a.scale,
        pattern_pitch=a.pattern_pitch,
        warps=a.warps,
        masks=a.masks,
        offsets=b.offsets * k,
    )


@dataclass
class ZoomRun:
    """Every setting's calibration (by focal length, mm) and its report pictures."""

    calibrations: list[Calibration]
    runs: dict[float, CalibrationRun]

    def save(self, path: str | os.PathLike[str]) -> dict[str, Path]:
        """Write ``X.lfcal`` (every setting), ``X.report.json`` and one
        ``X.report_<f>mm.png`` per setting; each atomically, the ``.lfcal`` last."""
        out = Path(path)
        if out.suffix != ".lfcal":
            out = out.with_name(out.name + ".lfcal")
        if not out.parent.is_dir():
            raise InputError(f"{out}: folder {out.parent} does not exist")
        stem = out.with_suffix("")
        paths: dict[str, Path] = {"report_json": stem.with_name(stem.name + ".report.json")}
        reports = {f"{c.focal_length:g}": c.report for c in self.calibrations}
        write_text_atomic(paths["report_json"], json.dumps({"settings": reports}, indent=2))
        for cal in self.calibrations:
            run = self.runs[cal.focal_length]
            png = stem.with_name(f"{stem.name}.report_{cal.focal_length:g}mm.png")
            fig = calibration_figure(run.calibration, run.white, run.residuals)
            write_image_atomic(png, fig)
            paths[f"report_png_{cal.focal_length:g}mm"] = png
        save_settings(out, self.calibrations)
        paths["calibration"] = out
        return paths


def run_zoom_calibration(
    cal_dir: str | os.PathLike[str],
    params: CalibrationParams | None = None,
    *,
    share_warps: bool | None = None,
    threads: int = 2,
    progress: Callable[[str], None] | None = None,
    **changes: Any,
) -> ZoomRun:
    """Calibrate every zoom setting of a folder (``zoom_<f>mm/``).

    Parameters
    ----------
    cal_dir : path
        The calibration folder.
    params, **changes
        As :func:`lfcam.calibrate`, for every setting.
    share_warps : bool, optional
        True: every setting uses the first (shortest focal length) setting's warp
        maps; False: each its own; None (default): shared where the measured
        difference (:func:`warp_difference`) is at most WARP_SHARE_MAX_PX and the
        reference distance is the same. The report's ``zoom`` entry has the
        difference either way.

    Returns
    -------
    ZoomRun
        The calibrations by increasing focal length; ``focal_length`` set on each.

    Raises
    ------
    lfcam.InputError
        A folder without ``zoom_<f>mm/`` settings, or as :func:`lfcam.calibrate`.
    lfcam.CalibrationError
        As :func:`lfcam.calibrate`, naming the setting's folder.
    """
    say = progress or (lambda _msg: None)
    settings = find_settings(cal_dir)
    if None in settings:
        raise InputError(f"{cal_dir}: no zoom settings (zoom_<f>mm/ folders)")
    runs: dict[float, CalibrationRun] = {}
    for f, inputs in settings.items():
        assert f is not None
        say(f"zoom {f:g} mm")
        run = run_calibration(
            inputs.root, params, threads=threads, progress=say, inputs=inputs, **changes
        )
        run.calibration = dataclasses.replace(run.calibration, focal_length=f)
        runs[f] = run
    focal = sorted(runs)
    first = runs[focal[0]].calibration
    cals = [first]
    for f in focal[1:]:
        cal = runs[f].calibration
        diff = warp_difference(first, cal)
        same_zb = cal.z_b == first.z_b
        share = (
            share_warps
            if share_warps is not None
            else same_zb and diff["rms_px"] <= WARP_SHARE_MAX_PX
        )
        if share and not same_zb:
            raise InputError(
                f"share_warps: setting {f:g} mm has reference distance {cal.z_b:g} m,"
                f" {focal[0]:g} mm has {first.z_b:g} m: the warp maps cannot be shared"
            )
        report = dict(cal.report)
        report["zoom"] = {
            "focal_length_mm": f,
            "warps_from_mm": focal[0] if share else f,
            "warp_difference_to_first": diff,
            "warp_share_max_px": WARP_SHARE_MAX_PX,
        }
        cal = dataclasses.replace(cal, report=report)
        cals.append(_shared(first, cal, diff["scale"]) if share else cal)
    first.report = {
        **first.report,
        "zoom": {"focal_length_mm": focal[0], "warps_from_mm": focal[0]},
    }
    return ZoomRun(cals, runs)
