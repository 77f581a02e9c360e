"""Products of a processed capture: 3-D points and cameras (:mod:`.geometry`), meshes
(:mod:`.mesh`) and novel views (:mod:`.render`), super-resolution (:mod:`.superres`)
and refocus (:mod:`.refocus`)."""

from .geometry import lenslet_camera, points_from_depth, pose_matrix, reference_camera
from .mesh import Mesh, mesh_from_depth, write_mesh_ply
from .refocus import all_in_focus, parallax_at_depth, refocus
from .render import RenderResult, render_mesh, render_view
from .superres import SuperResParams, super_resolve

__all__ = [
    "Mesh",
    "RenderResult",
    "SuperResParams",
    "all_in_focus",
    "lenslet_camera",
    "mesh_from_depth",
    "parallax_at_depth",
    "points_from_depth",
    "pose_matrix",
    "reference_camera",
    "refocus",
    "render_mesh",
    "render_view",
    "super_resolve",
    "write_mesh_ply",
]
