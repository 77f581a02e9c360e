"""PLY files (binary little-endian): coloured point clouds and triangle meshes.

Readable by MeshLab, Open3D, trimesh and plyfile.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from .atomic import atomic_output

__all__ = ["write_ply"]


def write_ply(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    colours: np.ndarray,
    faces: np.ndarray | None = None,
    *,
    comments: Sequence[str] = (),
) -> None:
    """Write a coloured point cloud or triangle mesh as binary PLY, atomically.

    Parameters
    ----------
    path : path-like
        Output file (its folder must exist).
    vertices : (M, 3) float array
        Vertex positions, stored as float32 ``x, y, z``.
    colours : (M, 3) uint8 array
        Display-encoded ``red, green, blue`` per vertex (see
        :func:`lfcam.io.display.encode_u8`).
    faces : (K, 3) int array, optional
        Vertex indices of each triangle, stored as ``list uchar int vertex_indices``;
        without, a point cloud.
    comments : sequence of str
        Header comment lines (units, frame), after ``comment written by lfcam``.
    """
    v = np.asarray(vertices)
    c = np.asarray(colours)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"vertices: expected shape (M, 3), got {v.shape}")
    if c.shape != v.shape or c.dtype != np.uint8:
        raise InputError(f"colours: expected uint8 of shape {v.shape}, got {c.dtype} {c.shape}")
    if any("\n" in line for line in comments):
        raise InputError("comments: a comment must be one line")
    n = len(v)
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by lfcam",
        *(f"comment {line}" for line in comments),
        f"element vertex {n}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
    ]
    vert = np.empty(n, dtype=[("p", "<f4", 3), ("c", "u1", 3)])
    vert["p"] = v
    vert["c"] = c
    body = [vert.tobytes()]
    if faces is not None:
        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 3:
            raise InputError(f"faces: expected shape (K, 3), got {f.shape}")
        lines += [f"element face {len(f)}", "property list uchar int vertex_indices"]
        face = np.empty(len(f), dtype=[("n", "u1"), ("v", "<i4", 3)])
        face["n"] = 3
        face["v"] = f
        body.append(face.tobytes())
    header = ("\n".join([*lines, "end_header"]) + "\n").encode("ascii")
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header)
        for b in body:
            fh.write(b)
