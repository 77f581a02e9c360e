"""Super-resolution from the raw samples (docs/design.md, "Super-resolution"; paper section
5.2; Farsiu, Robinson, Elad, Milanfar 2003 and 2004).

Super-resolution never fuses rectified (already interpolated) pixels: every raw sample
of every view is placed at its sub-pixel position in the reference view's rectified
frame, by inverting the view's warp map (raw -> its rectified position ``q``) and
undoing the parallax (``p + o_i s(p) = q``, docs/design.md, "Plane and parallax"). The samples are
fused on an ``r``-times finer grid by a robust (L1-like, reweighted) shift-and-add,
holes are filled, and the result is deblurred with bilateral-TV regularisation. All
per-sample and per-pixel work runs in the Rust core with the GIL released.

Pixel centres: fine pixel ``U`` sits at rectified ``(U + 0.5) / r - 0.5``.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

import lfcam._lfcam as _lfcam

from .._validate import as_int_array, check_instance
from ..calibration import Calibration
from ..errors import InputError
from ..io import demosaic
from ..processing import DepthResult

__all__ = [
    "SuperResParams",
    "fill_holes",
    "inverse_maps",
    "place_raw_samples",
    "raw_samples",
    "shift_and_add",
    "super_resolve",
]

_SCALE = {np.dtype(np.uint8): 1 / 255, np.dtype(np.uint16): 1 / 65535, np.dtype(np.float32): 1.0}


@dataclass(frozen=True)
class SuperResParams:
    """Tuning of :func:`super_resolve` (defaults tuned on the simulator, 2x; why each
    has its value: docs/tuning.md, "Super-resolution and refocus").

    Attributes
    ----------
    kernel_sigma : float
        Gaussian splat kernel of the shift-and-add, fine px.
    kernel_radius : int
        Splat kernel radius, fine px.
    robust_iterations : int
        Reweighting passes of the robust shift-and-add.
    huber : float
        Residual (image units, mean over channels) beyond which a sample's weight
        falls as ``huber / residual`` (an L1 fit).
    reject : float
        Residual beyond which a sample is dropped (occlusions, mismatched samples).
    place_iterations : int
        Fixed-point iterations of ``p = q - o_i s(p)``.
    place_tolerance : float
        Largest ``|p + o_i s(p) - q|`` accepted, rectified px.
    psf_sigma : float
        The camera's blur (optics and pixel), rectified px, as a Gaussian sigma.
    deblur_iterations : int
        BTV steepest-descent iterations (0: no deblurring).
    lam : float
        BTV regularisation weight.
    alpha : float
        BTV spatial decay.
    window : int
        BTV window ``P``.
    step : float
        Steepest-descent step.
    eps : float
        Smoothing of the sign function, image units.
    """

    kernel_sigma: float = 0.4
    kernel_radius: int = 1
    robust_iterations: int = 1
    huber: float = 0.015
    reject: float = 0.15
    place_iterations: int = 6
    place_tolerance: float = 0.25
    psf_sigma: float = 0.55
    deblur_iterations: int = 15
    lam: float = 0.015
    alpha: float = 0.7
    window: int = 1
    step: float = 0.02
    eps: float = 0.01

    def __post_init__(self) -> None:
        for name, lo, hi in _INT_RANGES:
            value = getattr(self, name)
            if (
                isinstance(value, (bool, np.bool_))
                or not isinstance(value, (int, np.integer))
                or not lo <= value <= hi
            ):
                raise InputError(f"{name}: expected an integer from {lo} to {hi}, got {value!r}")
        for name, positive in _FLOATS:
            value = getattr(self, name)
            ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
                value, (bool, np.bool_)
            )
            if not (ok and math.isfinite(value) and (value > 0 if positive else value >= 0)):
                what = "> 0" if positive else ">= 0"
                raise InputError(f"{name}: expected a finite number {what}, got {value!r}")
        if self.alpha > 1:
            raise InputError(f"alpha: expected a number in (0, 1], got {self.alpha!r}")


# (name, smallest, largest) of SuperResParams' integers: the largest bound the work.
_INT_RANGES = (
    ("kernel_radius", 0, 16),
    ("robust_iterations", 0, 100),
    ("place_iterations", 0, 100),
    ("deblur_iterations", 0, 1000),
    ("window", 1, 8),
)
# (name, must be > 0) of SuperResParams' floats; the others must be >= 0.
_FLOATS = (
    ("kernel_sigma", True),
    ("huber", True),
    ("reject", True),
    ("place_tolerance", True),
    ("psf_sigma", False),
    ("lam", False),
    ("alpha", True),
    ("step", True),
    ("eps", True),
)


# Inverse maps depend on the calibration only: computed once per Calibration object.
_INVERSE_CACHE: weakref.WeakKeyDictionary[
    Calibration, tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.int32]]
] = weakref.WeakKeyDictionary()


def inverse_maps(cal: Calibration) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
    """Where every raw pixel lies in its own view's rectified frame.

    Inverts each view's warp map (rectified -> raw) on its valid cells: Newton's
    method on each bilinear cell, in the Rust core, parallel over views. Cached per
    :class:`Calibration` object (recomputed if its ``warps`` array is replaced).

    Parameters
    ----------
    cal : Calibration
        The camera.

    Returns
    -------
    inv : (H_raw, W_raw, 2) float32
        Rectified ``(u, v)`` of each raw pixel centre in its view's frame; NaN where
        no valid rectified cell covers it (outside the crops, masked, baffles).
    view : (H_raw, W_raw) int32
        The view each raw pixel belongs to; -1 for none.

    Examples
    --------
    >>> inv, view = lfcam.superres.inverse_maps(cal)  # doctest: +SKIP
    """
    hit = _INVERSE_CACHE.get(cal)
    if hit is not None and hit[0] is cal.warps:
        return hit[1], hit[2]
    masks = np.ascontiguousarray(cal.masks).view(np.uint8)
    inv, view = _lfcam.invert_maps(
        np.ascontiguousarray(cal.warps, np.float32),
        masks,
        np.ascontiguousarray(cal.crops, np.int64),
        int(cal.raw_shape[0]),
        int(cal.raw_shape[1]),
    )
    _INVERSE_CACHE[cal] = (cal.warps, inv, view)
    return inv, view


def raw_samples(raw: ArrayLike, cal: Calibration) -> NDArray[np.float32]:
    """The raw frame as photometrically corrected samples, ``raw * scale * gains``.

    Parameters
    ----------
    raw : (H_raw, W_raw[, 3]) array
        uint8, uint16 or float32; a single-channel frame of a Bayer camera is
        demosaiced first.
    cal : Calibration
        The camera.

    Returns
    -------
    (H_raw, W_raw, C) float32
        In [0, 1] for white = 1; NaN where the photometric calibration masked.
    """
    arr = np.asarray(raw)
    if arr.ndim == 2 and cal.bayer is not None:
        arr = demosaic(arr, cal.bayer)
    if arr.dtype not in _SCALE:
        raise InputError(f"raw: dtype {arr.dtype} is not supported (uint8, uint16, float32)")
    if tuple(arr.shape[:2]) != tuple(cal.raw_shape):
        raise InputError(
            f"raw: frame is {arr.shape[1]}x{arr.shape[0]}, the calibration expects"
            f" {cal.raw_shape[1]}x{cal.raw_shape[0]}"
        )
    if arr.ndim not in (2, 3):
        raise InputError(f"raw: expected (H, W) or (H, W, C), got shape {arr.shape}")
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.shape[2] == 1 and cal.gains.shape[2] != 1:
        raise InputError(
            f"raw: one channel, but the calibration is of a {cal.gains.shape[2]}-channel "
            "camera (a Bayer frame needs cal.bayer)"
        )
    factors = _sample_factors(cal, arr.dtype)
    with np.errstate(invalid="ignore"):
        # One pass: arr converted to float32 times (gains * scale), NaN where gains = 0.
        out = np.multiply(arr, factors, dtype=np.float32)
    return np.ascontiguousarray(out, np.float32)


# gains * scale with NaN where the gain is 0, per Calibration object and raw dtype.
_FACTOR_CACHE: weakref.WeakKeyDictionary[
    Calibration, tuple[NDArray[np.float32], dict[np.dtype, NDArray[np.float32]]]
] = weakref.WeakKeyDictionary()


def _sample_factors(cal: Calibration, dtype: np.dtype) -> NDArray[np.float32]:
    """``gains * scale`` (float32, ``(H_raw, W_raw, C)``), NaN where ``gains == 0``: the
    factor :func:`raw_samples` multiplies the frame by. Cached per calibration object
    (recomputed if its ``gains`` array is replaced) and raw dtype."""
    hit = _FACTOR_CACHE.get(cal)
    if hit is None or hit[0] is not cal.gains:
        hit = (cal.gains, {})
        _FACTOR_CACHE[cal] = hit
    factors = hit[1].get(np.dtype(dtype))
    if factors is None:
        gains = cal.gains if cal.gains.ndim == 3 else cal.gains[..., None]
        scaled = (gains * np.float32(_SCALE[np.dtype(dtype)])).astype(np.float32)
        factors = np.where(gains == 0, np.float32(np.nan), scaled).astype(np.float32)
        hit[1][np.dtype(dtype)] = factors
    return factors


def parallax_map(
    depth: DepthResult | ArrayLike, cal: Calibration, name: str = "depth"
) -> NDArray[np.float32]:
    """The parallax ``s`` of a :class:`DepthResult` or of an ``s`` array, checked
    against the rectified frame (low-level: :func:`resolve_parallax` is the public way)."""
    s = depth.parallax if isinstance(depth, DepthResult) else np.asarray(depth)
    if s.dtype.kind not in "fiu":
        raise InputError(f"{name}: expected real numbers, got dtype {s.dtype}")
    if s.shape != tuple(cal.rect_shape):
        raise InputError(
            f"{name}: parallax of shape {s.shape} does not match the rectified frame"
            f" {tuple(cal.rect_shape)}"
        )
    return np.ascontiguousarray(s, np.float32)


def resolve_parallax(
    cal: Calibration,
    depth: DepthResult | None = None,
    *,
    parallax: ArrayLike | None = None,
    depth_m: ArrayLike | None = None,
) -> NDArray[np.float32]:
    """The parallax ``s`` map from exactly one of a depth result, ``parallax=`` or
    ``depth_m=``; an array passed as ``depth`` is refused rather than guessed.

    ``depth_m`` (metres, metric calibrations) is converted by inverting
    ``Z = Z_c + (Z_b - Z_c) / (1 - s)``: ``s = 1 - (Z_b - Z_c) / (Z - Z_c)`` (NaN for
    ``Z <= Z_c`` or unknown ``Z``).

    Examples
    --------
    The depth at the reference distance ``Z_b`` has parallax 0:

    >>> from types import SimpleNamespace
    >>> cal = SimpleNamespace(rect_shape=(1, 2), metric=True, z_b=1.0, z_c=0.05)
    >>> resolve_parallax(cal, depth_m=[[1.0, 0.525]])
    array([[ 0., -1.]], dtype=float32)
    """
    given = [
        k
        for k, v in (("depth", depth), ("parallax", parallax), ("depth_m", depth_m))
        if v is not None
    ]
    if len(given) != 1:
        raise InputError(
            "depth: give exactly one of a depth result (lfcam.DepthResult, positional),"
            f" parallax= (s) or depth_m= (metres); got {', '.join(given) or 'none'}"
        )
    if depth is not None:
        if not isinstance(depth, DepthResult):
            raise InputError(
                f"depth: expected a DepthResult (from lfcam.estimate_depth or"
                f" process_capture(...).depth), got {type(depth).__name__}; pass a map"
                " by keyword: parallax=s, or depth_m=Z in metres"
            )
        return parallax_map(depth, cal)
    if parallax is not None:
        return parallax_map(parallax, cal, "parallax")
    if not cal.metric:
        raise InputError("depth_m: the calibration is relative (no Z_c): pass parallax= instead")
    z = np.asarray(depth_m, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = 1.0 - (cal.z_b - cal.z_c) / (z - cal.z_c)
    s = np.where(z > cal.z_c, s, np.nan)
    return parallax_map(s, cal, "depth_m")


def place_raw_samples(
    cal: Calibration,
    depth: DepthResult | ArrayLike,
    *,
    iterations: int = 6,
    tolerance: float = 0.25,
) -> NDArray[np.float32]:
    """Position of every raw sample in the reference view's rectified frame.

    Raw pixel of view ``i`` at rectified ``q`` (:func:`inverse_maps`) goes to the
    reference point ``p`` with ``p + o_i s(p) = q``, solved by fixed-point iteration
    ``p <- q - o_i s(p)``; samples without a consistent solution (occluded in the
    reference, unknown parallax) are NaN.

    Parameters
    ----------
    cal : Calibration
        The camera.
    depth : DepthResult or (H_rect, W_rect) array
        The capture's depth result (its ``parallax``), or the parallax ``s`` itself.
    iterations : int
        Fixed-point iterations.
    tolerance : float
        Largest accepted ``|p + o_i s(p) - q|``, rectified px.

    Returns
    -------
    (H_raw, W_raw, 2) float32
        ``(x, y)`` in the reference view's rectified frame; NaN: not used.
    """
    inv, view = inverse_maps(cal)
    s = parallax_map(depth, cal)
    offsets = np.ascontiguousarray(cal.offsets, np.float64)
    return _lfcam.place_samples(inv, view, offsets, s, int(iterations), float(tolerance))


def shift_and_add(
    positions: ArrayLike,
    values: ArrayLike,
    shape: tuple[int, int],
    factor: float = 2,
    *,
    weights: ArrayLike | None = None,
    sigma: float = 0.0,
    radius: int = 0,
    iterations: int = 0,
    huber: float = 0.03,
    reject: float = 0.15,
    out: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Robust shift-and-add of scattered samples onto an ``r``-times finer grid.

    Sample ``k`` at rectified ``(x, y)`` lands at fine ``((x + 0.5) r - 0.5,
    (y + 0.5) r - 0.5)``; with ``sigma = 0`` it adds to the nearest fine pixel
    (``floor(X + 0.5)``), else to the fine pixels within
    ``radius`` of that one with Gaussian weights. ``iterations`` robust passes reweight
    each sample by ``min(1, huber / e)`` (``e``: its mean absolute residual against the
    current estimate; dropped above ``reject``).

    Parameters
    ----------
    positions : (..., 2) float32
        Rectified ``(x, y)``; NaN: skipped.
    values : (..., C) float32
        ``C <= 4``; NaN: skipped.
    shape : (int, int)
        The fine grid's ``(H, W)``.
    factor : float
        ``r``.
    weights : (...) float32, optional
        Per-sample weights (<= 0 or NaN: skipped).
    sigma, radius : float, int
        Splat kernel (fine px).
    iterations : int
        Robust passes.
    huber, reject : float
        Robust weighting (image units).
    out : (sum, wsum), optional
        C-contiguous float32 arrays of shapes ``(H, W, C)`` and ``(H, W)`` to write
        the result into (every element is overwritten; their contents do not matter),
        instead of fresh ones: for repeated calls, it saves the operating system's
        zeroing of fresh pages (about a fifth of a 2x fusion of 1 Mpx on one thread).

    Returns
    -------
    sum : (H, W, C) float32
        Weighted sums of the values (``out[0]`` if given).
    wsum : (H, W) float32
        Sums of the weights; ``sum / wsum[..., None]`` is the fused image (``out[1]``
        if given).

    Examples
    --------
    >>> import numpy as np
    >>> from lfcam.products.superres import shift_and_add
    >>> pos = np.array([[0.0, 0.0], [0.1, 0.0]], np.float32)
    >>> val = np.array([[1.0], [3.0]], np.float32)
    >>> s, w = shift_and_add(pos, val, (2, 2), factor=2)
    >>> float(s[1, 1, 0] / w[1, 1])
    2.0
    """
    pos = np.ascontiguousarray(positions, np.float32)
    val = np.ascontiguousarray(values, np.float32)
    if pos.ndim < 2 or pos.shape[-1] != 2:
        raise InputError(f"positions: expected shape (..., 2), got {pos.shape}")
    if val.shape[:-1] != pos.shape[:-1]:
        raise InputError(f"values: shape {val.shape} does not match positions' {pos.shape}")
    w = None if weights is None else np.ascontiguousarray(weights, np.float32)
    if w is not None and w.shape != pos.shape[:-1]:
        raise InputError(f"weights: expected shape {pos.shape[:-1]}, got {w.shape}")
    if len(shape) != 2 or min(shape) < 1:
        raise InputError(f"shape: expected a positive (H, W), got {shape!r}")
    if out is not None and (not isinstance(out, tuple | list) or len(out) != 2):
        raise InputError(f"out: expected a pair (sum, wsum) of arrays, got {type(out).__name__}")
    sum_out, wsum_out = (None, None) if out is None else out
    return _lfcam.shift_and_add(
        pos,
        val,
        w,
        int(shape[0]),
        int(shape[1]),
        float(factor),
        float(sigma),
        int(radius),
        int(iterations),
        float(huber),
        float(reject),
        sum_out,
        wsum_out,
    )


