"""Novel views: a depth mesh rendered from a new camera pose (paper section 5.3).

The camera model (DESIGN.md sections 1-3). In object space the reference lenslet is a
pinhole camera with centre ``C_ref = (b_ref, Z_c)`` in the front lens's frame, axes
those of the lens (X right, Y down, Z forward), whose image plane is the board at
``Z_b``: rectified pixel p sees the board point ``B(p)``. So its focal length, in
rectified pixels, is ``f = (Z_b - Z_c) / pitch_rect`` (``pitch_rect``: the size of a
rectified pixel on the board) and its principal point is the rectified pixel whose
board point lies straight ahead of ``C_ref``. Lenslet i's camera is the same one
moved by ``b_i - b_ref = o_i * pitch_rect`` laterally, with the principal point moved
by ``o_i`` px (the rectified views share the board plane as their image plane): a
point at depth Z seen at reference pixel p then projects to ``p + o_i s(Z)``,
DESIGN.md's depth equation. :func:`lenslet_camera` gives that pose and intrinsics.

A pose is the virtual camera's position and orientation in the reference camera's
frame: ``X_ref = R X_cam + t`` (``t``: its centre, metres; ``R``: its axes). Depth
maps returned here are the virtual camera's z plus ``Z_c``, so a render at the
reference pose returns the front-lens depth Z, comparable to ``result.depth.depth``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from . import _lfcam
from .calibration import Calibration
from .errors import InputError
from .mesh import DEFAULT_MAX_RATIO, Mesh, mesh_from_depth

if TYPE_CHECKING:
    from .pipeline import CaptureResult

__all__ = [
    "NovelViewOptions",
    "RenderResult",
    "lenslet_camera",
    "orbit_poses",
    "parse_pose",
    "pose_matrix",
    "rasterize",
    "reference_camera",
    "render_mesh",
    "render_view",
    "write_novel_views",
]

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


def _require_metric(cal: Calibration) -> None:
    if not cal.metric or not np.isfinite(cal.pattern_pitch):
        raise InputError(
            "cal: novel views need a metric calibration with a known pattern pitch"
            f" (metric={cal.metric}, pattern_pitch={cal.pattern_pitch})"
        )


def _pitch_rect(cal: Calibration) -> tuple[float, float]:
    """Size (m) of a rectified pixel on the board, along x and y."""
    sx = cal.pattern_shape[1] / cal.rect_shape[1]
    sy = cal.pattern_shape[0] / cal.rect_shape[0]
    return float(cal.pattern_pitch * sx), float(cal.pattern_pitch * sy)


def reference_camera(cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """The reference lenslet's object-space pinhole camera.

    Returns
    -------
    centre : (3,) float64
        ``(b_ref, Z_c)`` in the front lens's frame, metres (the lenslet array taken
        as centred on the lens axis, as :func:`lfcam.outputs.points_from_depth`).
    intrinsics : (3, 3) float64
        ``K`` of the rectified frame: ``f = (Z_b - Z_c) / pitch_rect`` px, principal
        point the rectified pixel straight ahead of the centre.
    """
    _require_metric(cal)
    px, py = _pitch_rect(cal)
    b_ref = -cal.offsets.mean(axis=0) * np.array([px, px])  # as points_from_depth
    sx = cal.pattern_shape[1] / cal.rect_shape[1]
    sy = cal.pattern_shape[0] / cal.rect_shape[0]
    # Board point of pixel u: x_pat * pitch, x_pat = (u + 0.5) sx - 0.5 - (W_pat - 1) / 2.
    cx = (b_ref[0] / cal.pattern_pitch + 0.5 + (cal.pattern_shape[1] - 1) / 2.0) / sx - 0.5
    cy = (b_ref[1] / cal.pattern_pitch + 0.5 + (cal.pattern_shape[0] - 1) / 2.0) / sy - 0.5
    dz = cal.z_b - cal.z_c
    K = np.array([[dz / px, 0.0, cx], [0.0, dz / py, cy], [0.0, 0.0, 1.0]])
    return np.array([b_ref[0], b_ref[1], cal.z_c]), K


def lenslet_camera(cal: Calibration, view: int) -> tuple[np.ndarray, np.ndarray]:
    """Pose and intrinsics of lenslet ``view``'s camera, relative to the reference.

    Rendering the reference's depth mesh with them reproduces view ``view``'s
    rectified geometry (``p -> p + o_i s``; see the module docs).

    Returns
    -------
    pose : (4, 4) float64
        Translation ``o_i * pitch_rect`` (metres), no rotation.
    intrinsics : (3, 3) float64
        The reference's, principal point moved by ``o_i`` px.
    """
    n = len(cal.offsets)
    if not 0 <= int(view) < n:
        raise InputError(f"view: index {view} is out of range for {n} views")
    _, K = reference_camera(cal)
    o = cal.offsets[int(view)]
    px, py = _pitch_rect(cal)
    pose = np.eye(4)
    pose[:2, 3] = o * np.array([px, py])
    K = K.copy()
    K[:2, 2] += o
    return pose, K


def pose_matrix(pose: Any) -> np.ndarray:
    """A pose as a 4 x 4 matrix.

    Parameters
    ----------
    pose : (4, 4) array, or (rotation, translation)
        ``rotation`` a (3, 3) matrix or a (3,) rotation vector (axis x angle, radians);
        ``translation`` (3,), metres. The camera's axes and centre in the reference
        camera's frame: ``X_ref = R X_cam + t``.
    """
    if isinstance(pose, (tuple, list)) and len(pose) == 2:
        R = np.asarray(pose[0], dtype=np.float64)
        t = np.asarray(pose[1], dtype=np.float64)
        if R.shape == (3,):
            R = _rodrigues(R)
        if R.shape != (3, 3) or t.shape != (3,):
            raise InputError(
                f"pose: expected (rotation (3, 3) or (3,), translation (3,)), got shapes"
                f" {R.shape} and {t.shape}"
            )
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, t
    else:
        M = np.asarray(pose, dtype=np.float64)
        if M.shape != (4, 4):
            raise InputError(
                f"pose: expected a (4, 4) matrix or (rotation, translation), got shape {M.shape}"
            )
    if not np.isfinite(M).all():
        raise InputError("pose: has non-finite values")
    R = M[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError("pose: the rotation is not a proper rotation matrix")
    if not np.allclose(M[3], [0, 0, 0, 1]):
        raise InputError(f"pose: last row must be (0, 0, 0, 1), got {M[3].tolist()}")
    return M


def _rodrigues(r: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R: np.ndarray = np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * (Kx @ Kx)
    return R


def render_mesh(
    mesh: Mesh,
    cal: Calibration,
    pose: Any,
    intrinsics: np.ndarray | None = None,
    *,
    shape: tuple[int, int] | None = None,
) -> RenderResult:
    """Render a depth mesh (:func:`lfcam.mesh.mesh_from_depth`) from ``pose``.

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
    _require_metric(cal)
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
    result: CaptureResult | Mesh,
    pose: Any,
    intrinsics: np.ndarray | None = None,
    *,
    cal: Calibration,
    shape: tuple[int, int] | None = None,
    max_ratio: float = DEFAULT_MAX_RATIO,
) -> RenderResult:
    """Render a processed capture from a new camera pose (paper section 5.3).

    The depth is turned into a mesh (:func:`lfcam.mesh.mesh_from_depth`, cut at
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


def orbit_poses(
    cal: Calibration,
    n: int,
    *,
    radius: float | None = None,
    target_depth: float | None = None,
) -> list[np.ndarray]:
    """``n`` poses on a circle in the lens plane, looking at a point on the axis.

    Parameters
    ----------
    cal : Calibration
        The camera (metric).
    n : int
        Number of poses (>= 1).
    radius : float, optional
        Circle radius, metres; default the lenslet baseline (largest ``|b_i - b_ref|``).
    target_depth : float, optional
        Depth (m, front-lens frame) of the point the camera turns to; default ``Z_b``.

    Returns
    -------
    list of (4, 4) float64
    """
    _require_metric(cal)
    if int(n) < 1:
        raise InputError(f"n: expected at least 1 frame, got {n}")
    px, py = _pitch_rect(cal)
    if radius is None:
        radius = float(np.max(np.hypot(cal.offsets[:, 0] * px, cal.offsets[:, 1] * py)))
    if not (np.isfinite(radius) and radius >= 0):
        raise InputError(f"radius: expected a finite number >= 0, got {radius}")
    zt = cal.z_b if target_depth is None else float(target_depth)
    if not (np.isfinite(zt) and zt > cal.z_c):
        raise InputError(f"target_depth: expected a depth beyond Z_c = {cal.z_c} m, got {zt}")
    centre, _ = reference_camera(cal)
    target = np.array([0.0, 0.0, zt - centre[2]])  # straight ahead of the reference camera
    poses = []
    for k in range(int(n)):
        a = 2 * math.pi * k / int(n)
        t = np.array([radius * math.cos(a), radius * math.sin(a), 0.0])
        fwd = target - t
        fwd /= np.linalg.norm(fwd)
        right = np.cross([0.0, 1.0, 0.0], fwd)  # Y down: right = down x forward
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        M = np.eye(4)
        M[:3, :3] = np.column_stack([right, down, fwd])
        M[:3, 3] = t
        poses.append(M)
    return poses


def parse_pose(text: str) -> np.ndarray:
    """``"TX,TY,TZ[,RX,RY,RZ]"`` (metres, rotation vector in degrees) -> 4 x 4 pose."""
    try:
        vals: Sequence[float] = [float(s) for s in text.split(",")]
    except ValueError:
        raise InputError(f"pose: expected TX,TY,TZ[,RX,RY,RZ] numbers, got {text!r}") from None
    if len(vals) not in (3, 6):
        raise InputError(f"pose: expected 3 or 6 comma-separated numbers, got {len(vals)}")
    r = np.radians(vals[3:]) if len(vals) == 6 else np.zeros(3)
    return pose_matrix((r, np.array(vals[:3])))


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

    Called by :func:`lfcam.outputs.write_capture` inside its atomic folder. PNGs are
    gamma-encoded like the other previews; holes (nothing seen) are black.

    Returns
    -------
    dict
        What was written, for ``result.json``.
    """
    import time
    from pathlib import Path

    import cv2

    from .io import write_image
    from .mesh import write_mesh_ply
    from .outputs import _to_u8

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
        write_image(out / "novel_view.png", _to_u8(r.image))
        write_image(out / "novel_view_depth.tiff", r.depth)
        info["novel_view_pose"] = options.pose.tolist()
        info["novel_view_coverage"] = float(r.mask.mean())
    if options.orbit > 0:
        (out / "orbit").mkdir()
        H, W = cal.rect_shape
        video = cv2.VideoWriter(str(out / "orbit.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), 12, (W, H))
        try:
            for k, pose in enumerate(orbit_poses(cal, options.orbit)):
                rgb = _to_u8(render_mesh(mesh, cal, pose).image)
                if rgb.ndim == 2:
                    rgb = np.repeat(rgb[..., None], 3, 2)
                write_image(out / "orbit" / f"frame_{k:03d}.png", rgb)
                video.write(np.ascontiguousarray(rgb[..., ::-1]))
        finally:
            video.release()
        info["orbit_frames"] = options.orbit
    info["novel_views_s"] = time.perf_counter() - t0
    return info
