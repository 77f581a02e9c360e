"""Robust statistics over stacks of images or maps (e.g. calibration maps measured on
several captures)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lfcam._lfcam as _lfcam
from lfcam.errors import InputError

__all__ = ["nan_median"]


def nan_median(
    stack: ArrayLike, axis: int = 0
) -> tuple[NDArray[np.float32], NDArray[np.unsignedinteger[Any]]]:
    """Per-element median of a float32 stack along one axis, ignoring NaN, and the count.

    The robust average of calibration maps over captures: equal to
    ``numpy.nanmedian(stack, axis)`` (for an even count, the float32 mean of the two
    middle values), but in parallel in Rust, without numpy's all-NaN warning, and
    with the number of values each median was taken over.

    Parameters
    ----------
    stack : array_like of float32, shape (..., K, ...)
        ``K >= 1`` values per element along ``axis``. Other dtypes are refused (convert
        with ``.astype(numpy.float32)``). If ``axis`` is not 0 or the array is not
        C-contiguous, it is copied once.
    axis : int, optional
        The axis to reduce (negative counts from the end). Default 0.

    Returns
    -------
    median : numpy.ndarray of float32
        Shape of ``stack`` without ``axis`` (0-d for a 1-D stack). NaN where every
        value is NaN.
    count : numpy.ndarray of uint8 (K <= 255) or uint16 (K <= 65535)
        Same shape: the number of non-NaN values (``numpy.isfinite`` for stacks without
        infinities; infinities count, as ``numpy.nanmedian`` keeps them).

    Raises
    ------
    InputError
        If ``stack`` is not float32, is 0-d, has ``K = 0`` or ``K > 65535``, or if
        ``axis`` is out of range. ``InputError`` is a ``ValueError``.

    See Also
    --------
    numpy.nanmedian

    Examples
    --------
    >>> import numpy as np
    >>> import lfcam
    >>> stack = np.array([[1, np.nan, np.nan], [3, 2, np.nan], [2, 4, np.nan]], np.float32)
    >>> median, count = lfcam.nan_median(stack)
    >>> median
    array([ 2.,  3., nan], dtype=float32)
    >>> count
    array([3, 2, 0], dtype=uint8)
    """
    try:
        arr = np.asarray(stack)
    except (TypeError, ValueError) as e:
        raise InputError(f"stack: cannot be converted to an array ({e})") from e
    if arr.dtype != np.float32:
        raise InputError(
            f"stack: expected float32, got dtype {arr.dtype} (convert with .astype(numpy.float32))"
        )
    if arr.ndim == 0:
        raise InputError("stack: expected at least 1 dimension, got a 0-d array")
    if isinstance(axis, (bool, np.bool_)) or not isinstance(axis, (int, np.integer)):
        raise InputError(f"axis: expected an integer, got {axis!r}")
    if not -arr.ndim <= axis < arr.ndim:
        raise InputError(f"axis: {axis} is out of range for a {arr.ndim}-D stack")
    k = arr.shape[axis]
    if k == 0:
        raise InputError(f"stack: has no values along axis {axis} (K = 0), shape {arr.shape}")
    if k > np.iinfo(np.uint16).max:
        raise InputError(f"stack: K = {k} values per element; at most 65535 are supported")
    arr = np.ascontiguousarray(np.moveaxis(arr, axis, 0))
    median, count = _lfcam.nan_median(arr)
    return median, count
