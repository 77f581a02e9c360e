"""Rectification: a raw frame -> the calibrated views, in one fused pass per view.

Photometric gain x crop x warp-map resampling, in the Rust core
(:mod:`lfcam.kernels.warp`); each calibration's prepared plan is cached with it.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from .._validate import as_image, check_instance
from ..calibration import Calibration
from ..errors import InputError
from ..io import demosaic
from ..kernels.warp import RectifyPlan
from ..kernels.warp import rectify as _rectify

__all__ = ["rectify", "rectify_plan"]


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
    Bilinear rectification runs through the calibration's :class:`lfcam.kernels.warp.RectifyPlan`,
    prepared on the first call and cached with the calibration (about as long as a few
    captures' rectification; then each capture's is faster). Replacing ``cal.gains``,
    ``cal.crops``, ``cal.warps`` or ``cal.masks`` prepares a new plan; changing their
    values in place does not: assign new arrays instead.
    """
    check_instance(cal, Calibration, "cal")
    raw = as_image(raw, "raw", dtypes=(np.uint8, np.uint16, np.float32))
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
    """The calibration's :class:`lfcam.kernels.warp.RectifyPlan` (bilinear), prepared on first use
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
