"""Novel views: a depth mesh rendered from a new camera pose (paper section 5.3).

The cameras (the reference lenslet's, the other lenslets', virtual ones) are in
:mod:`lfcam.products.geometry`. Depth maps returned here are the virtual camera's z
plus ``Z_c``, so a render at the reference pose returns the front-lens depth Z,
comparable to ``result.depth.depth``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

import lfcam._lfcam as _lfcam

from ..calibration import Calibration
from ..errors import InputError
from ..processing import DepthResult
from .geometry import pose_matrix, reference_camera, require_metric
from .mesh import DEFAULT_MAX_RATIO, Mesh, mesh_from_depth


class Processed(Protocol):
    """What :func:`render_view` needs of a processed capture (a
    :class:`~lfcam.CaptureResult`): its rectified views and its depth."""

    views: np.ndarray
    depth: DepthResult


__all__ = ["NEAR_M", "Processed", "RenderResult", "rasterize", "render_mesh", "render_view"]

#: Vertices nearer than this to the virtual camera's centre plane (metres) are not
#: drawn (their triangles are skipped, not clipped).
NEAR_M = 1e-3


@dataclass
class RenderResult:
    """A rendered view.

    Attributes
    ----------
    image : (H, W, C) float32
        Linear colour, [0, 1]; NaN where nothing was seen.
    depth : (H, W) float32
        Virtual camera's z + ``Z_c`` (metres; see the module docs); NaN where nothing
        was seen.
    mask : (H, W) bool
        True where a triangle was drawn.
    """

    image: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


def rasterize(
    vertices: np.ndarray,
    colours: np.ndarray,
    faces: np.ndarray,
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-buffered rasterisation of a triangle mesh already projected to the image.

    Pixel ``(u, v)`` is centred at integer coordinates; a pixel centre is drawn by a
    triangle containing it (an edge shared by two triangles belongs to exactly one of
    them); colour and depth are interpolated perspective-correctly; the nearest
    surface wins. Triangles with a non-finite vertex or ``z <= 0`` are skipped.

    Parameters
    ----------
    vertices : (M, 3) array
        ``x`` (column, px), ``y`` (row, px), ``z`` (depth, > 0) of each vertex.
    colours : (M,) or (M, C) array
        Per-vertex values to interpolate.
    faces : (K, 3) integer array
        Vertex indices.
    shape : (int, int)
        Output ``(H, W)``.

    Returns
    -------
    image : (H, W, C) float32
        NaN where nothing was drawn.
    depth : (H, W) float32
        Interpolated z; NaN where nothing was drawn.
    mask : (H, W) bool
    """
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"vertices: expected shape (M, 3), got {v.shape}")
    c = np.asarray(colours, dtype=np.float32)
    if c.ndim == 1:
        c = c[:, None]
    c = np.ascontiguousarray(c)
    if c.ndim != 2 or c.shape[0] != v.shape[0]:
        raise InputError(f"colours: expected shape ({v.shape[0]}, C), got {c.shape}")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and not np.issubdtype(f.dtype, np.integer)):
        raise InputError(f"faces: expected an integer (K, 3) array, got {f.shape} {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(
            f"faces: vertex indices must be in [0, {len(v)}), got {f.min()}..{f.max()}"
        )
    f = np.ascontiguousarray(f, dtype=np.int32)
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape: expected (H, W), got {shape!r}") from None
    image, depth, mask = _lfcam.rasterize(v, c, f, h, w)
    return image, depth, mask.view(bool)  # 0/1 bytes: a valid bool array, no copy


def render_mesh(
    mesh: Mesh,
    cal: Calibration,
    pose: Any,
    intrinsics: np.ndarray | None = None,
    *,
    shape: tuple[int, int] | None = None,
) -> RenderResult:
    """Render a depth mesh (:func:`lfcam.products.mesh.mesh_from_depth`) from ``pose``.

    Parameters
    ----------
    mesh : Mesh
        Vertices in metres (front-lens frame).
    cal : Calibration
        The camera the mesh came from (metric, pattern pitch known).
    pose : (4, 4) array or (rotation, translation)
        See :func:`pose_matrix`; the identity is the reference camera.
    intrinsics : (3, 3) array, optional
        ``K`` of the virtual camera in pixels; default the reference's
        (:func:`reference_camera`).
    shape : (int, int), optional
        Output ``(H, W)``; default the rectified frame's.

    Returns
    -------
    RenderResult
    """
    require_metric(cal)
    if mesh.units != "m":
        raise InputError(f"mesh: vertices must be in metres, got {mesh.units!r}")
    M = pose_matrix(pose)
    centre, K_ref = reference_camera(cal)
    K = K_ref if intrinsics is None else np.asarray(intrinsics, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise InputError(f"intrinsics: expected a finite (3, 3) matrix, got shape {K.shape}")
    if shape is None:
        shape = (int(cal.rect_shape[0]), int(cal.rect_shape[1]))
    R, t = M[:3, :3], M[:3, 3]
    # X_cam = R^T (X_ref - t), X_ref = X_lens - centre.
    P = (mesh.vertices.astype(np.float64) - (centre + t)) @ R
    z = P[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = P @ K.T
        xy = uvw[:, :2] / uvw[:, 2:3]
    proj = np.empty((len(P), 3), np.float32)
    proj[:, :2] = xy
    proj[:, 2] = np.where(z > NEAR_M, z, np.nan)
    image, depth, mask = rasterize(proj, mesh.colours, mesh.faces, shape)
    depth += np.float32(cal.z_c)
    return RenderResult(image, depth, mask)


def render_view(
    result: Processed | Mesh,
    pose: Any,
    intrinsics: np.ndarray | None = None,
    *,
    cal: Calibration,
    shape: tuple[int, int] | None = None,
    max_ratio: float = DEFAULT_MAX_RATIO,
) -> RenderResult:
    """Render a processed capture from a new camera pose (paper section 5.3).

    The depth is turned into a mesh (:func:`lfcam.products.mesh.mesh_from_depth`, cut at
    discontinuities) coloured from the reference view, and drawn with a z-buffer.
    Holes (nothing seen) are NaN in the image and depth and False in the mask.

    Parameters
    ----------
    result : CaptureResult or Mesh
        From :func:`lfcam.process_capture` (metric depth), or a mesh.
    pose : (4, 4) array or (rotation, translation)
        The virtual camera in the reference camera's frame (:func:`pose_matrix`).
    intrinsics : (3, 3) array, optional
        Default: the reference view's rectified-frame camera.
    cal : Calibration
        The camera.
    shape : (int, int), optional
        Output ``(H, W)``; default the rectified frame's.
    max_ratio : float
        Discontinuity threshold of the mesh.

    Returns
    -------
    RenderResult
        ``image`` (H, W, C) float32, ``depth`` (H, W) float32, ``mask`` (H, W) bool.

    Examples
    --------
    >>> res = lfcam.process_capture("capture.png", cal)  # doctest: +SKIP
    >>> view = lfcam.render_view(res, (np.zeros(3), [0.01, 0, 0]), cal=cal)  # doctest: +SKIP
    """
    if isinstance(result, Mesh):
        mesh = result
    else:
        depth = result.depth.depth
        if depth is None:
            raise InputError("result: has no metric depth (relative calibration)")
        mesh = mesh_from_depth(depth, cal, result.views[cal.reference], max_ratio=max_ratio)
    return render_mesh(mesh, cal, pose, intrinsics, shape=shape)
