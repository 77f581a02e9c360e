"""Dense optical flow (OpenCV DIS), tuned for lfcam's images.

Flow is computed on 8-bit grey images; :func:`prepare` turns float images
(any brightness, NaN where there is no data) into locally contrast-normalised
8-bit images so that flow between differently lit or vignetted views works.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["FlowParams", "dis_flow", "end_point_error", "normalize", "prepare"]


@dataclass(frozen=True)
class FlowParams:
    """Parameters of OpenCV's DIS optical flow (Kroeger et al. 2016).

    The defaults (fine patches, dense stride, variational refinement) favour
    sub-pixel precision over speed; see ``cv2.DISOpticalFlow`` for meanings.
    """

    finest_scale: int = 0
    patch_size: int = 8
    patch_stride: int = 3
    gradient_descent_iterations: int = 25
    variational_iterations: int = 5
    alpha: float = 20.0
    gamma: float = 10.0
    delta: float = 5.0
    mean_normalization: bool = True
    spatial_propagation: bool = True

    def create(self) -> cv2.DISOpticalFlow:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        dis.setFinestScale(self.finest_scale)
        dis.setPatchSize(self.patch_size)
        dis.setPatchStride(self.patch_stride)
        dis.setGradientDescentIterations(self.gradient_descent_iterations)
        dis.setVariationalRefinementIterations(self.variational_iterations)
        dis.setVariationalRefinementAlpha(self.alpha)
        dis.setVariationalRefinementGamma(self.gamma)
        dis.setVariationalRefinementDelta(self.delta)
        dis.setUseMeanNormalization(self.mean_normalization)
        dis.setUseSpatialPropagation(self.spatial_propagation)
        return dis


def normalize(img: np.ndarray, sigma: float = 6.0) -> np.ndarray:
    """Local contrast normalisation: ``(img - local mean) / local std``, float32.

    Grey or RGB input (RGB is averaged); NaN stays NaN.
    """
    g = img.mean(axis=2) if img.ndim == 3 else img
    g = g.astype(np.float32)
    valid = np.isfinite(g)
    g0 = np.where(valid, g, 0.0).astype(np.float32)
    w = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), sigma)
    m = cv2.GaussianBlur(g0, (0, 0), sigma)
    m2 = cv2.GaussianBlur(g0 * g0, (0, 0), sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = m / w
        var = np.maximum(m2 / w - mean * mean, 0.0)
        z = (g0 - mean) / np.sqrt(var + 1e-6)
    return np.where(valid & (w > 0.2), z, np.nan).astype(np.float32)


def prepare(img: np.ndarray, sigma: float = 6.0) -> np.ndarray:
    """Float image (grey or RGB, NaN = no data) -> contrast-normalised uint8.

    Subtracts a local mean and divides by a local standard deviation (Gaussian
    windows of ``sigma`` px), so vignetting, colour casts and exposure do not
    matter; pixels without data get the neutral value 128.
    """
    z = np.nan_to_num(normalize(img, sigma), nan=0.0)
    return np.clip(np.round(128.0 + 40.0 * z), 0, 255).astype(np.uint8)


def dis_flow(
    a: np.ndarray,
    b: np.ndarray,
    params: FlowParams | None = None,
    init: np.ndarray | None = None,
) -> np.ndarray:
    """Flow from uint8 image ``a`` to ``b``: ``a(p) ~ b(p + flow(p))``.

    Returns ``(H, W, 2)`` float32 (x, y). ``init`` is an initial flow.
    """
    dis = (params or FlowParams()).create()
    if init is not None:
        return dis.calc(a, b, np.ascontiguousarray(init, dtype=np.float32))
    return dis.calc(a, b, None)


def end_point_error(flow: np.ndarray, truth: np.ndarray) -> float:
    """Mean end-point error (px) of ``flow`` against ``truth`` (both ``(H, W, 2)``)
    over the pixels where the truth is known (finite), as Middlebury scores flow."""
    ok = np.isfinite(truth).all(-1)
    return float(np.mean(np.hypot(*np.moveaxis(flow[ok] - truth[ok], -1, 0))))
