"""Cutting the lenslet sub-images ("views") out of a raw frame."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lfcam._lfcam as _lfcam
from lfcam._validate import as_image, as_int_array

__all__ = ["crop_lenslets"]

_DTYPES = (np.uint8, np.uint16, np.float32)


def crop_lenslets(raw: ArrayLike, rects: ArrayLike) -> NDArray[Any]:
    """Crop equally sized rectangles (one per lenslet view) out of a raw frame.

    Equivalent to ``np.stack([raw[y0:y0+h, x0:x0+w] for x0, y0, w, h in rects])``,
    but checked, run in parallel in Rust with the GIL released, and without the
    intermediate copies.

    Parameters
    ----------
    raw : array_like, shape (H, W) or (H, W, C)
        The raw sensor frame, uint8, uint16 or float32 (no dtype conversion is made).
        A non-C-contiguous array (a transposed or strided view) is first copied once
        with ``numpy.ascontiguousarray``; a C-contiguous one is read in place.
    rects : array_like of int, shape (N, 4)
        One row ``(x0, y0, w, h)`` per view, in raw pixels: ``x0`` is the column and
        ``y0`` the row of the top-left pixel. All rectangles must have the same
        ``(w, h)`` and lie inside the frame.

    Returns
    -------
    views : numpy.ndarray, shape (N, h, w) or (N, h, w, C)
        A new C-contiguous array of ``raw``'s dtype; ``views[i]`` is view ``i``.

    Raises
    ------
    InputError
        If ``raw`` has another dtype or number of dimensions or is empty; if ``rects``
        is not an ``(N, 4)`` integer array or is empty; if a rectangle lies outside
        the frame, is empty, or differs in size from ``rects[0]`` (the message names
        its index, e.g. ``rects[3]: ...``). ``InputError`` is a ``ValueError``.

    See Also
    --------
    numpy.stack

    Examples
    --------
    >>> import numpy as np
    >>> import lfcam
    >>> raw = np.arange(4 * 6, dtype=np.uint8).reshape(4, 6)
    >>> views = lfcam.crop_lenslets(raw, [[0, 0, 3, 2], [3, 2, 3, 2]])
    >>> views.shape
    (2, 2, 3)
    >>> views[1]
    array([[15, 16, 17],
           [21, 22, 23]], dtype=uint8)
    """
    raw_arr = as_image(raw, "raw", dtypes=_DTYPES)
    rects_arr = as_int_array(rects, "rects", shape=(None, 4))
    return _lfcam.crop_lenslets(raw_arr, rects_arr)
