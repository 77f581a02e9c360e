"""Warp maps applied to images: bilinear remap, and rectification of raw frames.

Maps follow OpenCV: float32 ``(H', W', 2)`` arrays of positions ``(x, y)``, ``x`` the
column. Pixel centres are at integer coordinates. Samples that have no data (a NaN
position, a footprint leaving the image, a masked pixel) are NaN, never extrapolated.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lfcam._lfcam as _lfcam
from lfcam._validate import as_image, as_int_array
from lfcam.errors import InputError

__all__ = [
    "INTERPOLATIONS",
    "Interp",
    "RectifyPlan",
    "identity_grid",
    "rectify",
    "remap",
    "remap_bilinear",
]

Interp = Literal["bilinear", "bilinear-exact", "bilinear-q32", "bicubic"]

#: The interpolation methods :func:`rectify` accepts.
INTERPOLATIONS: tuple[Interp, ...] = ("bilinear", "bilinear-exact", "bilinear-q32", "bicubic")

_RAW_DTYPES = (np.uint8, np.uint16, np.float32)
_MAX_CHANNELS = 4


def _as_float32(values: Any, name: str, shape: Sequence[int | str]) -> NDArray[np.float32]:
    """``values`` as a C-contiguous float32 array of ``shape`` (ints are fixed sizes,
    strings name free ones), or :class:`InputError` naming ``name``."""
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: cannot be converted to an array ({e})") from e
    expected = "(" + ", ".join(str(s) for s in shape) + ")"
    if arr.dtype != np.float32:
        raise InputError(
            f"{name}: expected float32 of shape {expected}, got dtype {arr.dtype} "
            "(convert with .astype(numpy.float32))"
        )
    if arr.ndim != len(shape) or any(
        isinstance(s, int) and s != n for s, n in zip(shape, arr.shape)
    ):
        raise InputError(f"{name}: expected shape {expected}, got {arr.shape}")
    if arr.size == 0:
        raise InputError(f"{name}: is empty, shape {arr.shape}")
    return np.ascontiguousarray(arr)


def _check_out(out: Any, shape: tuple[int, ...]) -> NDArray[np.float32] | None:
    """``out`` if it is a writeable, C-contiguous float32 array of ``shape``."""
    if out is None:
        return None
    if not isinstance(out, np.ndarray):
        raise InputError(f"out: expected a numpy.ndarray, got {type(out).__name__}")
    if out.dtype != np.float32 or out.shape != shape:
        raise InputError(f"out: expected float32 of shape {shape}, got {out.dtype} {out.shape}")
    if not out.flags.c_contiguous or not out.flags.writeable:
        raise InputError("out: must be C-contiguous and writeable")
    return out


def _check_channels(image: NDArray[Any], name: str) -> None:
    if image.ndim == 3 and image.shape[2] > _MAX_CHANNELS:
        raise InputError(
            f"{name}: has {image.shape[2]} channels; 1 to {_MAX_CHANNELS} are supported"
        )


def _check_maps(
    crops: ArrayLike, warps: ArrayLike, masks: ArrayLike | None
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.uint8] | None]:
    """``crops``, ``warps`` and ``masks`` as the bindings take them (masks as bytes)."""
    crops_arr = as_int_array(crops, "crops", shape=(None, 4))
    warps_arr = _as_float32(warps, "warps", ("N", "H", "W", 2))
    n, h, w = warps_arr.shape[:3]
    if len(crops_arr) != n:
        raise InputError(
            f"crops: has {len(crops_arr)} rectangles but warps has {n} views; one rectangle "
            "per view is needed"
        )
    masks_arr = None
    if masks is not None:
        m = np.asarray(masks)
        if m.dtype != np.bool_:
            raise InputError(f"masks: expected bool, got dtype {m.dtype}")
        if m.shape != (n, h, w):
            raise InputError(
                f"masks: shape {m.shape} differs from the warps' (N, H, W) = {(n, h, w)}"
            )
        # The bindings read masks as bytes (a bool array is one byte per element).
        masks_arr = np.ascontiguousarray(m).view(np.uint8)
    return crops_arr, warps_arr, masks_arr


def _check_interp(interp: Any, allowed: Sequence[str]) -> None:
    if not isinstance(interp, str) or interp not in allowed:
        choices = ", ".join(repr(i) for i in allowed)
        raise InputError(f"interp: expected one of {choices}, got {interp!r}")


def _check_views(views: ArrayLike | None, n: int) -> NDArray[np.int64] | None:
    """``views`` as int64 indices into ``n`` views, or None (all)."""
    if views is None:
        return None
    views_arr = as_int_array(views, "views", shape=(None,))
    bad = np.flatnonzero((views_arr < 0) | (views_arr >= n))
    if bad.size:
        j = int(bad[0])
        raise InputError(
            f"views[{j}]: view index {int(views_arr[j])} is out of range for {n} views"
        )
    return views_arr


def remap_bilinear(
    src: ArrayLike, map: ArrayLike, *, out: NDArray[np.float32] | None = None
) -> NDArray[np.float32]:
    """Sample an image (or a map) at the positions of a map, with exact bilinear weights.

    Output pixel ``(r, c)`` is ``src`` interpolated at ``(x, y) = map[r, c]``. The weights
    come from the true fractional position, in float32 (OpenCV >= 4.11 computes
    ``cv2.remap(src, map, None, cv2.INTER_LINEAR)`` the same way for 1-, 3- and
    4-channel images; for 2-channel images, such as maps, OpenCV still rounds positions
    to 1/32 pixel). With a ``(H, W, 2)`` map as ``src`` this composes maps:
    ``remap_bilinear(a, b)[r, c]`` is ``a`` at the position ``b[r, c]``.

    A sample is NaN in every channel when its map entry is NaN, when its footprint
    (the source pixels with non-zero weight: 2 x 2, or fewer on whole-number positions)
    is not entirely inside ``src``, or when a value in the footprint is NaN. A position
    exactly on the last row or column therefore still has a value.

    Parameters
    ----------
    src : array_like of float32, shape (H, W) or (H, W, C)
        The image or map to sample, ``C <= 4``. A non-C-contiguous array is copied
        once.
    map : array_like of float32, shape (H', W', 2)
        Positions ``(x, y)`` in ``src``, ``x`` the column; pixel centres at integers.
    out : numpy.ndarray of float32, optional
        Written instead of a new array: C-contiguous, of the output's shape, sharing no
        memory with the inputs. Reusing one saves the page faults of a fresh output.

    Returns
    -------
    numpy.ndarray of float32, shape (H', W') or (H', W', C)
        A new array (or ``out``), 2-D if ``src`` is.

    Raises
    ------
    InputError
        If ``src`` or ``map`` is not float32, has the wrong number of dimensions or
        channels, or is empty. ``InputError`` is a ``ValueError``.

    See Also
    --------
    rectify : the fused gain, crop and remap of raw frames.
    cv2.remap

    Examples
    --------
    >>> import numpy as np
    >>> import lfcam
    >>> src = np.array([[0, 1, 2], [3, 4, 5]], dtype=np.float32)
    >>> map = np.array([[[0.5, 0.5], [2.0, 0.25], [2.5, 0.0]]], dtype=np.float32)
    >>> lfcam.remap_bilinear(src, map)
    array([[2.  , 2.75,  nan]], dtype=float32)
    """
    src_arr = as_image(src, "src", dtypes=(np.float32,))
    _check_channels(src_arr, "src")
    map_arr = _as_float32(map, "map", ("H'", "W'", 2))
    out_arr = _check_out(out, map_arr.shape[:2] + src_arr.shape[2:])
    return _lfcam.remap_bilinear(src_arr, map_arr, out_arr)


def remap(src: np.ndarray, warp: np.ndarray) -> np.ndarray:
    """Bilinear sampling of ``src`` (H, W[, C]) at ``warp`` (H', W', 2); NaN outside.

    :func:`remap_bilinear` after converting both to C-contiguous float32: a sample is
    NaN when its 2x2 footprint leaves ``src`` or touches a NaN.
    """
    return remap_bilinear(
        np.ascontiguousarray(src, np.float32), np.ascontiguousarray(warp, np.float32)
    )


def identity_grid(h: int, w: int) -> NDArray[np.float32]:
    """``(h, w, 2)`` float32 map of every pixel's own coordinates ``(x, y)``: the map
    that :func:`remap_bilinear` leaves an image unchanged with."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([xx, yy], -1)


