"""Plane + parallax triangulation: the parallax ``s`` of every reference pixel from the
optical flows to all views at once, robustly (docs/design.md, "Triangulation")."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

import lfcam._lfcam as _lfcam

from .._validate import check_positive_int
from ..errors import InputError

__all__ = [
    "CONFIDENCE_INFO",
    "CONFIDENCE_TAU",
    "MAX_VIEWS",
    "TriangulationParams",
    "TriangulationResult",
    "triangulate",
]

#: Most views (the reference included) :func:`triangulate` accepts.
MAX_VIEWS = 128
#: Share of the parallax information at which the confidence's first factor is 1 - 1/e.
CONFIDENCE_INFO = 0.25
#: Residual (px) at which the confidence's second factor is 1/e.
CONFIDENCE_TAU = 0.5


@dataclass(frozen=True)
class TriangulationParams:
    """Settings of :func:`triangulate` (see it for the estimator)."""

    #: Fewest surviving views for a parallax; fewer give NaN.
    min_views: int = 1
    #: Lower bound of the robust scale, px: flows that agree to better than this are
    #: not told apart.
    sigma_floor: float = 0.25
    #: Tukey's cutoff in robust scales: a view this far off is dropped.
    cutoff: float = 3.0
    #: Most reweighted least-squares iterations.
    iterations: int = 5


@dataclass(frozen=True, eq=False)
class TriangulationResult:
    """What :func:`triangulate` returns: five ``(H, W)`` arrays in the reference frame.

    Attributes
    ----------
    parallax : numpy.ndarray of float32
        ``s``: a scene point at reference pixel ``p`` appears at ``p + o_i s`` in view
        ``i`` (0 on the calibration board's plane, towards 1 at infinity, negative
        nearer than the board). NaN where fewer than ``min_views`` views survive.
    confidence : numpy.ndarray of float32
        In [0, 1]; 0 where ``parallax`` is NaN. See :func:`triangulate`, Notes.
    residual : numpy.ndarray of float32
        Weighted RMS of ``|u_i - o_i s|`` over the surviving views, px. NaN where
        ``parallax`` is.
    perpendicular : numpy.ndarray of float32
        RMS of the flow component perpendicular to ``o_i`` over the surviving views, px:
        pure error, a measure of calibration quality. NaN where ``parallax`` is.
    n_used : numpy.ndarray of uint8
        Number of surviving views (also where there are fewer than ``min_views``).
    """

    parallax: NDArray[np.float32]
    confidence: NDArray[np.float32]
    residual: NDArray[np.float32]
    perpendicular: NDArray[np.float32]
    n_used: NDArray[np.uint8]


def _float32_stack(value: Any, name: str, ndim: int, layout: str) -> NDArray[np.float32]:
    """``value`` as a C-contiguous float32 ndarray with ``ndim`` dimensions, none empty."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: cannot be converted to an array ({e})") from e
    if arr.dtype != np.float32:
        raise InputError(
            f"{name}: dtype {arr.dtype} is not supported; expected float32 "
            "(convert with .astype(numpy.float32))"
        )
    if arr.ndim != ndim or arr.size == 0:
        raise InputError(f"{name}: expected a non-empty {layout} array, got shape {arr.shape}")
    return np.ascontiguousarray(arr)


