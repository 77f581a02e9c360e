"""Per-capture processing: raw frame -> rectified views -> depth (DESIGN.md section 5).

Pure steps composed; no file writing and no printing here (see :mod:`lfcam.outputs`
and :mod:`lfcam.cli`).
"""

from __future__ import annotations

import os
import threading
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .calibration import Calibration
from .depth import DepthResult, estimate_depth
from .errors import InputError
from .io import demosaic, read_raw
from .warp import RectifyPlan

__all__ = ["CaptureResult", "process_capture", "rectify", "rectify_plan"]


def rectify(raw: np.ndarray, cal: Calibration, *, interp: str = "bilinear") -> np.ndarray:
    """Rectify a raw frame into the calibrated views, in one fused pass per view.

    Photometric gain x crop x warp-map resampling, in the Rust core.

    Parameters
    ----------
    raw : (H_raw, W_raw) or (H_raw, W_raw, 3) array
        uint8, uint16 or float32, as read by :func:`lfcam.read_raw`. A
        single-channel frame of a Bayer camera (``cal.bayer``) is demosaiced.
    cal : Calibration
        The camera.
    interp : {'bilinear', 'bilinear-exact', 'bicubic'}
        Resampling (``bilinear`` matches ``cv2.remap``).

    Returns
    -------
    numpy.ndarray
        ``(N, H_rect, W_rect, C)`` float32 in [0, 1] (white target = 1); NaN
        where a view does not see.

    Examples
    --------
    >>> views = lfcam.rectify(lfcam.read_raw("capture.png"), cal)  # doctest: +SKIP

    Notes
    -----
    Bilinear rectification runs through the calibration's :class:`lfcam.warp.RectifyPlan`,
    prepared on the first call and cached with the calibration (about as long as a few
    captures' rectification; then each capture's is faster). Replacing ``cal.gains``,
    ``cal.crops``, ``cal.warps`` or ``cal.masks`` prepares a new plan; changing their
    values in place does not: assign new arrays instead.
    """
    from .warp import rectify as _rectify

    raw = np.asarray(raw)
    if raw.ndim == 2 and cal.bayer is not None:
        raw = demosaic(raw, cal.bayer)
    if tuple(raw.shape[:2]) != tuple(cal.raw_shape):
        raise InputError(
            f"raw: frame is {raw.shape[1]}x{raw.shape[0]}, the calibration expects"
            f" {cal.raw_shape[1]}x{cal.raw_shape[0]}"
        )
    if interp in ("bilinear", "bilinear-exact"):
        return rectify_plan(cal).rectify(raw)
    return _rectify(raw, cal.gains, cal.crops, cal.warps, cal.masks, interp=interp)


# Each calibration's prepared rectification, with the arrays it was prepared from.
_PLANS: weakref.WeakKeyDictionary[Calibration, tuple[tuple[np.ndarray, ...], RectifyPlan]]
_PLANS = weakref.WeakKeyDictionary()
_PLANS_LOCK = threading.Lock()


def rectify_plan(cal: Calibration) -> RectifyPlan:
    """The calibration's :class:`lfcam.warp.RectifyPlan` (bilinear), prepared on first use
    and cached while ``cal`` lives; prepared again if ``cal``'s gains, crops, warps or
    masks have been replaced by other arrays since."""
    arrays = (cal.gains, cal.crops, cal.warps, cal.masks)
    with _PLANS_LOCK:
        cached = _PLANS.get(cal)
    if cached is not None and all(a is b for a, b in zip(cached[0], arrays)):
        return cached[1]
    plan = RectifyPlan(*arrays)
    with _PLANS_LOCK:
        _PLANS[cal] = (arrays, plan)
    return plan


@dataclass
class CaptureResult:
    """Everything one capture produced (see :func:`process_capture`)."""

    views: np.ndarray
    depth: DepthResult
    source: str | None = None
    timings: dict[str, float] = field(default_factory=dict)
    #: Super-resolved reference view ``(r H, r W, C)`` (``superres=r``), else None.
    superres: np.ndarray | None = None
    #: Refocused images by focus distance in metres (``refocus=(...)``).
    refocused: dict[float, np.ndarray] = field(default_factory=dict)


def process_capture(
    raw_or_path: np.ndarray | str | os.PathLike[str],
    cal: Calibration,
    *,
    interp: str = "bilinear",
    threads: int = 2,
    superres: int | None = None,
    refocus: Sequence[float] = (),
    **depth_options: Any,
) -> CaptureResult:
    """Everything one capture needs: read, rectify, flow, triangulate.

    Parameters
    ----------
    raw_or_path : array or path
        The raw frame, or its file (PNG, TIFF, JPEG).
    cal : Calibration
        The camera.
    interp : str
        Rectification resampling.
    threads : int
        Concurrent optical flows.
    superres : int, optional
        Also super-resolve the reference view by this factor (1 to 4), from the raw
        samples (:func:`lfcam.super_resolve`).
    refocus : sequence of float
        Also refocus at these distances, metres (:func:`lfcam.refocus`).
    **depth_options
        Passed to :func:`lfcam.estimate_depth`.

    Returns
    -------
    CaptureResult
        ``views`` (rectified), ``depth`` (a :class:`DepthResult`), ``timings``.
    """
    t0 = time.perf_counter()
    source = None
    if isinstance(raw_or_path, (str, os.PathLike)):
        source = str(raw_or_path)
        raw = read_raw(Path(raw_or_path), cal.bayer)
    else:
        raw = np.asarray(raw_or_path)
    t1 = time.perf_counter()
    views = rectify(raw, cal, interp=interp)
    t2 = time.perf_counter()
    res = estimate_depth(views, cal, threads=threads, **depth_options)
    t3 = time.perf_counter()
    timings = {"read": t1 - t0, "rectify": t2 - t1, **res.timings}
    out = CaptureResult(views, res, source, timings)
    if superres is not None or refocus:
        from .superres import refocus as _refocus
        from .superres import super_resolve

        if superres is not None:
            out.superres = super_resolve(raw, cal, res, superres)
        t4 = time.perf_counter()
        out.refocused = {float(z): _refocus(raw, cal, float(z)) for z in refocus}
        timings.update(superres=t4 - t3, refocus=time.perf_counter() - t4)
    timings["total"] = time.perf_counter() - t0
    return out
