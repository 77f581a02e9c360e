"""Geometry of the calibrated camera: 3-D points of a depth map, and the object-space
pinhole cameras of the lenslets and of virtual views.

The camera model (docs/design.md, "Camera model"). In object space the reference lenslet
is a pinhole camera with centre ``C_ref = (b_ref, Z_c)`` in the front lens's frame, axes
those of the lens (X right, Y down, Z forward), whose image plane is the board at
``Z_b``: rectified pixel p sees the board point ``B(p)``. So its focal length, in
rectified pixels, is ``f = (Z_b - Z_c) / pitch_rect`` (``pitch_rect``: the size of a
rectified pixel on the board) and its principal point is the rectified pixel whose
board point lies straight ahead of ``C_ref``. Lenslet i's camera is the same one
moved by ``b_i - b_ref = o_i * pitch_rect`` laterally, with the principal point moved
by ``o_i`` px (the rectified views share the board plane as their image plane): a
point at depth Z seen at reference pixel p then projects to ``p + o_i s(Z)``,
the depth equation (docs/design.md, "Plane and parallax"). :func:`lenslet_camera`
gives that pose and intrinsics.

A pose is the virtual camera's position and orientation in the reference camera's
frame: ``X_ref = R X_cam + t`` (``t``: its centre, metres; ``R``: its axes). Depth
maps returned here are the virtual camera's z plus ``Z_c``, so a render at the
reference pose returns the front-lens depth Z, comparable to ``result.depth.depth``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..errors import InputError

__all__ = [
    "lenslet_camera",
    "orbit_poses",
    "parse_pose",
    "pitch_rect",
    "points_from_depth",
    "pose_matrix",
    "reference_camera",
    "require_metric",
]

#: Largest ``|translation|`` component of a novel-view pose, metres, and largest
#: rotation-vector component, degrees: beyond them a pose is a mistake (and its
#: arithmetic overflows).
MAX_POSE_TRANSLATION_M = 1e4
MAX_POSE_ROTATION_DEG = 1e4


def points_from_depth(depth: np.ndarray, cal: Calibration) -> tuple[np.ndarray, np.ndarray, str]:
    """3-D points (metres, front-lens frame: X right, Y down, Z forward) of finite depths.

    The reference view's object-space centre is ``(b_ref, Z_c)``; its ray through
    rectified pixel p passes the board point ``B(p)`` at ``Z_b``, so the point at
    depth Z is ``C + (B - C)(Z - Z_c)/(Z_b - Z_c)``. Lateral positions need the
    pattern pitch; the lenslet array is taken as centred on the lens axis
    (``sum_i b_i = 0``). Without a pitch, X and Y are in rectified pixels at
    ``Z_b`` (units ``"board px"``).

    Returns
    -------
    points : (M, 3) float32
    index : (M, 2) int64
        Row and column of each point in the rectified frame.
    units : str
        ``"m"`` or ``"board px"`` for X and Y.
    """
    vv, uu = np.nonzero(np.isfinite(depth))
    Z = depth[vv, uu].astype(np.float64)
    sx, sy = cal.pattern_shape[1] / cal.rect_shape[1], cal.pattern_shape[0] / cal.rect_shape[0]
    xp = (uu + 0.5) * sx - 0.5 - (cal.pattern_shape[1] - 1) / 2.0
    yp = (vv + 0.5) * sy - 0.5 - (cal.pattern_shape[0] - 1) / 2.0
    metric_xy = np.isfinite(cal.pattern_pitch)
    if metric_xy:
        pitch_rect = cal.pattern_pitch * sx
        B = np.stack([xp * cal.pattern_pitch, yp * cal.pattern_pitch], 1)
    else:
        pitch_rect = 1.0
        B = np.stack([uu, vv], 1).astype(np.float64)
    if cal.metric:
        b_ref = -cal.offsets.mean(axis=0) * pitch_rect
        f = (Z - cal.z_c) / (cal.z_b - cal.z_c)
        XY = b_ref + (B - b_ref) * f[:, None]
    else:
        XY = B
    pts = np.column_stack([XY, Z]).astype(np.float32)
    return pts, np.stack([vv, uu], 1), "m" if metric_xy else "board px"


def require_metric(cal: Calibration) -> None:
    if not cal.metric or not np.isfinite(cal.pattern_pitch):
        raise InputError(
            "cal: novel views need a metric calibration with a known pattern pitch"
            f" (metric={cal.metric}, pattern_pitch={cal.pattern_pitch})"
        )


def pitch_rect(cal: Calibration) -> tuple[float, float]:
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
        as centred on the lens axis, as :func:`points_from_depth`).
    intrinsics : (3, 3) float64
        ``K`` of the rectified frame: ``f = (Z_b - Z_c) / pitch_rect`` px, principal
        point the rectified pixel straight ahead of the centre.
    """
    require_metric(cal)
    px, py = pitch_rect(cal)
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
    px, py = pitch_rect(cal)
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
    require_metric(cal)
    if int(n) < 1:
        raise InputError(f"n: expected at least 1 frame, got {n}")
    px, py = pitch_rect(cal)
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
    limits = [MAX_POSE_TRANSLATION_M] * 3 + [MAX_POSE_ROTATION_DEG] * 3
    for v, limit in zip(vals, limits):
        if not (math.isfinite(v) and abs(v) <= limit):
            raise InputError(
                f"pose: translation within +-{MAX_POSE_TRANSLATION_M:g} m and rotation within "
                f"+-{MAX_POSE_ROTATION_DEG:g} degrees expected, got {v!r} in {text!r}"
            )
    r = np.radians(vals[3:]) if len(vals) == 6 else np.zeros(3)
    return pose_matrix((r, np.array(vals[:3])))