def rectify(
    raw: ArrayLike,
    gains: ArrayLike,
    crops: ArrayLike,
    warps: ArrayLike,
    masks: ArrayLike | None = None,
    *,
    interp: Interp = "bilinear",
    views: ArrayLike | None = None,
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """Rectify the views of a raw frame: gain, crop and remap in one parallel pass.

    For view ``i`` and rectified pixel ``(u, v)`` the raw position is ``(x, y) =
    warps[i, v, u] + (x0_i, y0_i)``, and the output is ``raw * scale * gains``
    interpolated there (``scale`` is 1/255 for uint8, 1/65535 for uint16, 1 for
    float32), computed without materialising any intermediate image. With
    ``interp="bilinear"`` this equals, within 1e-5 wherever both are defined::

        g = raw.astype(np.float32) * scale * gains
        x0, y0, w, h = crops[i]
        cv2.remap(g[y0:y0 + h, x0:x0 + w], warps[i], None, cv2.INTER_LINEAR)

    The output is NaN in every channel where ``masks[i, v, u]`` is False, the warp is
    NaN, the interpolation footprint (the raw pixels with non-zero weight) leaves the
    crop rectangle ``crops[i]``, or a gain in the footprint is 0 (a pixel the
    photometric calibration masked) or NaN. OpenCV instead fills such places with 0 or
    with values from outside the crop.

    Parameters
    ----------
    raw : array_like, shape (H_raw, W_raw) or (H_raw, W_raw, C)
        The raw frame, uint8, uint16 or float32, ``C <= 4`` (Bayer frames are
        demosaiced first). Not converted; a non-C-contiguous array is copied once.
    gains : array_like of float32, shape (H_raw, W_raw) or (H_raw, W_raw, G)
        Per-pixel gains (photometric calibration), ``G`` 1 or ``C``. One channel
        applies to every channel of ``raw`` (an RGB raw with mono gains is
        vignetting-only correction); a mono raw with 3-channel gains is an error.
    crops : array_like of int, shape (N, 4)
        View ``i``'s rectangle ``(x0, y0, w, h)`` in raw pixels, inside the frame.
        Rectangles may differ in size.
    warps : array_like of float32, shape (N, H_rect, W_rect, 2)
        For each view, the position ``(x, y)`` relative to its crop that each
        rectified pixel samples; NaN for none.
    masks : array_like of bool, shape (N, H_rect, W_rect), optional
        False where a view has no data. Default: everywhere True.
    interp : {"bilinear", "bilinear-exact", "bilinear-q32", "bicubic"}, optional
        ``"bilinear"`` (default) computes what ``cv2.remap`` with ``cv2.INTER_LINEAR``
        computes from float maps in OpenCV >= 4.11 (including 5.0): true sub-pixel
        positions, float32 in OpenCV's order of operations. ``"bilinear-exact"``
        (bilinear at the true position, as :func:`remap_bilinear`) is therefore the
        same. ``"bilinear-q32"`` rounds positions to 1/32 pixel and uses OpenCV's
        weight table, as ``cv2.remap`` did before 4.11 (and still does for 2-channel
        images or fixed-point maps from ``cv2.convertMaps``). ``"bicubic"`` is what
        ``cv2.INTER_CUBIC`` computes on float32 images in OpenCV 5.0: Keys' kernel with
        a = -0.75 at the true position on a 4 x 4 footprint (within 1e-5 of OpenCV).
    views : array_like of int, shape (M,), optional
        Indices of the views to rectify, in output order (repeats allowed). Default:
        all ``N``.
    out : numpy.ndarray of float32, optional
        Written instead of a new array: C-contiguous, of the output's shape, sharing no
        memory with the inputs. Processing many captures, reusing one saves the page
        faults of a fresh output (a third of the time at 12 x 2000 x 1350 x 3).

    Returns
    -------
    numpy.ndarray of float32, shape (M, H_rect, W_rect) or (M, H_rect, W_rect, C)
        A new array (or ``out``): ``[j]`` is view ``views[j]``; 3-D for a 2-D ``raw``.

    Raises
    ------
    InputError
        Naming the argument: wrong dtype or number of dimensions; ``gains`` of another
        ``(H, W)`` than ``raw`` or with an unusable channel count; ``crops``, ``warps``
        and ``masks`` disagreeing on ``N`` (or ``masks`` on ``(H, W)``); a crop outside
        the raw frame or empty (``crops[3]: ...``); a view index out of range
        (``views[0]: ...``); an unknown ``interp``. ``InputError`` is a ``ValueError``.

    See Also
    --------
    RectifyPlan : the same, prepared once per calibration (bilinear): much faster for
        many captures.
    remap_bilinear, crop_lenslets

    Examples
    --------
    >>> import numpy as np
    >>> import lfcam.kernels.warp
    >>> raw = np.arange(12, dtype=np.uint8).reshape(3, 4) * 10
    >>> gains = np.full((3, 4), 2.0, dtype=np.float32)
    >>> crops = [[2, 0, 2, 3]]  # the right half
    >>> warps = np.array([[[[0.5, 0.0], [1.0, 0.5], [1.5, 0.0]]]], dtype=np.float32)
    >>> out = lfcam.kernels.warp.rectify(raw, gains, crops, warps)
    >>> out.shape
    (1, 1, 3)
    >>> np.round(out * 255 / 2, 3)
    array([[[25., 50., nan]]], dtype=float32)
    """
    raw_arr = as_image(raw, "raw", dtypes=_RAW_DTYPES)
    _check_channels(raw_arr, "raw")
    gains_arr = as_image(gains, "gains", dtypes=(np.float32,))
    if gains_arr.shape[:2] != raw_arr.shape[:2]:
        raise InputError(
            f"gains: (H, W) = {gains_arr.shape[:2]} differs from raw's {raw_arr.shape[:2]}"
        )
    channels = raw_arr.shape[2] if raw_arr.ndim == 3 else 1
    gain_channels = gains_arr.shape[2] if gains_arr.ndim == 3 else 1
    if gain_channels not in (1, channels):
        raise InputError(
            f"gains: has {gain_channels} channels but raw has {channels}; gains need 1 "
            f"channel (shared by every channel of raw) or {channels}"
        )
    crops_arr, warps_arr, masks_arr = _check_maps(crops, warps, masks)
    n, h, w = warps_arr.shape[:3]
    _check_interp(interp, INTERPOLATIONS)
    views_arr = _check_views(views, n)
    n_out = n if views_arr is None else len(views_arr)
    out_arr = _check_out(out, (n_out, h, w, *raw_arr.shape[2:]))
    return _lfcam.rectify(
        raw_arr, gains_arr, crops_arr, warps_arr, masks_arr, interp, views_arr, out_arr
    )


class RectifyPlan:
    """Rectification prepared once per calibration, for many raw frames.

    Everything :func:`rectify` derives from the gains, crops, warps and masks alone is
    derived here once: for every view and rectified row the runs of pixels that have a
    value, and for each such pixel its footprint and fractions; the gains of the raw
    pixels that footprints read are copied. A capture's :meth:`rectify` is then one
    streaming pass (gain, interpolate, NaN-fill the rest) with no map arithmetic and no
    work on the pixels without data beyond writing NaN. Its output equals
    :func:`rectify`'s with the same arguments, bit for bit.

    The plan copies what it needs (about 12 bytes per rectified pixel with a value, plus
    the gains that footprints read): changing the arrays afterwards does not change it.
    Prepare a new plan for a new calibration.

    Parameters
    ----------
    gains : array_like of float32, shape (H_raw, W_raw) or (H_raw, W_raw, G)
        Per-pixel gains, as for :func:`rectify`; they fix the raw frame's size.
    crops : array_like of int, shape (N, 4)
        View ``i``'s rectangle ``(x0, y0, w, h)`` in raw pixels, inside the frame.
    warps : array_like of float32, shape (N, H_rect, W_rect, 2)
        Crop-relative positions ``(x, y)`` to sample; NaN for none.
    masks : array_like of bool, shape (N, H_rect, W_rect), optional
        False where a view has no data. Default: everywhere True.
    interp : {"bilinear", "bilinear-exact"}, optional
        As for :func:`rectify` (both are OpenCV's ``INTER_LINEAR``). For the other
        methods, call :func:`rectify`.

    Raises
    ------
    InputError
        Naming the argument, as :func:`rectify` (``crops[3]: ...``), and for an
        ``interp`` other than the two above. ``InputError`` is a ``ValueError``.

    See Also
    --------
    rectify, lfcam.rectify : the calibration's plan is built on first use and cached.

    Examples
    --------
    >>> import numpy as np
    >>> import lfcam.kernels.warp
    >>> raw = np.arange(12, dtype=np.uint8).reshape(3, 4) * 10
    >>> gains = np.full((3, 4), 2.0, dtype=np.float32)
    >>> warps = np.array([[[[0.5, 0.0], [1.0, 0.5], [1.5, 0.0]]]], dtype=np.float32)
    >>> plan = lfcam.kernels.warp.RectifyPlan(gains, [[2, 0, 2, 3]], warps)
    >>> plan
    RectifyPlan(n_views=1, shape=(1, 3), raw_shape=(3, 4), kept=2)
    >>> np.round(plan.rectify(raw) * 255 / 2, 3)
    array([[[25., 50., nan]]], dtype=float32)
    """

    def __init__(
        self,
        gains: ArrayLike,
        crops: ArrayLike,
        warps: ArrayLike,
        masks: ArrayLike | None = None,
        *,
        interp: Interp = "bilinear",
    ) -> None:
        gains_arr = as_image(gains, "gains", dtypes=(np.float32,))
        _check_channels(gains_arr, "gains")
        crops_arr, warps_arr, masks_arr = _check_maps(crops, warps, masks)
        _check_interp(interp, ("bilinear", "bilinear-exact"))
        self.interp: Interp = interp
        self._plan = _lfcam.RectifyPlan(gains_arr, crops_arr, warps_arr, masks_arr, interp)

    @property
    def n_views(self) -> int:
        """Number of views ``N``."""
        return self._plan.n_views

    @property
    def shape(self) -> tuple[int, int]:
        """The rectified frame's ``(H_rect, W_rect)``."""
        return self._plan.shape

    @property
    def raw_shape(self) -> tuple[int, int]:
        """The raw frames' ``(H_raw, W_raw)`` (the gains')."""
        return self._plan.raw_shape

    @property
    def gain_channels(self) -> int:
        """Channels of the gains: 1 (shared by every channel of raw) or raw's."""
        return self._plan.gain_channels

    @property
    def kept(self) -> int:
        """Rectified pixels with a value, over all views."""
        return self._plan.kept

    @property
    def nbytes(self) -> int:
        """Bytes of memory the plan holds."""
        return self._plan.nbytes

    def __repr__(self) -> str:
        return (
            f"RectifyPlan(n_views={self.n_views}, shape={self.shape}, "
            f"raw_shape={self.raw_shape}, kept={self.kept})"
        )

    def rectify(
        self,
        raw: ArrayLike,
        *,
        views: ArrayLike | None = None,
        out: NDArray[np.float32] | None = None,
    ) -> NDArray[np.float32]:
        """Rectify the views of a raw frame with this plan.

        Parameters
        ----------
        raw : array_like, shape (H_raw, W_raw) or (H_raw, W_raw, C)
            The raw frame, uint8, uint16 or float32, ``C <= 4``, of the plan's
            :attr:`raw_shape`; ``C`` equal to :attr:`gain_channels` unless that is 1.
            Not converted; a non-C-contiguous array is copied once.
        views : array_like of int, shape (M,), optional
            Indices of the views to rectify, in output order (repeats allowed).
            Default: all ``N``.
        out : numpy.ndarray of float32, optional
            Written instead of a new array: C-contiguous, of the output's shape, sharing
            no memory with ``raw``.

        Returns
        -------
        numpy.ndarray of float32, shape (M, H_rect, W_rect) or (M, H_rect, W_rect, C)
            As :func:`rectify` with the plan's arguments: ``[j]`` is view ``views[j]``,
            NaN where it has no data; 3-D for a 2-D ``raw``.

        Raises
        ------
        InputError
            Naming the argument: ``raw`` of the wrong dtype, size or channel count,
            a view index out of range (``views[0]: ...``), an unusable ``out``.
        """
        raw_arr = as_image(raw, "raw", dtypes=_RAW_DTYPES)
        _check_channels(raw_arr, "raw")
        if raw_arr.shape[:2] != self.raw_shape:
            raise InputError(
                f"raw: (H, W) = {raw_arr.shape[:2]} differs from the plan's {self.raw_shape} "
                "(the gains' it was prepared with)"
            )
        channels = raw_arr.shape[2] if raw_arr.ndim == 3 else 1
        if self.gain_channels not in (1, channels):
            raise InputError(
                f"raw: has {channels} channels but the plan's gains have "
                f"{self.gain_channels}; gains need 1 channel (shared by every channel of "
                "raw) or as many as raw"
            )
        views_arr = _check_views(views, self.n_views)
        n_out = self.n_views if views_arr is None else len(views_arr)
        out_arr = _check_out(out, (n_out, *self.shape, *raw_arr.shape[2:]))
        return self._plan.rectify(raw_arr, views_arr, out_arr)