def _positive_float(value: Any, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise InputError(f"{name}: expected a finite number > 0, got {value!r}")
    number = float(value)
    if not (math.isfinite(number) and number > 0):
        raise InputError(f"{name}: expected a finite number > 0, got {value!r}")
    return number


def triangulate(
    flows: ArrayLike,
    offsets: ArrayLike,
    reference: int,
    weights: ArrayLike | None = None,
    *,
    min_views: int = TriangulationParams.min_views,
    sigma_floor: float = TriangulationParams.sigma_floor,
    cutoff: float = TriangulationParams.cutoff,
    iterations: int = TriangulationParams.iterations,
) -> TriangulationResult:
    """Robust parallax ``s`` of every reference pixel from the flows to all views.

    In rectified coordinates a scene point seen at reference pixel ``p`` appears at
    ``p + o_i s(p)`` in view ``i``, so the optical flow ``u_i(p)`` from the reference to
    view ``i`` estimates ``o_i s``. Per pixel, over the *usable* views (not the
    reference, ``|o_i| > 0``, finite flow, weight > 0), with ``w_i`` the weight (1
    without ``weights``):

    1. ``s_i = o_i . u_i / |o_i|^2`` per view; start from their weighted median with
       weights ``w_i |o_i|^2``, which survives occluded views holding less than half
       of that weight.
    2. A pass: residuals ``r_i = |u_i - o_i s|`` (px), robust scale ``sigma =
       max(sigma_floor, 1.4826 * median(r_i))`` (median weighted by ``w_i``), Tukey's
       biweight ``(1 - (r_i / c)^2)^2`` with ``c = cutoff * sigma``: a view at or beyond
       ``c`` gets weight 0, i.e. is dropped. (Tukey rather than Huber: Huber's weight
       never reaches 0, so it cannot drop an occluded view.)
    3. Up to ``iterations`` times: a pass, then weighted least squares
       ``s = sum(w_i t_i o_i . u_i) / sum(w_i t_i |o_i|^2)`` with the Tukey weights
       ``t_i``; stop early once ``s`` moves by less than 1e-6.
    4. A final pass at the final ``s``; the views with ``r_i < c`` *survive* and the
       outputs are computed over them.

    Weighted medians of ``x`` with weights ``v``: sorted ascending with cumulative
    weights ``C_k`` and total ``T``, the mean of the first ``x_k`` with ``2 C_k >= T``
    and the first with ``2 C_k > T`` (for equal weights, the ordinary median).

    Parameters
    ----------
    flows : array_like of float32, shape (N, H, W, 2)
        ``flows[i, y, x]`` is the flow ``(dx, dy)`` from reference pixel ``(x, y)`` to
        view ``i``, px; NaN or infinity: no measurement. The reference's own entry is
        not read. Other dtypes are refused (a float64 stack of 12 full-size flows is
        200 MB: convert it once yourself with ``.astype(numpy.float32)``); a
        non-C-contiguous array is copied once. ``2 <= N <= 128``.
    offsets : array_like of float, shape (N, 2)
        ``o_i``, px per unit ``s`` (rectified frame, ``x`` first), finite;
        ``offsets[reference]`` must be ``(0, 0)``. Views with a zero offset are not used.
    reference : int
        Index of the reference view, ``0 <= reference < N``.
    weights : array_like of float32, shape (N, H, W), optional
        A weight ``>= 0`` per flow vector, e.g. the forward-backward consistency (0 or
        NaN: do not use). The reference's entries are not read. Default: 1 for every
        finite flow vector.
    min_views : int, optional
        Fewest surviving views for a parallax; fewer give NaN. Default 1.
    sigma_floor : float, optional
        Lower bound of the robust scale ``sigma``, px: flows that agree to better than
        this are not told apart. Default 0.25.
    cutoff : float, optional
        A view whose residual reaches ``cutoff * sigma`` is dropped. Default 3. Below
        ~0.68 every view can be dropped.
    iterations : int, optional
        Most reweighting iterations; 0 keeps the weighted median. Default 5.

    Returns
    -------
    TriangulationResult
        ``parallax`` (``s``), ``confidence``, ``residual``, ``perpendicular`` (float32)
        and ``n_used`` (uint8), each ``(H, W)``.

    Raises
    ------
    InputError
        If an argument has the wrong type, dtype or shape, if ``N`` is outside
        ``2..128``, if ``offsets`` has a non-finite value, a non-zero reference offset
        or no non-zero offset at all, if ``reference`` is not a view index, if a
        parameter is out of range, or if a weight of a non-reference view is negative
        or infinite (the message names the view, e.g. ``weights[3]: ...``, and the
        pixel). The message starts with the argument's name. ``InputError`` is a
        ``ValueError``.

    See Also
    --------
    lfcam.depth_from_views : flows from rectified views, then this.

    Notes
    -----
    ``residual = sqrt(sum(w_i t_i r_i^2) / sum(w_i t_i))`` and ``perpendicular =
    sqrt(mean(q_i^2))`` with ``q_i = (o_i x u_i) / |o_i|`` (unweighted), both over the
    surviving views.

    ``confidence = (1 - exp(-info / 0.25)) * exp(-(residual / 0.5)^2)``, with ``info =
    sum(w_i |o_i|^2 over the surviving views) / sum(|o_i|^2 over all views but the
    reference)``: the share of the camera's parallax information that was measured and
    kept (the variance of ``s`` is ``sigma_flow^2 / sum(w_i |o_i|^2)``). The first
    factor is 0.98 with every view, 0.86 with half of the information and 0.30 with one
    view of twelve; the second is 0.96 at a residual of 0.1 px, 0.78 at 0.25 px and 0.02
    at 1 px. Weights above 1 raise ``info`` above 1 (the first factor then saturates).

    Computed in float32 in the Rust core, in parallel over rows on lfcam's thread pool
    with the GIL released; the result does not depend on the number of threads.

    Examples
    --------
    >>> import numpy as np
    >>> import lfcam
    >>> offsets = np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0], [-20.0, -20.0]])
    >>> s = np.array([[0.25, -0.5, 0.0]], np.float32)            # (H, W) = (1, 3)
    >>> flows = (offsets[:, None, None, :] * s[None, :, :, None]).astype(np.float32)
    >>> flows[3, 0, 1] += (5.0, -5.0)                             # one occluded view
    >>> res = lfcam.triangulate(flows, offsets, reference=0)
    >>> res.parallax
    array([[ 0.25, -0.5 ,  0.  ]], dtype=float32)
    >>> res.n_used
    array([[3, 2, 3]], dtype=uint8)
    >>> res.confidence.round(2)
    array([[0.98, 0.86, 0.98]], dtype=float32)
    """
    flows_arr = _float32_stack(flows, "flows", 4, "(N, H, W, 2)")
    n = flows_arr.shape[0]
    if flows_arr.shape[3] != 2:
        raise InputError(f"flows: expected shape (N, H, W, 2), got {flows_arr.shape}")
    if not 2 <= n <= MAX_VIEWS:
        raise InputError(
            f"flows: expected between 2 and {MAX_VIEWS} views (the reference and at least "
            f"one other), got N = {n}"
        )
    try:
        offsets_arr = np.asarray(offsets)
    except (TypeError, ValueError) as e:
        raise InputError(f"offsets: cannot be converted to an array ({e})") from e
    if offsets_arr.dtype.kind not in "iuf":
        raise InputError(f"offsets: expected real numbers, got dtype {offsets_arr.dtype}")
    if offsets_arr.shape != (n, 2):
        raise InputError(
            f"offsets: expected shape (N, 2) = ({n}, 2), one row per view of flows, "
            f"got {offsets_arr.shape}"
        )
    offsets_arr = np.ascontiguousarray(offsets_arr, dtype=np.float64)
    if not np.isfinite(offsets_arr).all():
        bad = int(np.flatnonzero(~np.isfinite(offsets_arr).all(axis=1))[0])
        raise InputError(f"offsets[{bad}]: {tuple(offsets_arr[bad])} is not finite")
    reference = check_positive_int(reference, "reference", minimum=0)
    if reference >= n:
        raise InputError(f"reference: expected a view index between 0 and {n - 1}, got {reference}")
    if offsets_arr[reference].any():
        raise InputError(
            f"offsets[{reference}]: the reference view's offset must be (0, 0), got "
            f"{tuple(offsets_arr[reference])}; is reference = {reference} the view the "
            "offsets are relative to?"
        )
    weights_arr = None
    if weights is not None:
        weights_arr = _float32_stack(weights, "weights", 3, "(N, H, W)")
        if weights_arr.shape != flows_arr.shape[:3]:
            raise InputError(
                f"weights: expected shape (N, H, W) = {flows_arr.shape[:3]} like flows, "
                f"got {weights_arr.shape}"
            )
    min_views = check_positive_int(min_views, "min_views", minimum=1)
    if min_views > n - 1:
        raise InputError(
            f"min_views: expected an integer between 1 and N - 1 = {n - 1}, got {min_views}"
        )
    sigma_floor = _positive_float(sigma_floor, "sigma_floor")
    cutoff = _positive_float(cutoff, "cutoff")
    iterations = check_positive_int(iterations, "iterations", minimum=0)
    parallax, confidence, residual, perpendicular, n_used = _lfcam.triangulate(
        flows_arr,
        offsets_arr,
        reference,
        weights_arr,
        min_views,
        sigma_floor,
        cutoff,
        iterations,
    )
    return TriangulationResult(parallax, confidence, residual, perpendicular, n_used)
