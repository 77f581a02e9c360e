"""Processing: one capture's rectified views -> parallax and depth.

:mod:`.rectify` (raw frame -> views), :mod:`.depth` (flow from the reference view to
every view, then :mod:`.triangulate` onto the calibrated parallax vectors and
:mod:`.fill` of the unreliable pixels, optionally :mod:`.refine`'s plane sweep) -> metric
depth.
"""

from .depth import DEPTH_FLOW, DepthParams, DepthResult, depth_from_views, estimate_depth
from .fill import fill_parallax, guide_image
from .rectify import rectify, rectify_plan
from .refine import RefineParams, RefineResult, refine_parallax
from .triangulate import TriangulationParams, TriangulationResult, triangulate

__all__ = [
    "DEPTH_FLOW",
    "DepthParams",
    "DepthResult",
    "RefineParams",
    "RefineResult",
    "TriangulationParams",
    "TriangulationResult",
    "depth_from_views",
    "estimate_depth",
    "fill_parallax",
    "guide_image",
    "rectify",
    "rectify_plan",
    "refine_parallax",
    "triangulate",
]
