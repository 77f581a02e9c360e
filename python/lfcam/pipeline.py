"""Per-capture processing: raw frame -> rectified views -> depth -> asked-for products
(docs/design.md, "Processing pipeline").

Pure steps composed; no file writing and no printing here (see :mod:`lfcam.outputs`
and :mod:`lfcam.cli`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .calibration import Calibration, SettingChoice, ZoomCalibration
from .io import (
    MAX_IMAGE_FILE_BYTES,
    CaptureMetadata,
    is_image_file,
    read_file_bytes,
    read_metadata,
    read_raw,
)
from .processing import DepthParams, DepthResult, estimate_depth, rectify
from .products import refocus as refocus_at
from .products import super_resolve

__all__ = ["CaptureResult", "process_capture"]


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
    #: What the capture's file says about how it was taken (EXIF; empty for arrays).
    metadata: CaptureMetadata = field(default_factory=CaptureMetadata)
    #: The calibration setting used and why (``setting.calibration`` is the camera the
    #: views, depth and products are in).
    setting: SettingChoice | None = None


def process_capture(
    raw_or_path: np.ndarray | str | os.PathLike[str],
    cal: Calibration | ZoomCalibration,
    *,
    focal_length: float | None = None,
    interp: str = "bilinear",
    threads: int = 2,
    superres: int | None = None,
    refocus: Sequence[float] = (),
    depth: DepthParams | None = None,
) -> CaptureResult:
    """Everything one capture needs: read, rectify, flow, triangulate.

    Parameters
    ----------
    raw_or_path : array or path
        The raw frame, or its file (PNG, TIFF, JPEG, camera raw).
    cal : Calibration or ZoomCalibration
        The camera; a :class:`ZoomCalibration` of several zoom settings gives the
        setting whose focal length matches the capture's (``focal_length``, else the
        file's EXIF focal length) within 2%.
    focal_length : float, optional
        The front lens's focal length, mm: picks the zoom setting, overriding the
        capture's metadata (``lfcam process --zoom``).
    interp : str
        Rectification resampling.
    threads : int
        Concurrent optical flows.
    superres : int, optional
        Also super-resolve the reference view by this factor (1 to 4), from the raw
        samples (:func:`lfcam.super_resolve`).
    refocus : sequence of float
        Also refocus at these distances, metres (:func:`lfcam.refocus`).
    depth : DepthParams, optional
        The depth chain's settings (:func:`lfcam.estimate_depth`).

    Returns
    -------
    CaptureResult
        ``views`` (rectified), ``depth`` (a :class:`DepthResult`), ``timings``,
        ``metadata`` (the file's focal length, exposure, ISO, aperture, camera),
        ``setting`` (the calibration setting used).

    Raises
    ------
    InputError
        Besides a bad capture: a focal length (given, or the capture's) that matches
        none of ``cal``'s zoom settings, or several settings and no focal length known,
        naming the focal length and the settings.
    """
    zoom = ZoomCalibration.of(cal)
    if focal_length is not None:
        zoom.select(focal_length, "focal_length")  # a bad one is refused before reading
    t0 = time.perf_counter()
    source = None
    metadata = CaptureMetadata()
    # Every setting shares the raw frame's layout and Bayer pattern.
    bayer = zoom.settings[0].bayer
    if isinstance(raw_or_path, (str, os.PathLike)):
        source = str(raw_or_path)
        # Pixels and metadata from one read of the file (read_raw words any error).
        data = None
        if is_image_file(Path(raw_or_path)):
            data = read_file_bytes(raw_or_path, MAX_IMAGE_FILE_BYTES)
        raw = read_raw(Path(raw_or_path), bayer, data=data)
        metadata = read_metadata(Path(raw_or_path), data=data)
    else:
        raw = np.asarray(raw_or_path)
    setting = zoom.choose(
        focal_length,
        capture_focal_length=metadata.focal_length_mm,
        capture=source or "raw_or_path",
    )
    cal = setting.calibration
    t1 = time.perf_counter()
    views = rectify(raw, cal, interp=interp)
    t2 = time.perf_counter()
    res = estimate_depth(views, cal, depth, threads=threads)
    t3 = time.perf_counter()
    timings = {"read": t1 - t0, "rectify": t2 - t1, **res.timings}
    out = CaptureResult(views, res, source, timings, metadata=metadata, setting=setting)
    if superres is not None or refocus:
        if superres is not None:
            out.superres = super_resolve(raw, cal, res, superres)
        t4 = time.perf_counter()
        out.refocused = {float(z): refocus_at(raw, cal, float(z)) for z in refocus}
        timings.update(superres=t4 - t3, refocus=time.perf_counter() - t4)
    timings["total"] = time.perf_counter() - t0
    return out