def fill_holes(
    image: NDArray[np.float32], weight: NDArray[np.float32], min_weight: float = 1e-3
) -> NDArray[np.float32]:
    """Fill pixels whose weight is below ``min_weight`` by normalised convolution at
    growing scales (sigma 1, 2, 4, ... px) of the pixels that have data.

    Parameters
    ----------
    image : (H, W, C) float32
        Values (anything where ``weight`` is small).
    weight : (H, W) float32
        Data weight per pixel.
    min_weight : float
        Pixels below this count as holes.

    Returns
    -------
    (H, W, C) float32
        ``image`` with holes filled (everything finite if any pixel has data).
    """
    have = (weight >= min_weight) & np.isfinite(image).all(-1)
    out = np.where(have[..., None], image, np.float32(0)).astype(np.float32, copy=False)
    return _fill_where(out, have)


def _fill_where(out: NDArray[np.float32], have: NDArray[np.bool_]) -> NDArray[np.float32]:
    """:func:`fill_holes` once ``have`` (the pixels with data) is known and ``out`` (the
    image, 0 elsewhere, ours to change) is prepared: fills ``out``'s holes in place."""
    out = np.ascontiguousarray(out)
    hole = ~have
    if not hole.any() or not have.any():
        return out
    # `out` is zero where there is no data: it is the data image the blurs read, so
    # the values filled in are kept aside and written once every level has read it.
    data = out
    mask = have.astype(np.float32)
    h, w = mask.shape
    fills: list[tuple[tuple[slice, slice], NDArray[np.bool_], NDArray[np.float32]]] = []
    # Holes spread over the whole frame: filled by flat index, pixel by pixel in the
    # same (row-major) order as a boolean mask would take them, without full-frame
    # mask passes.
    flat_fills: list[tuple[NDArray[np.intp], NDArray[np.float32]]] = []
    flat_hole = hole.reshape(-1)  # a view
    # Normalised convolution at sigma 1, 2, 4, 8 px; larger holes from a coarser
    # level (the same at a quarter or less of the resolution), then the mean.
    for sigma in (1.0, 2.0, 4.0, 8.0):
        if not hole.any():
            break
        for region, tile, inner in _hole_tiles(hole, sigma):
            num = cv2.GaussianBlur(data[region], (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
            den = cv2.GaussianBlur(mask[region], (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
            if region == (slice(0, h), slice(0, w)):
                left = np.flatnonzero(flat_hole)
                d = den.reshape(-1)[left]
                sel = d > 1e-3
                idx = left[sel]
                if idx.size:
                    vals = num.reshape(h * w, -1)[idx] / d[sel][:, None]
                    flat_fills.append((idx, vals))
                    flat_hole[idx] = False
                continue
            num = num.reshape(den.shape + data.shape[2:])[inner]
            den = den[inner]
            sub = hole[tile]  # a view: clearing it clears those holes in `hole`
            ok = sub & (den > 1e-3)
            if ok.any():
                fills.append((tile, ok, num[ok] / den[ok][:, None]))
                sub &= ~ok
    if hole.any():
        small = (max(1, w // 16), max(1, h // 16))
        num = cv2.resize(data, small, interpolation=cv2.INTER_AREA).reshape(small[1], small[0], -1)
        den = cv2.resize(mask, small, interpolation=cv2.INTER_AREA)
        num = cv2.GaussianBlur(num, (0, 0), 4.0).reshape(small[1], small[0], -1)
        den = cv2.GaussianBlur(den, (0, 0), 4.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            coarse = num / den[..., None]
        coarse = np.where(den[..., None] > 1e-6, coarse, data.sum((0, 1)) / mask.sum())
        up = cv2.resize(coarse.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        rest = hole.copy()
        fills.append(((slice(0, h), slice(0, w)), rest, up.reshape(h, w, -1)[rest]))
    flat_out = out.reshape(h * w, -1)  # a view (`out` is C-contiguous)
    for idx, vals in flat_fills:
        flat_out[idx] = vals
    for tile, ok, vals in fills:
        out[tile][ok] = vals
    return out


_TILE = 64


def _hole_tiles(
    hole: NDArray[np.bool_], sigma: float
) -> list[tuple[tuple[slice, slice], tuple[slice, slice], tuple[slice, slice]]]:
    """Where to blur for the holes at ``sigma``: ``(region, tile, inner)`` for each
    ``_TILE``-square tile that holds a hole: the tile extended by OpenCV's kernel
    radius for ``sigma`` (float images: ``4 sigma``) and clipped to the frame, the tile,
    and the tile within the region. Blurring the region with ``BORDER_REFLECT`` gives,
    inside the tile, what blurring the whole frame gives (the frame's own edges reflect
    the same), at a fraction of the cost when holes are sparse. One entry for the
    whole frame when the regions would cover half of it."""
    h, w = hole.shape
    whole = (slice(0, h), slice(0, w))
    reach = (round(sigma * 8 + 1) | 1) // 2
    ny, nx = -(-h // _TILE), -(-w // _TILE)
    pad = np.zeros((ny * _TILE, nx * _TILE), bool)
    pad[:h, :w] = hole
    busy = pad.reshape(ny, _TILE, nx, _TILE).any(axis=(1, 3))
    if (_TILE + 2 * reach) ** 2 * int(busy.sum()) >= h * w // 2:
        return [(whole, whole, whole)]
    out = []
    for ty, tx in zip(*np.nonzero(busy)):
        y0, x0 = int(ty) * _TILE, int(tx) * _TILE
        y1, x1 = min(h, y0 + _TILE), min(w, x0 + _TILE)
        r0, c0 = max(0, y0 - reach), max(0, x0 - reach)
        region = (slice(r0, min(h, y1 + reach)), slice(c0, min(w, x1 + reach)))
        tile = (slice(y0, y1), slice(x0, x1))
        inner = (slice(y0 - r0, y1 - r0), slice(x0 - c0, x1 - c0))
        out.append((region, tile, inner))
    return out


def super_resolve(
    raw: ArrayLike,
    cal: Calibration,
    depth: DepthResult | None = None,
    factor: int = 2,
    *,
    parallax: ArrayLike | None = None,
    depth_m: ArrayLike | None = None,
    params: SuperResParams | None = None,
    views: ArrayLike | None = None,
) -> NDArray[np.float32]:
    """Super-resolved reference view from the raw samples of all views.

    Parameters
    ----------
    raw : (H_raw, W_raw[, 3]) array
        The capture (uint8, uint16 or float32; Bayer frames are demosaiced).
    cal : Calibration
        The camera.
    depth : DepthResult, optional
        The capture's depth (:func:`lfcam.estimate_depth`). Or, by keyword, exactly
        one of ``parallax`` and ``depth_m``; an array passed here is refused.
    factor : int
        ``r``, 1 to 4.
    parallax : (H_rect, W_rect) array, optional
        The parallax ``s`` per rectified pixel.
    depth_m : (H_rect, W_rect) array, optional
        Depth in metres (metric calibrations), converted to ``s``.
    params : SuperResParams, optional
        Tuning (defaults: :class:`SuperResParams`).
    views : sequence of int, optional
        The views whose samples are used (default: all).

    Returns
    -------
    (r H_rect, r W_rect, C) float32
        In the reference view's rectified frame, fine pixel ``U`` at rectified
        ``(U + 0.5) / r - 0.5``; linear, white = 1.

    Raises
    ------
    InputError
        Naming the argument: wrong factor, raw of another size, parallax of another
        shape, an array as ``depth`` or not exactly one of ``depth``, ``parallax``,
        ``depth_m``, view indices out of range.

    Examples
    --------
    >>> res = lfcam.process_capture("capture.png", cal)       # doctest: +SKIP
    >>> sr = lfcam.super_resolve(raw, cal, res.depth, factor=2)  # doctest: +SKIP
    >>> sr = lfcam.super_resolve(raw, cal, depth_m=z, factor=2)  # doctest: +SKIP
    """
    check_instance(cal, Calibration, "cal")
    p = params or SuperResParams()
    check_instance(p, SuperResParams, "params")
    if (
        isinstance(factor, (bool, np.bool_))
        or not isinstance(factor, (int, np.integer))
        or not (1 <= int(factor) <= 4)
    ):
        raise InputError(f"factor: expected an integer from 1 to 4, got {factor!r}")
    r = int(factor)
    H, W = (int(x) for x in cal.rect_shape)
    s = resolve_parallax(cal, depth, parallax=parallax, depth_m=depth_m)
    values = raw_samples(raw, cal)
    positions = place_raw_samples(
        cal, s, iterations=p.place_iterations, tolerance=p.place_tolerance
    )
    weights = None
    if views is not None:
        sel = as_int_array(np.asarray(views).ravel(), "views", shape=(None,))
        if sel.size == 0:
            raise InputError("views: no view given (None uses all)")
        bad = sel[(sel < 0) | (sel >= cal.n_views)]
        if bad.size:
            raise InputError(f"views: index {int(bad[0])} is out of range for {cal.n_views} views")
        _, view = inverse_maps(cal)
        weights = np.isin(view, sel).astype(np.float32)
    # The fused image sum / wsum (0 where wsum < 1e-3: the holes) straight from the
    # core, as fill_holes(sum / wsum, wsum) would prepare it, without passes over it.
    z, wsum, have = _lfcam.shift_and_add_mean(
        positions,
        values,
        weights,
        r * H,
        r * W,
        float(r),
        float(p.kernel_sigma),
        int(p.kernel_radius),
        int(p.robust_iterations),
        float(p.huber),
        float(p.reject),
        1e-3,
    )
    z = _fill_where(z, have)
    if p.deblur_iterations <= 0:
        return z
    # sqrt(clip(wsum / median(wsum[wsum > 0]), 0, 4)), numpy's median, in one pass.
    a = _lfcam.data_weights(wsum)
    psf = math.sqrt((p.psf_sigma * r) ** 2 + p.kernel_sigma**2)
    return _lfcam.btv_deblur(
        z, a, None, psf, p.lam, p.alpha, p.window, p.deblur_iterations, p.step, p.eps
    )
