"""Calibration: once per camera (and zoom setting), a folder of captures becomes a
:class:`Calibration`.

One module per step, in the order they run: :mod:`.inputs` (the folder),
:mod:`.layout` (image circles and crops), :mod:`.photometric` (white gains),
:mod:`.geometric` (warp maps), :mod:`.parallax` (``o_i`` and ``Z_c``), then
:mod:`.calibrate` composes them and :mod:`.report` draws the report;
:mod:`.file` is the :class:`Calibration` type and its ``.lfcal`` file, and
:mod:`.pattern` the digital pattern shown on the board.
"""

from .calibrate import CalibrationParams, CalibrationRun, calibrate, run_calibration
from .file import FORMAT_NAME, FORMAT_VERSION, Calibration, info
from .inputs import CalibrationInputs, find_inputs
from .pattern import make_pattern, procedural_texture

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Calibration",
    "CalibrationInputs",
    "CalibrationParams",
    "CalibrationRun",
    "calibrate",
    "find_inputs",
    "info",
    "make_pattern",
    "procedural_texture",
    "run_calibration",
]
