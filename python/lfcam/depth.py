"""Depth by optical flow and triangulation (DESIGN.md sections 3 and 5).

Rectified views -> OpenCV DIS flow from the reference view to every other view
(and back, for a forward-backward consistency check) -> robust triangulation
of the parallax ``s`` in the Rust core -> metric depth
``Z = Z_c + (Z_b - Z_c) / (1 - s)``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .calibration import Calibration
from .errors import InputError
from .flow import FlowParams, dis_flow, prepare

__all__ = [
    "DEPTH_FLOW",
    "DepthResult",
    "compute_flows",
    "depth_from_parallax",
    "depth_from_views",
    "estimate_depth",
]

#: DIS parameters for depth (tuned on the simulator: fine patches, dense
#: stride, variational refinement; see ``benchmarks/flow_tuning.py``).
DEPTH_FLOW = FlowParams(patch_size=8, patch_stride=3, variational_iterations=5)


@dataclass
class DepthResult:
    """Depth of one capture in the reference view's rectified frame.

    Attributes
    ----------
    parallax : (H, W) float32
        ``s`` (0 on the reference board plane, -> 1 at infinity); NaN unknown.
    confidence : (H, W) float32
        0 (no information) .. 1.
    residual : (H, W) float32
        RMS of ``|u_i - o_i s|`` over the views used, px.
    perpendicular : (H, W) float32
        RMS flow component perpendicular to ``o_i``, px (calibration quality).
    n_used : (H, W) uint8
        Views used per pixel.
    depth : (H, W) float32 or None
        Metres from the front lens plane (metric calibrations); NaN unknown.
    relative : (H, W) float32 or None
        ``t = s Z_c / Z_b`` for relative calibrations.
    timings : dict
        Seconds per stage.
    """

    parallax: np.ndarray
    confidence: np.ndarray
    residual: np.ndarray
    perpendicular: np.ndarray
    n_used: np.ndarray
    depth: np.ndarray | None = None
    relative: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)


def _grid(h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([xx, yy], -1)


def compute_flows(
    views: np.ndarray,
    reference: int,
    *,
    params: FlowParams | None = None,
    fb_threshold: float = 0.75,
    threads: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Flow from the reference view to each view, with forward-backward weights.

    Parameters
    ----------
    views : (N, H, W[, C]) float array
        Rectified views; NaN where a view does not see.
    reference : int
        Reference view index.
    params : FlowParams, optional
        DIS parameters (default :data:`DEPTH_FLOW`).
    fb_threshold : float
        Pixels whose forward-backward round trip misses by more than this (px)
        get weight 0 (occlusions, flow failures).
    threads : int
        Flows computed concurrently (OpenCV releases the GIL).

    Returns
    -------
    flows : (N, H, W, 2) float32
        ``u_i(p)``: the reference pixel p appears at ``p + u_i(p)`` in view i;
        NaN where unusable; the reference's own entry is NaN.
    weights : (N, H, W) float32
        1 where the flow passed the checks, 0 elsewhere.
    """
    from .warp import remap_bilinear

    params = params or DEPTH_FLOW
    N, H, W = views.shape[:3]
    valid = np.isfinite(views).all(-1) if views.ndim == 4 else np.isfinite(views)
    prepared = [prepare(v) for v in views]
    grid = _grid(H, W)
    flows = np.full((N, H, W, 2), np.nan, np.float32)
    weights = np.zeros((N, H, W), np.float32)

    def one(i: int) -> None:
        f = dis_flow(prepared[reference], prepared[i], params)
        b = dis_flow(prepared[i], prepared[reference], params)
        target = grid + f
        back = remap_bilinear(b, target)
        fb = np.hypot(*np.moveaxis(f + back, -1, 0))
        lands = remap_bilinear(valid[i].astype(np.float32), target)
        ok = valid[reference] & (fb < fb_threshold) & (lands > 0.999)
        flows[i] = np.where(ok[..., None], f, np.nan)
        weights[i] = ok

    others = [i for i in range(N) if i != reference]
    with ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
        list(ex.map(one, others))
    return flows, weights


