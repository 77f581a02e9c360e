"""lfcam: multiview light-field camera processing.

Raw frames from a camera with one front lens and an array of large lenslets become
rectified views, metric depth, super-resolved, refocused and novel-view images. The
per-pixel work runs in a Rust core (``lfcam._lfcam``) on lfcam's own thread pool; see
:func:`set_num_threads` and the ``LFCAM_NUM_THREADS`` environment variable.

The stages live in subpackages that import only downwards (docs/design.md, "Module
map"): :mod:`lfcam.io` and :mod:`lfcam.kernels` <- :mod:`lfcam.calibration` <-
:mod:`lfcam.processing` <- :mod:`lfcam.products` and :mod:`lfcam.sim` <-
:mod:`lfcam.pipeline` <- :mod:`lfcam.outputs` <- :mod:`lfcam.batch` <- :mod:`lfcam.cli`.
"""

from lfcam._build import build_info
from lfcam._lfcam import __version__, get_num_threads, set_num_threads
from lfcam.batch import BatchSummary, ProcessOptions, process_folder
from lfcam.calibration import (
    Calibration,
    CalibrationParams,
    ZoomCalibration,
    calibrate,
    make_pattern,
)
from lfcam.errors import (
    CalibrationError,
    InputError,
    LfcamError,
    LfcamWarning,
    NumericalError,
)
from lfcam.io import read_image, read_pfm, read_raw, write_pfm
from lfcam.kernels import crop_lenslets, nan_median, remap_bilinear
from lfcam.pipeline import CaptureResult, process_capture
from lfcam.processing import (
    DepthParams,
    DepthResult,
    RefineParams,
    TriangulationParams,
    TriangulationResult,
    depth_from_views,
    estimate_depth,
    rectify,
    triangulate,
)
from lfcam.products import (
    Mesh,
    RenderResult,
    SuperResParams,
    all_in_focus,
    mesh_from_depth,
    refocus,
    render_view,
    super_resolve,
)
from lfcam.sim import LightField, SimConfig, SimulationResult, simulate

__all__ = [
    "BatchSummary",
    "Calibration",
    "CalibrationError",
    "CalibrationParams",
    "CaptureResult",
    "DepthParams",
    "DepthResult",
    "InputError",
    "LfcamError",
    "LfcamWarning",
    "LightField",
    "Mesh",
    "NumericalError",
    "ProcessOptions",
    "RefineParams",
    "RenderResult",
    "SimConfig",
    "SimulationResult",
    "SuperResParams",
    "TriangulationParams",
    "TriangulationResult",
    "ZoomCalibration",
    "__version__",
    "all_in_focus",
    "build_info",
    "calibrate",
    "crop_lenslets",
    "depth_from_views",
    "estimate_depth",
    "get_num_threads",
    "make_pattern",
    "mesh_from_depth",
    "nan_median",
    "process_capture",
    "process_folder",
    "read_image",
    "read_pfm",
    "read_raw",
    "rectify",
    "refocus",
    "remap_bilinear",
    "render_view",
    "set_num_threads",
    "simulate",
    "super_resolve",
    "triangulate",
    "write_pfm",
]
