"""Data with ground truth: the camera simulator (:mod:`.camera`, :mod:`.scenes`,
:mod:`.simulator`), light fields made elsewhere (:mod:`.lightfield`) and the accuracy
measures (:mod:`.metrics`)."""

from .camera import SCENES, SimConfig, SimulatedCamera
from .lightfield import LightField, RigParameters, parse_views
from .metrics import BADPIX_THRESHOLD, HCI_BORDER, depth_accuracy, disparity_metrics
from .simulator import SimulationResult, load_truth, simulate

__all__ = [
    "BADPIX_THRESHOLD",
    "HCI_BORDER",
    "SCENES",
    "LightField",
    "RigParameters",
    "SimConfig",
    "SimulatedCamera",
    "SimulationResult",
    "depth_accuracy",
    "disparity_metrics",
    "load_truth",
    "parse_views",
    "simulate",
]
