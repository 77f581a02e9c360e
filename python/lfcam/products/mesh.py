"""Triangle meshes from depth maps (paper section 5.3).

The reference view's rectified frame is a pixel grid; every 2 x 2 quad of pixels
gives two triangles (split along the quad's down-right diagonal), and a triangle is
kept when its three depths are finite and do not straddle a depth discontinuity:

    max(Z) / min(Z) <= 1 + max_ratio         (default ``max_ratio`` = 0.03)

A smooth surface changes depth by ``tan(slope) / f_px`` per pixel (about 0.1% per
pixel for a 60 degree slope with ``f_px`` ~ 1000), so 3% keeps surfaces up to a
grazing ~85 degrees and cuts occlusion edges, where depth jumps by tens of percent.

Vertices are the 3-D points of :func:`lfcam.products.geometry.points_from_depth`: metres in the
front lens's frame (X right, Y down, Z forward) when the calibration is metric and
knows the pattern pitch; otherwise X and Y are in rectified pixels at ``Z_b``
(``Mesh.units`` says which). Colours come from the reference view (linear, [0, 1]).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .._validate import check_instance
from ..calibration import Calibration
from ..errors import InputError
from ..io import rgb_u8, write_ply
from .geometry import points_from_depth

__all__ = ["DEFAULT_MAX_RATIO", "Mesh", "mesh_from_depth", "write_mesh_ply"]

#: Default discontinuity threshold: a triangle whose largest depth exceeds its smallest
#: by more than this fraction is cut.
DEFAULT_MAX_RATIO = 0.03


@dataclass
class Mesh:
    """A coloured triangle mesh over the reference view's rectified pixel grid.

    Attributes
    ----------
    vertices : (M, 3) float32
        Points (see ``units``), front-lens frame: X right, Y down, Z forward.
    colours : (M, C) float32
        Linear colour of each vertex, [0, 1] (C = 1 or 3).
    faces : (K, 3) int32
        Vertex indices of each triangle.
    index : (M, 2) int64
        Row and column of each vertex in the rectified frame.
    units : str
        ``"m"``, or ``"board px"`` when X and Y are rectified pixels at ``Z_b``.
    shape : tuple of int
        ``(H, W)`` of the rectified frame.
    """

    vertices: np.ndarray
    colours: np.ndarray
    faces: np.ndarray
    index: np.ndarray
    units: str
    shape: tuple[int, int]


def mesh_from_depth(
    depth: np.ndarray,
    cal: Calibration,
    colours: np.ndarray | None = None,
    *,
    max_ratio: float = DEFAULT_MAX_RATIO,
) -> Mesh:
    """Grid triangulation of a depth map, cut at depth discontinuities.

    Parameters
    ----------
    depth : (H, W) float array
        Depth in the reference view's rectified frame (metres; NaN unknown), e.g.
        ``result.depth.depth``.
    cal : Calibration
        The camera (for the 3-D positions, see :func:`~lfcam.products.geometry.points_from_depth`).
    colours : (H, W) or (H, W, C) float array, optional
        The reference view (linear, [0, 1]); grey 0.5 if not given.
    max_ratio : float
        A triangle is kept when ``max(Z) / min(Z) <= 1 + max_ratio`` (> 0).

    Returns
    -------
    Mesh
        Only vertices used by a triangle are kept.

    Examples
    --------
    >>> res = lfcam.process_capture("capture.png", cal)  # doctest: +SKIP
    >>> mesh = mesh_from_depth(res.depth.depth, cal, res.views[cal.reference])  # doctest: +SKIP
    """
    check_instance(cal, Calibration, "cal")
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.size == 0:
        raise InputError(f"depth: expected a non-empty (H, W) array, got shape {depth.shape}")
    if tuple(depth.shape) != tuple(cal.rect_shape):
        raise InputError(
            f"depth: shape {depth.shape} is not the calibration's rectified shape"
            f" {tuple(cal.rect_shape)}"
        )
    if not (np.isfinite(max_ratio) and max_ratio > 0):
        raise InputError(f"max_ratio: expected a finite number > 0, got {max_ratio}")
    H, W = depth.shape
    if colours is None:
        col_img = np.full((H, W, 1), 0.5, np.float32)
    else:
        col_img = np.asarray(colours, dtype=np.float32)
        if col_img.ndim == 2:
            col_img = col_img[..., None]
        if col_img.ndim != 3 or col_img.shape[:2] != (H, W):
            raise InputError(
                f"colours: expected an image of {W}x{H} px, (H, W) or (H, W, C), got shape"
                f" {col_img.shape}"
            )
    z = depth.astype(np.float64)
    z[~(z > 0)] = np.nan  # non-positive depth is no surface
    pts, idx, units = points_from_depth(z.astype(np.float32), cal)
    ids = np.full((H, W), -1, np.int64)
    ids[idx[:, 0], idx[:, 1]] = np.arange(len(pts))

    a, b = ids[:-1, :-1], ids[:-1, 1:]
    c, d = ids[1:, :-1], ids[1:, 1:]
    za, zb, zc, zd = z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]
    limit = 1.0 + max_ratio
    tris = []
    # Vertices ordered so that the normal faces the camera (-Z) in X right, Y down.
    for (i0, i1, i2), (z0, z1, z2) in (((a, c, b), (za, zc, zb)), ((b, c, d), (zb, zc, zd))):
        with np.errstate(invalid="ignore"):
            hi = np.fmax(np.fmax(z0, z1), z2)
            lo = np.fmin(np.fmin(z0, z1), z2)
            keep = (i0 >= 0) & (i1 >= 0) & (i2 >= 0) & (hi <= lo * limit)
        tris.append(np.stack([i0[keep], i1[keep], i2[keep]], 1))
    # Row-major order of the quads, both triangles of a quad together.
    faces = np.concatenate(tris, 0)
    used = np.zeros(len(pts), bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    faces = remap[faces].astype(np.int32)
    vidx = idx[used]
    return Mesh(
        vertices=np.ascontiguousarray(pts[used]),
        colours=np.ascontiguousarray(col_img[vidx[:, 0], vidx[:, 1]]),
        faces=np.ascontiguousarray(faces),
        index=vidx,
        units=units,
        shape=(H, W),
    )


def write_mesh_ply(path: str | os.PathLike[str], mesh: Mesh) -> None:
    """Write ``mesh`` as a binary little-endian PLY file, atomically.

    Vertex properties ``float x, y, z`` and ``uchar red, green, blue`` (gamma-encoded
    as the PNG outputs), faces ``list uchar int vertex_indices``. Readable by MeshLab,
    Open3D, trimesh and plyfile.

    Parameters
    ----------
    path : path
        Output file (its folder must exist).
    mesh : Mesh
        From :func:`mesh_from_depth`.
    """
    write_ply(
        path,
        mesh.vertices,
        rgb_u8(mesh.colours),
        mesh.faces,
        comments=[f"units {mesh.units}, front-lens frame: X right, Y down, Z forward"],
    )
