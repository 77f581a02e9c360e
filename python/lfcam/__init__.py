"""lfcam: multiview light-field camera processing.

Raw frames from a camera with one front lens and an array of large lenslets become
rectified views, metric depth, super-resolved, refocused and novel-view images. The
per-pixel work runs in a Rust core (``lfcam._lfcam``) on lfcam's own thread pool; see
:func:`set_num_threads` and the ``LFCAM_NUM_THREADS`` environment variable.
"""

from lfcam._lfcam import __version__, get_num_threads, set_num_threads
from lfcam.calibrate import calibrate
from lfcam.calibration import Calibration
from lfcam.crop import crop_lenslets
from lfcam.depth import DepthResult, depth_from_views, estimate_depth
from lfcam.errors import CalibrationError, InputError, LfcamError, NumericalError
from lfcam.io import read_image, read_pfm, read_raw, write_pfm
from lfcam.lightfield import LightField
from lfcam.mesh import Mesh, mesh_from_depth
from lfcam.pattern import make_pattern
from lfcam.pipeline import CaptureResult, process_capture, rectify
from lfcam.render import RenderResult, render_view
from lfcam.simulator import SimConfig, SimulationResult, simulate
from lfcam.stats import nan_median
from lfcam.superres import all_in_focus, refocus, super_resolve
from lfcam.triangulate import TriangulationResult, triangulate
from lfcam.warp import remap_bilinear

__all__ = [
    "Calibration",
    "CalibrationError",
    "CaptureResult",
    "DepthResult",
    "InputError",
    "LfcamError",
    "LightField",
    "Mesh",
    "NumericalError",
    "RenderResult",
    "SimConfig",
    "SimulationResult",
    "TriangulationResult",
    "__version__",
    "all_in_focus",
    "calibrate",
    "crop_lenslets",
    "depth_from_views",
    "estimate_depth",
    "get_num_threads",
    "make_pattern",
    "mesh_from_depth",
    "nan_median",
    "process_capture",
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
