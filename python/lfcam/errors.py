"""Exceptions raised by lfcam.

Every error lfcam raises on purpose is an :class:`LfcamError`, so ``except
lfcam.LfcamError`` catches all of them. Bad arguments raise :class:`InputError`, which
is also a :class:`ValueError`, so code written for the usual Python convention keeps
working. The Rust core's errors are mapped onto these classes one variant at a time.
"""

from __future__ import annotations

__all__ = ["CalibrationError", "InputError", "LfcamError", "LfcamWarning", "NumericalError"]


class LfcamError(Exception):
    """Base class of every exception lfcam raises on purpose.

    Also raised, with a message starting ``internal error in``, when the Rust core
    hits a bug (a panic); please report those.
    """


class InputError(LfcamError, ValueError):
    """An argument is unusable: wrong type, dtype, shape or value.

    The message starts with the argument's name, and for one bad element of a
    sequence, its index: ``"rects[3]: rectangle ... lies outside the 1920x1080 frame"``.

    Examples
    --------
    >>> import numpy as np, lfcam
    >>> try:
    ...     lfcam.crop_lenslets(np.zeros((4, 4), np.float64), [[0, 0, 2, 2]])
    ... except ValueError as e:
    ...     print(e)
    raw: dtype float64 is not supported; expected one of uint8, uint16, float32
    """


class CalibrationError(LfcamError):
    """Calibration data is missing, inconsistent with the input, or unusable."""


class NumericalError(LfcamError, ArithmeticError):
    """A numerical procedure failed: a singular system, no convergence, or a
    non-finite result."""


class LfcamWarning(UserWarning):
    """Something lfcam did but could not check or do as well as usual, for example a
    calibration file of an older format without checksums, or a result with little
    coverage."""
