"""Accuracy measures: the HCI benchmark's disparity scores, and depth against the
simulator's ground truth."""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

__all__ = ["BADPIX_THRESHOLD", "HCI_BORDER", "depth_accuracy", "disparity_metrics"]

#: Border (px) the HCI benchmark leaves out when scoring (``boundary_offset``).
HCI_BORDER = 15
#: BadPix threshold (px) of the HCI benchmark's headline metric.
BADPIX_THRESHOLD = 0.07


def disparity_metrics(
    disparity: np.ndarray,
    ground_truth: np.ndarray,
    *,
    border: int = 0,
    threshold: float = BADPIX_THRESHOLD,
) -> dict[str, float]:
    """The HCI benchmark's scores of a disparity map.

    Parameters
    ----------
    disparity, ground_truth : (H, W) arrays
        Estimate and truth, px per grid step.
    border : int
        Pixels left out on every side (the benchmark uses 15).
    threshold : float
        BadPix threshold, px.

    Returns
    -------
    dict
        ``badpix_percent`` (percent of pixels with ``|d - gt| > threshold``; a missing (NaN)
        estimate counts as bad), ``mse_x100`` (100 x the mean squared error over the
        pixels with an estimate), ``coverage`` (share of pixels with an estimate) and
        ``pixels`` scored.
    """
    d = np.asarray(disparity, np.float64)
    g = np.asarray(ground_truth, np.float64)
    if d.shape != g.shape or d.ndim != 2:
        raise InputError(f"disparity: shape {d.shape} does not match the ground truth's {g.shape}")
    b = int(border)
    if b < 0 or 2 * b >= min(d.shape):
        raise InputError(f"border: {border} leaves nothing of a {d.shape[1]}x{d.shape[0]} image")
    if b:
        d, g = d[b:-b, b:-b], g[b:-b, b:-b]
    ok = np.isfinite(g)
    err = d[ok] - g[ok]
    have = np.isfinite(err)
    bad = ~have | (np.abs(np.where(have, err, 0.0)) > threshold)
    return {
        "badpix_percent": float(100.0 * bad.mean()) if bad.size else math.nan,
        "mse_x100": float(100.0 * np.mean(err[have] ** 2)) if have.any() else math.nan,
        "coverage": float(have.mean()) if have.size else 0.0,
        "pixels": int(ok.sum()),
    }


def depth_accuracy(
    depth: np.ndarray, truth: np.ndarray, seen: np.ndarray
) -> tuple[float, float, float]:
    """Depth against the simulator's truth, as ``lfcam demo`` reports it.

    Over the pixels the reference view ``seen`` (all of them, occlusion bands
    included): the median of ``|Z - Z_true| / Z_true``, the share of pixels off by
    more than 5%, and the coverage (share with a finite error).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.abs(depth - truth) / truth
    ok = seen & np.isfinite(rel)
    return float(np.median(rel[ok])), float((rel[ok] > 0.05).mean()), float(ok.sum() / seen.sum())
