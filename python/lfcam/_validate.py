"""Argument checks that coerce an argument or raise :class:`~lfcam.InputError` naming it.

Only the first layer of validation: the bindings check dtype, contiguity and shape
again, and the Rust core re-checks sizes. Everything here is cheap except the single,
documented copy of a non-C-contiguous image.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import DTypeLike, NDArray

from lfcam.errors import InputError

__all__ = ["as_image", "as_int_array", "check_instance", "check_path", "check_positive_int"]


def _dtype_list(dtypes: Sequence[np.dtype[Any]]) -> str:
    return ", ".join(str(d) for d in dtypes)


def as_image(
    image: Any,
    name: str,
    *,
    dtypes: Sequence[DTypeLike],
    ndims: Sequence[int] = (2, 3),
) -> NDArray[Any]:
    """Return ``image`` as a non-empty, C-contiguous ndarray of one of ``dtypes``.

    Parameters
    ----------
    image : array_like
        ``(H, W)`` or ``(H, W, C)`` image (as restricted by ``ndims``).
    name : str
        The argument's name, for error messages.
    dtypes : sequence of dtype-like
        Accepted dtypes; no conversion between dtypes is made.
    ndims : sequence of int, optional
        Accepted numbers of dimensions.

    Returns
    -------
    numpy.ndarray
        ``image`` itself if it already is a C-contiguous ndarray, else one copy
        (``numpy.ascontiguousarray``).

    Raises
    ------
    InputError
        If ``image`` is not array-like, has another dtype or number of dimensions, or
        is empty.
    """
    allowed = [np.dtype(d) for d in dtypes]
    try:
        arr = np.asarray(image)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: cannot be converted to an array ({e})") from e
    if arr.dtype not in allowed:
        raise InputError(
            f"{name}: dtype {arr.dtype} is not supported; expected one of {_dtype_list(allowed)}"
        )
    if arr.ndim not in ndims:
        shapes = " or ".join({2: "(H, W)", 3: "(H, W, C)"}.get(n, f"{n}-D") for n in ndims)
        raise InputError(
            f"{name}: expected a {shapes} image, got {arr.ndim} dimensions, shape {arr.shape}"
        )
    if arr.size == 0:
        raise InputError(f"{name}: image is empty, shape {arr.shape}")
    return np.ascontiguousarray(arr)


def as_int_array(
    values: Any,
    name: str,
    *,
    shape: Sequence[int | None],
) -> NDArray[np.int64]:
    """Return ``values`` as a C-contiguous int64 array of the given ``shape``.

    Parameters
    ----------
    values : array_like of int
        Integers (any integer dtype; booleans and floats are refused, even if whole).
    name : str
        The argument's name, for error messages.
    shape : sequence of int or None
        Expected shape; ``None`` matches any length along that axis.

    Returns
    -------
    numpy.ndarray of int64

    Raises
    ------
    InputError
        If ``values`` is not an integer array of that shape, or does not fit in int64.
    """
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: cannot be converted to an array ({e})") from e
    expected = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
    if arr.dtype.kind not in "iu":
        raise InputError(f"{name}: expected integers of shape {expected}, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        raise InputError(f"{name}: expected shape {expected}, got {arr.shape}")
    if arr.dtype == np.uint64 and arr.size and int(arr.max()) > np.iinfo(np.int64).max:
        raise InputError(f"{name}: values do not fit in int64")
    return np.ascontiguousarray(arr, dtype=np.int64)


def check_positive_int(value: Any, name: str, *, minimum: int = 1) -> int:
    """Return ``value`` as an ``int`` if it is an integer >= ``minimum``.

    Raises
    ------
    InputError
        If ``value`` is not an integer (booleans and floats are refused) or is
        smaller than ``minimum``.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise InputError(f"{name}: expected an integer >= {minimum}, got {value}")
    return int(value)


def check_instance(value: Any, cls: type, name: str) -> None:
    """Raise :class:`~lfcam.InputError` naming ``name`` unless ``value`` is a ``cls``.

    For arguments such as ``cal`` whose attributes are used at once: without it a
    ``None`` surfaces as an ``AttributeError`` deep inside.
    """
    if not isinstance(value, cls):
        raise InputError(f"{name}: expected a {cls.__name__}, got {type(value).__name__}")


def check_path(value: Any, name: str) -> None:
    """Raise :class:`~lfcam.InputError` naming ``name`` unless ``value`` is a str or path."""
    if not isinstance(value, (str, os.PathLike)):
        raise InputError(f"{name}: expected a file path, got {value!r}")