def depth_from_parallax(s: np.ndarray, z_b: float, z_c: float) -> np.ndarray:
    """``Z = Z_c + (Z_b - Z_c) / (1 - s)``; NaN where ``s >= 1`` (beyond infinity)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z = z_c + (z_b - z_c) / (1.0 - s)
    return np.where(s < 1.0, z, np.nan).astype(np.float32)


def depth_from_views(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    *,
    flow: FlowParams | None = None,
    threads: int = 2,
    **triangulation: Any,
) -> DepthResult:
    """Parallax from bare rectified views: any camera array or light field.

    Parameters
    ----------
    views : (N, H, W[, C]) float array
        Rectified views (NaN where a view does not see), any brightness.
    offsets : (N, 2) array
        ``o_i``: view i's parallax vector in px per unit ``s`` (the reference
        pixel p appears at ``p + o_i s`` in view i); ``offsets[reference] = 0``.
    reference : int
        Reference view index.
    flow : FlowParams, optional
        DIS parameters.
    threads : int
        Concurrent flows.
    **triangulation
        Passed to :func:`lfcam.triangulate` (``cutoff``, ``sigma_floor``, ...).

    Returns
    -------
    DepthResult
        ``parallax`` (= s), ``confidence``, ``residual``, ``perpendicular``,
        ``n_used``; ``depth`` is None (no metric model here).

    Examples
    --------
    >>> res = lfcam.depth_from_views(views, offsets, reference=4)   # doctest: +SKIP
    >>> disparity = res.parallax                                    # doctest: +SKIP
    """
    import time

    from .triangulate import triangulate

    views = np.asarray(views)
    if views.ndim not in (3, 4) or views.shape[0] < 2:
        raise InputError(f"views: expected (N, H, W[, C]) with N >= 2, got shape {views.shape}")
    if views.dtype != np.float32:
        views = views.astype(np.float32)
    offsets = np.asarray(offsets, np.float64)
    if offsets.shape != (views.shape[0], 2) or not np.isfinite(offsets).all():
        raise InputError(
            f"offsets: expected finite (N, 2) = ({views.shape[0]}, 2), got {offsets.shape}"
        )
    if not (0 <= int(reference) < views.shape[0]):
        raise InputError(f"reference: {reference} is not a view index (0..{views.shape[0] - 1})")
    t0 = time.perf_counter()
    flows, weights = compute_flows(views, int(reference), params=flow, threads=threads)
    t1 = time.perf_counter()
    tri = triangulate(flows, offsets, int(reference), weights, **triangulation)
    t2 = time.perf_counter()
    return DepthResult(
        parallax=tri.parallax,
        confidence=tri.confidence,
        residual=tri.residual,
        perpendicular=tri.perpendicular,
        n_used=tri.n_used,
        timings={"flow": t1 - t0, "triangulation": t2 - t1},
    )


def estimate_depth(views: np.ndarray, cal: Calibration, **kwargs: Any) -> DepthResult:
    """Depth of one capture from its rectified views and the camera's calibration.

    Parameters
    ----------
    views : (N, H_rect, W_rect, C) float array
        From :func:`lfcam.rectify`.
    cal : Calibration
        The camera.
    **kwargs
        Passed to :func:`depth_from_views`.

    Returns
    -------
    DepthResult
        With ``depth`` in metres (metric calibrations) or ``relative``
        (``t = s Z_c / Z_b``, triangulated against ``d_i``) otherwise.
    """
    if views.shape[0] != cal.n_views or tuple(views.shape[1:3]) != tuple(cal.rect_shape):
        raise InputError(
            f"views: shape {views.shape} does not match the calibration"
            f" ({cal.n_views}, {cal.rect_shape[0]}, {cal.rect_shape[1]}, C)"
        )
    res = depth_from_views(views, cal.offsets, cal.reference, **kwargs)
    if cal.metric:
        res.depth = depth_from_parallax(res.parallax, cal.z_b, cal.z_c)
    else:
        res.relative = res.parallax
    return res
