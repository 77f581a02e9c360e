"""Depth by optical flow and triangulation (docs/design.md, "Processing pipeline").

Rectified views -> OpenCV DIS flow from the reference view to every other view
(and back, for a forward-backward consistency check) -> robust triangulation
of the parallax ``s`` in the Rust core -> refill of the unreliable pixels -> metric
depth ``Z = Z_c + (Z_b - Z_c) / (1 - s)``.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from .._validate import check_instance
from ..calibration import Calibration
from ..errors import InputError
from ..kernels.flow import FlowParams, dis_flow, prepare
from ..kernels.warp import identity_grid, remap_bilinear
from .fill import FILL_MAX_RESIDUAL, FILL_MIN_USED, fill_parallax, guide_image, unsure
from .refine import RefineParams, refine_parallax
from .triangulate import MAX_VIEWS, TriangulationParams, TriangulationResult, triangulate

__all__ = [
    "DEPTH_FLOW",
    "DepthParams",
    "DepthResult",
    "compute_flows",
    "depth_from_parallax",
    "depth_from_views",
    "estimate_depth",
    "near_views",
]

#: Smallest view width or height depth accepts, px (OpenCV's DIS optical flow refuses
#: images under 12 px a side).
MIN_VIEW_SIDE = 16

#: DIS parameters for depth: fine patches, a dense stride and four variational
#: refinement iterations (docs/tuning.md, "Depth").
DEPTH_FLOW = FlowParams(patch_size=8, patch_stride=3, variational_iterations=4)


@dataclass(frozen=True)
class DepthParams:
    """Settings of the depth chain: flow, triangulation, fill. Why each default is what
    it is: docs/tuning.md, "Depth"."""

    #: DIS parameters; None: :data:`DEPTH_FLOW` at the finest scale (0, 1, ...) whose
    #: image has at most ``flow_max_pixels`` pixels.
    flow: FlowParams | None = None
    #: Pixels of the flow window above which the flow runs at half resolution (and so
    #: on): full resolution for 0.5 Mpx views, half for the full-size camera's.
    flow_max_pixels: int = 500_000
    #: The flow window: the reference's data grown by this share of the largest
    #: parallax vector (plus 16 px); content moving further is lost for that view only.
    flow_margin: float = 0.5
    #: Sigma (px at full resolution) of the Gaussian windows the flow's images are
    #: contrast-normalised over.
    flow_sigma: float = 6.0
    #: Compute the flows back from each view for a forward-backward check (about
    #: twice the flow time).
    backward: bool = True
    #: Finest scale of the backward flows (1: half resolution), or the forward flows'
    #: if coarser; they only check, so they skip variational refinement too.
    backward_scale: int = 1
    #: Forward-backward round-trip tolerance, px at full resolution for a backward
    #: flow as fine as the forward one (doubled per scale it is coarser).
    fb_threshold: float = 0.75
    #: Robust triangulation of the flows onto the parallax vectors.
    triangulation: TriangulationParams = field(default_factory=TriangulationParams)
    #: Refill unreliable pixels (occlusion bands, failed flows) from their confident
    #: neighbours of the same colour; False gives the bare triangulation.
    fill: bool = True
    #: A pixel whose triangulation residual exceeds this (px) is refilled ...
    fill_max_residual: float = FILL_MAX_RESIDUAL
    #: ... or one that lost more than ``1 - fill_min_used`` of the views that see it.
    fill_min_used: float = FILL_MIN_USED
    #: With at least ``fill_support_min_views`` views, a pixel whose window holds less
    #: reliable weight of its own colour than this goes to the fill's wider pass.
    fill_min_support: float = 0.002
    #: Views (the reference included) from which ``fill_min_support`` applies.
    fill_support_min_views: int = 25
    #: Window radius (px) of the fill's median, and its sampling stride (px).
    fill_radius: int = 20
    fill_stride: int = 2
    #: Colour tolerance of the fill's median, Lab units (L runs 0..100).
    fill_sigma_colour: float = 3.0
    #: With many views, a pixel the triangulation over all views leaves unsure takes a
    #: second triangulation over the near views (``|o_i| <= max |o_j| / 2``) where that
    #: one is sure, when there are at least this many near views besides the reference.
    near_views_min: int = 24
    #: Refine the parallax by a plane sweep along the parallax lines over all views
    #: (:mod:`lfcam.processing.refine`); None: off.
    refine: RefineParams | None = None

    def __post_init__(self) -> None:
        positive = ("flow_max_pixels", "flow_margin", "flow_sigma", "fb_threshold")
        for name in (*positive, "fill_max_residual", "fill_radius", "fill_stride"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (
                isinstance(value, (int, float)) and math.isfinite(value) and value > 0
            ):
                raise InputError(f"params.{name}: expected a finite number > 0, got {value!r}")
        if not (0 <= self.fill_min_used <= 1):
            raise InputError(f"params.fill_min_used: expected 0 .. 1, got {self.fill_min_used!r}")
        if self.flow is not None and not isinstance(self.flow, FlowParams):
            raise InputError(f"params.flow: expected a FlowParams, got {type(self.flow).__name__}")
        if self.refine is not None and not isinstance(self.refine, RefineParams):
            raise InputError(
                f"params.refine: expected a RefineParams or None, got {type(self.refine).__name__}"
            )

    def flow_for(self, n_pixels: int) -> FlowParams:
        """The flow's parameters for a window of ``n_pixels``: ``flow`` if given, else
        :data:`DEPTH_FLOW` at the finest scale with at most ``flow_max_pixels``."""
        if self.flow is not None:
            return self.flow
        scale = 0
        while n_pixels > self.flow_max_pixels * 4**scale:
            scale += 1
        return replace(DEPTH_FLOW, finest_scale=scale)


@dataclass
class DepthResult:
    """Depth of one capture in the reference view's rectified frame.

    Attributes
    ----------
    parallax : (H, W) float32
        ``s`` (0 on the reference board plane, -> 1 at infinity); NaN unknown.
    confidence : (H, W) float32
        0 (no information) .. 1.
    residual : (H, W) float32
        RMS of ``|u_i - o_i s|`` over the views used, px.
    perpendicular : (H, W) float32
        RMS flow component perpendicular to ``o_i``, px (calibration quality).
    n_used : (H, W) uint8
        Views used per pixel.
    depth : (H, W) float32 or None
        Metres from the front lens plane (metric calibrations); NaN unknown.
    relative : (H, W) float32 or None
        ``t = s Z_c / Z_b`` for relative calibrations.
    filled : (H, W) bool or None
        Pixels whose parallax comes from :func:`fill_parallax` (unconfident
        triangulations, occlusion bands), not from their own triangulation.
    swept : (H, W) bool or None
        With :attr:`DepthParams.refine`: pixels whose parallax comes from the plane
        sweep (there ``confidence`` is the sweep's).
    timings : dict
        Seconds per stage.
    """

    parallax: np.ndarray
    confidence: np.ndarray
    residual: np.ndarray
    perpendicular: np.ndarray
    n_used: np.ndarray
    depth: np.ndarray | None = None
    relative: np.ndarray | None = None
    filled: np.ndarray | None = None
    swept: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)


def compute_flows(
    views: np.ndarray,
    reference: int,
    params: DepthParams | None = None,
    *,
    threads: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Flow from the reference view to each view, with forward-backward weights.

    Parameters
    ----------
    views : (N, H, W[, C]) float array
        Rectified views; NaN where a view does not see.
    reference : int
        Reference view index.
    params : DepthParams, optional
        The flow's settings (``flow``, ``flow_max_pixels``, ``flow_sigma``,
        ``backward``, ``backward_scale``, ``fb_threshold``): pixels whose
        forward-backward round trip misses by more than ``fb_threshold`` (px) get
        weight 0 (occlusions, flow failures).
    threads : int
        Flows computed concurrently (OpenCV releases the GIL).

    Returns
    -------
    flows : (N, H, W, 2) float32
        ``u_i(p)``: the reference pixel p appears at ``p + u_i(p)`` in view i;
        NaN where unusable; the reference's own entry is NaN.
    weights : (N, H, W) float32
        1 where the flow passed the checks, 0 elsewhere.
    """
    flows, weights, _, _ = _flows_and_seen(views, reference, params or DepthParams(), threads)
    return flows, weights


def _flows_and_seen(
    views: np.ndarray,
    reference: int,
    params: DepthParams,
    threads: int,
    *,
    margin: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[slice, slice]]:
    """:func:`compute_flows` over a window of the frame, which views see each of its
    pixels (``(N, h, w)`` bool: the forward flow lands inside that view's data,
    consistent or not), and the window (rows, columns); outside it the reference sees
    nothing.

    ``margin``: the window is the bounding box of the reference's data grown by this
    many px (content moves at most about that far), not the whole rectified frame,
    most of which the reference does not see on a lenslet camera, and each view's flow
    covers only the window's part where both it and the reference have data, grown
    the same way (``params.flow_margin``); None: the frame, for every view.
    ``params.backward=False`` skips the backward flows and the consistency check.
    """
    N, H, W = views.shape[:3]
    ref_frame = views[reference]
    valid = np.isfinite(ref_frame).all(-1) if views.ndim == 4 else np.isfinite(ref_frame)
    ys, xs = np.nonzero(valid)
    if margin is None or ys.size == 0:
        win = (slice(0, H), slice(0, W))
    else:
        win = (
            slice(max(0, int(ys.min()) - margin), min(H, int(ys.max()) + 1 + margin)),
            slice(max(0, int(xs.min()) - margin), min(W, int(xs.max()) + 1 + margin)),
        )
    h, w = win[0].stop - win[0].start, win[1].stop - win[1].start
    flows = np.full((N, h, w, 2), np.nan, np.float32)
    weights = np.zeros((N, h, w), np.float32)
    seen = np.zeros((N, h, w), bool)
    if ys.size == 0:
        return flows, weights, seen, win
    flow_params = params.flow_for(h * w)
    # Finest scale k > 0: the flow runs at 1 / 2**k of the resolution, so everything
    # before the final flows runs there too (the views' block means, their
    # normalisation, DIS at its finest scale 0, the checks), then the flows and the
    # checks' results are interpolated back to the window (pixel centres aligned).
    f = 2**flow_params.finest_scale
    flow_params = replace(flow_params, finest_scale=0)
    # The backward flows at backward_scale of the full resolution unless the forward
    # ones are coarser; the round trip's tolerance grows with their pixel size.
    back_scale = max(0, params.backward_scale - int(np.log2(f)))
    back_params = replace(flow_params, variational_iterations=0, finest_scale=back_scale)
    fb_low = params.fb_threshold * 2**back_scale / f  # px at the flow's resolution
    sigma = params.flow_sigma / f

    hl, wl = -(-h // f), -(-w // f)  # the window at the flow's resolution

    def low(i: int, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray]:
        """View i over low-resolution ``rows, cols`` of the window, at the flow's
        resolution (block means, NaN where a block is not all data), and where it has
        data."""
        v = views[i, win[0].start + rows.start * f : win[0].start + min(h, rows.stop * f)]
        v = v[:, win[1].start + cols.start * f : win[1].start + min(w, cols.stop * f)]
        if f > 1:
            ph, pw = (
                (rows.stop - rows.start) * f - v.shape[0],
                (cols.stop - cols.start) * f - v.shape[1],
            )
            if ph or pw:
                v = np.pad(v, [(0, ph), (0, pw)] + [(0, 0)] * (v.ndim - 2), constant_values=np.nan)
            # An integer factor: OpenCV's area resize is the block mean (NaN spreads).
            v = cv2.resize(
                np.ascontiguousarray(v, np.float32),
                (v.shape[1] // f, v.shape[0] // f),
                interpolation=cv2.INTER_AREA,
            )
        return v, (np.isfinite(v).all(-1) if v.ndim == 3 else np.isfinite(v))

    ref_low, _ = low(reference, slice(0, hl), slice(0, wl))
    ref_prepared = prepare(ref_low, sigma=sigma)
    ref_valid = valid[win]
    del ref_low
    ref_box = _bounding_box(ref_valid)

    def full(a: np.ndarray, rows: slice, cols: slice) -> np.ndarray:
        """A low-resolution array over ``rows, cols`` (flow, or a mask as float) at full
        resolution, cut to the window."""
        if f > 1:
            a = cv2.resize(a, (a.shape[1] * f, a.shape[0] * f), interpolation=cv2.INTER_LINEAR)
        return a[: h - rows.start * f, : w - cols.start * f]

    def one(i: int) -> None:
        # Only where the reference and this view both have data (grown by the margin:
        # content moves): far lenslets' views overlap the reference's by half. The
        # flow's box starts on the low-resolution grid.
        if margin is None:
            rows, cols = slice(0, hl), slice(0, wl)
        else:
            box = _data_box(views[(i, *win)])
            if box is None or ref_box is None:
                return
            y0, y1 = max(box[0], ref_box[0]) - margin, min(box[1], ref_box[1]) + margin
            x0, x1 = max(box[2], ref_box[2]) - margin, min(box[3], ref_box[3]) + margin
            y0, y1, x0, x1 = (
                max(0, y0) // f,
                -(-min(h, y1) // f),
                max(0, x0) // f,
                -(-min(w, x1) // f),
            )
            if y1 - y0 < 8 or x1 - x0 < 8:
                return
            rows, cols = slice(y0, y1), slice(x0, x1)
        # Each worker prepares its own view (OpenCV and numpy release the GIL).
        view, view_valid = low(i, rows, cols)
        view_prepared = prepare(view, sigma=sigma)
        ref_sub = np.ascontiguousarray(ref_prepared[rows, cols])
        flow = dis_flow(ref_sub, view_prepared, flow_params)
        target = identity_grid(*flow.shape[:2]) + flow
        lands = remap_bilinear(view_valid.astype(np.float32), target) > 0.999
        ok = lands
        if params.backward:
            b = dis_flow(view_prepared, ref_sub, back_params)
            back = remap_bilinear(b, target)
            ok = lands & (np.hypot(*np.moveaxis(flow + back, -1, 0)) < fb_low)
        out = (
            slice(rows.start * f, min(h, rows.stop * f)),
            slice(cols.start * f, min(w, cols.stop * f)),
        )
        if f > 1:
            flow = full(flow, rows, cols) * np.float32(f)
            # A pixel passes where all the low-resolution pixels around it passed.
            ok = full(ok.astype(np.float32), rows, cols) > 0.999
            lands = full(lands.astype(np.float32), rows, cols) > 0.5
        ok &= ref_valid[out]
        np.copyto(flows[i][out], flow)
        np.copyto(flows[i][out], np.float32(np.nan), where=~ok[..., None])
        weights[i][out] = ok
        np.logical_and(lands, ref_valid[out], out=seen[i][out])

    others = [i for i in range(N) if i != reference]
    with ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
        list(ex.map(one, others))
    return flows, weights, seen, win


def _bounding_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)`` (stops exclusive) of a mask's true pixels; None if none."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _data_box(view: np.ndarray, step: int = 4) -> tuple[int, int, int, int] | None:
    """:func:`_bounding_box` of a view's data (finite pixels, NaN elsewhere), from every
    ``step``-th row and column (grown by ``step - 1`` so that it holds the whole box):
    a 16th of the work, for a box at most 3 px too large."""
    sub = view[::step, ::step]
    box = _bounding_box(np.isfinite(sub if sub.ndim == 2 else sub[..., 0]))
    if box is None:
        return None
    y0, y1, x0, x1 = box
    h, w = view.shape[:2]
    return (
        max(0, y0 * step - step + 1),
        min(h, (y1 - 1) * step + step),
        max(0, x0 * step - step + 1),
        min(w, (x1 - 1) * step + step),
    )


def depth_from_parallax(s: np.ndarray, z_b: float, z_c: float) -> np.ndarray:
    """``Z = Z_c + (Z_b - Z_c) / (1 - s)``; NaN where ``s >= 1`` (beyond infinity)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z = z_c + (z_b - z_c) / (1.0 - s)
    return np.where(s < 1.0, z, np.nan).astype(np.float32)


def near_views(
    offsets: np.ndarray, reference: int, min_views: int = DepthParams.near_views_min
) -> np.ndarray | None:
    """The views of the near-view triangulation (:attr:`DepthParams.near_views_min`):
    those within half the largest parallax vector of the reference (``|o_i| <= max
    |o_j| / 2``), reference included, as sorted indices; None when fewer than
    ``min_views`` others."""
    length = np.hypot(offsets[:, 0], offsets[:, 1])
    near = np.nonzero(length <= 0.5 * length.max() * (1 + 1e-9))[0]
    if near.size - 1 < min_views or near.size == len(offsets):
        return None
    assert reference in near
    return near


def depth_from_views(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    params: DepthParams | None = None,
    *,
    threads: int = 2,
) -> DepthResult:
    """Parallax from bare rectified views: any camera array or light field.

    Parameters
    ----------
    views : (N, H, W[, C]) float array
        Rectified views (NaN where a view does not see), any brightness.
    offsets : (N, 2) array
        ``o_i``: view i's parallax vector in px per unit ``s`` (the reference
        pixel p appears at ``p + o_i s`` in view i); ``offsets[reference] = 0``.
    reference : int
        Reference view index.
    params : DepthParams, optional
        The chain's settings (flow, triangulation, fill); default ``DepthParams()``.
    threads : int
        Concurrent flows.

    Returns
    -------
    DepthResult
        ``parallax`` (= s), ``confidence``, ``residual``, ``perpendicular``,
        ``n_used``; ``depth`` is None (no metric model here).

    Examples
    --------
    >>> res = lfcam.depth_from_views(views, offsets, reference=4)   # doctest: +SKIP
    >>> disparity = res.parallax                                    # doctest: +SKIP
    """
    p = params if params is not None else DepthParams()
    if not isinstance(p, DepthParams):
        raise InputError(f"params: expected a DepthParams, got {type(p).__name__}")
    views = np.asarray(views)
    if views.ndim not in (3, 4) or views.shape[0] < 2:
        raise InputError(f"views: expected (N, H, W[, C]) with N >= 2, got shape {views.shape}")
    if views.dtype.kind not in "fiu":
        raise InputError(f"views: expected real numbers, got dtype {views.dtype}")
    if min(views.shape[1:3]) < MIN_VIEW_SIDE:
        raise InputError(
            f"views: each view is {views.shape[2]} x {views.shape[1]} px; optical flow needs "
            f"at least {MIN_VIEW_SIDE} px a side"
        )
    if isinstance(reference, (bool, np.bool_)) or not isinstance(reference, (int, np.integer)):
        raise InputError(f"reference: expected a view index (an integer), got {reference!r}")
    if views.dtype != np.float32:
        views = views.astype(np.float32)
    offsets = np.asarray(offsets, np.float64)
    if offsets.shape != (views.shape[0], 2) or not np.isfinite(offsets).all():
        raise InputError(
            f"offsets: expected finite (N, 2) = ({views.shape[0]}, 2), got {offsets.shape}"
        )
    if views.shape[0] > MAX_VIEWS:  # before minutes of flow, not after
        raise InputError(
            f"views: {views.shape[0]} views; at most {MAX_VIEWS} are supported"
            " (choose a subset of the grid)"
        )
    if not (0 <= int(reference) < views.shape[0]):
        raise InputError(f"reference: {reference} is not a view index (0..{views.shape[0] - 1})")
    t0 = time.perf_counter()
    # Content moves by o_i s; |s| <= 2 covers a scene from half the board's
    # distance to infinity on the reference camera, and light fields' |s| of a few px.
    margin = int(np.ceil(p.flow_margin * np.abs(offsets).max())) + 16
    flows, weights, seen, win = _flows_and_seen(views, int(reference), p, threads, margin=margin)
    t1 = time.perf_counter()
    tri = _triangulate(flows, offsets, weights, slice(None), int(reference), p.triangulation)
    n_seen = seen.sum(axis=0, dtype=np.uint8)
    out = {k: getattr(tri, k) for k in _TRI_FIELDS}
    near = near_views(offsets, int(reference), p.near_views_min)
    if near is not None:
        # Where all views together are unsure, the near views' own triangulation.
        ref_near = int(np.searchsorted(near, int(reference)))
        tri_near = _triangulate(flows, offsets, weights, near, ref_near, p.triangulation)
        seen_near = seen[near].sum(axis=0, dtype=np.uint8)
        lim = (p.fill_max_residual, p.fill_min_used)
        unsure_all = unsure(tri.residual, tri.n_used, n_seen, *lim)
        unsure_near = unsure(tri_near.residual, tri_near.n_used, seen_near, *lim)
        take = (unsure_all | ~np.isfinite(tri.parallax)) & ~(
            unsure_near | ~np.isfinite(tri_near.parallax)
        )
        for k in _TRI_FIELDS:
            out[k] = np.where(take, getattr(tri_near, k), out[k])
        n_seen = np.where(take, seen_near, n_seen)
    del flows, weights, seen
    t2 = time.perf_counter()
    timings = {"flow": t1 - t0, "triangulation": t2 - t1}
    parallax, confidence, filled = out["parallax"], out["confidence"], None
    if p.fill:
        many = len(offsets) >= p.fill_support_min_views
        parallax, confidence, filled = fill_parallax(
            parallax,
            confidence,
            guide_image(views[(int(reference), *win)]),
            residual=out["residual"],
            n_used=out["n_used"],
            n_seen=n_seen,
            where=n_seen > 0,
            max_residual=p.fill_max_residual,
            min_used=p.fill_min_used,
            min_support=p.fill_min_support if many else 0.0,
            radius=p.fill_radius,
            stride=p.fill_stride,
            sigma_colour=p.fill_sigma_colour,
        )
        timings["fill"] = time.perf_counter() - t2
    swept = None
    if p.refine is not None:
        t3 = time.perf_counter()
        ref = refine_parallax(
            views[(slice(None), *win)], offsets, int(reference), parallax, p.refine, filled
        )
        parallax, swept = ref.parallax, ref.swept
        confidence = np.where(swept, ref.confidence, confidence).astype(np.float32)
        timings["refine"] = time.perf_counter() - t3
    shape = views.shape[1:3]
    return DepthResult(
        parallax=_paste(parallax, win, shape, np.nan),
        confidence=_paste(confidence, win, shape, 0),
        residual=_paste(out["residual"], win, shape, np.nan),
        perpendicular=_paste(out["perpendicular"], win, shape, np.nan),
        n_used=_paste(out["n_used"], win, shape, 0),
        filled=None if filled is None else _paste(filled, win, shape, False),
        swept=None if swept is None else _paste(swept, win, shape, False),
        timings=timings,
    )


def _triangulate(
    flows: np.ndarray,
    offsets: np.ndarray,
    weights: np.ndarray,
    views: np.ndarray | slice,
    reference: int,
    params: TriangulationParams,
) -> TriangulationResult:
    """:func:`triangulate` over a subset of the views (``reference`` indexes the subset)."""
    return triangulate(
        flows[views],
        offsets[views],
        reference,
        weights[views],
        min_views=params.min_views,
        sigma_floor=params.sigma_floor,
        cutoff=params.cutoff,
        iterations=params.iterations,
    )


def _paste(
    a: np.ndarray, win: tuple[slice, slice], shape: tuple[int, ...], value: Any
) -> np.ndarray:
    """``a`` (a window's values) in a frame of ``shape`` filled with ``value`` elsewhere."""
    if a.shape == tuple(shape):
        return a
    out = np.full(shape, value, a.dtype)
    out[win] = a
    return out


_TRI_FIELDS = ("parallax", "confidence", "residual", "perpendicular", "n_used")


def estimate_depth(
    views: np.ndarray,
    cal: Calibration,
    params: DepthParams | None = None,
    *,
    threads: int = 2,
) -> DepthResult:
    """Depth of one capture from its rectified views and the camera's calibration.

    Parameters
    ----------
    views : (N, H_rect, W_rect, C) float array
        From :func:`lfcam.rectify`.
    cal : Calibration
        The camera.
    params : DepthParams, optional
        The depth chain's settings (see :func:`depth_from_views`).
    threads : int
        Concurrent flows.

    Returns
    -------
    DepthResult
        With ``depth`` in metres (metric calibrations) or ``relative``
        (``t = s Z_c / Z_b``, triangulated against ``d_i``) otherwise.
    """
    check_instance(cal, Calibration, "cal")
    views = np.asarray(views)
    if views.shape[0] != cal.n_views or tuple(views.shape[1:3]) != tuple(cal.rect_shape):
        raise InputError(
            f"views: shape {views.shape} does not match the calibration"
            f" ({cal.n_views}, {cal.rect_shape[0]}, {cal.rect_shape[1]}, C)"
        )
    res = depth_from_views(views, cal.offsets, cal.reference, params, threads=threads)
    if cal.metric:
        res.depth = depth_from_parallax(res.parallax, cal.z_b, cal.z_c)
    else:
        res.relative = res.parallax
    return res
