"""Calibration: once per camera (and zoom setting), a folder of captures becomes a
:class:`Calibration`.

One module per step, in the order they run: :mod:`.inputs` (the folder),
:mod:`.layout` (image circles and crops), :mod:`.photometric` (white gains),
:mod:`.geometric` (warp maps), :mod:`.parallax` (``o_i`` and ``Z_c``), then
:mod:`.calibrate` composes them and :mod:`.report` draws the report;
:mod:`.file` is the :class:`Calibration` type and its ``.lfcal`` file, :mod:`.zoom`
calibrates a zoom lens's settings into one file, :mod:`.settings` holds a file's
settings together and picks one per capture, and :mod:`.pattern` the digital pattern
shown on the board.
"""

from .calibrate import CalibrationParams, CalibrationRun, calibrate, run_calibration
from .file import FORMAT_NAME, FORMAT_VERSION, Calibration, info, load_settings, save_settings
from .inputs import CalibrationInputs, find_inputs, find_settings
from .pattern import make_pattern, procedural_texture
from .settings import SettingChoice, ZoomCalibration
from .zoom import ZoomRun, run_zoom_calibration

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Calibration",
    "CalibrationInputs",
    "CalibrationParams",
    "CalibrationRun",
    "SettingChoice",
    "ZoomCalibration",
    "ZoomRun",
    "calibrate",
    "find_inputs",
    "find_settings",
    "info",
    "load_settings",
    "make_pattern",
    "procedural_texture",
    "run_calibration",
    "run_zoom_calibration",
    "save_settings",
]
