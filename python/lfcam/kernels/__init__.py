"""Array operations with no knowledge of the camera or of files: lenslet crops, warp
maps and rectification over the Rust core, OpenCV optical flow, robust statistics.
Both calibration and processing are built from them."""

from .crop import crop_lenslets
from .flow import FlowParams, dis_flow, prepare
from .stats import nan_median
from .warp import INTERPOLATIONS, RectifyPlan, identity_grid, rectify, remap, remap_bilinear

__all__ = [
    "INTERPOLATIONS",
    "FlowParams",
    "RectifyPlan",
    "crop_lenslets",
    "dis_flow",
    "identity_grid",
    "nan_median",
    "prepare",
    "rectify",
    "remap",
    "remap_bilinear",
]
