"""Depth by optical flow and triangulation (DESIGN.md sections 3 and 5).

Rectified views -> OpenCV DIS flow from the reference view to every other view
(and back, for a forward-backward consistency check) -> robust triangulation
of the parallax ``s`` in the Rust core -> metric depth
``Z = Z_c + (Z_b - Z_c) / (1 - s)``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from .calibration import Calibration
from .errors import InputError
from .flow import FlowParams, dis_flow, prepare

__all__ = [
    "BACKWARD_SCALE",
    "DEPTH_FLOW",
    "FB_THRESHOLD",
    "FILL_MAX_RESIDUAL",
    "FILL_MIN_SUPPORT",
    "FILL_MIN_USED",
    "FILL_SUPPORT_MIN_VIEWS",
    "FLOW_MARGIN",
    "FLOW_MAX_PIXELS",
    "NEAR_VIEWS_MIN",
    "DepthResult",
    "compute_flows",
    "depth_flow",
    "depth_from_parallax",
    "depth_from_views",
    "estimate_depth",
    "fill_parallax",
    "guide_image",
    "near_views",
]

#: :func:`fill_parallax` refills a pixel whose triangulation residual exceeds this
#: (px: the views disagree, as where flow mixes an occluder and what it hides) ...
FILL_MAX_RESIDUAL = 0.2
#: ... or which lost more than this share of the views that see it (occlusions,
#: failed flows). Measured, ``benchmarks/hci.py`` and the simulator's cameras:
#: HCI antinous 3 x 4 BadPix0.07 12.8% -> 9.3%, MSE x 100 26.9 -> 4.6; simulated
#: layered scenes 3.9% -> 2.0% (3 x 4) and 6.2% -> 2.0% (3 x 3) of pixels off by > 5%.
#: (Refilling by low confidence instead broke whole surfaces seen by few views.)
FILL_MIN_USED = 0.75
#: With ``min_support > 0``, a pixel whose window holds less reliable weight than
#: that (its ``support``: the total weight over the window's grid positions) is not
#: filled from it: its median would come from neighbours of another colour (the
#: colour weight is tiny but a median only sees relative weights). It goes to the
#: wider second pass instead. :func:`depth_from_views` uses it for light fields of at
#: least :data:`FILL_SUPPORT_MIN_VIEWS` views, where the far views' occlusion bands are
#: wide; :func:`fill_parallax` alone has it off (0). Measured with it (HCI antinous,
#: ``benchmarks/hci.py``, BadPix0.07 / MSE x 100): 5 x 5 7.5% / 8.85 -> 7.3% / 4.4,
#: 9 x 9 (with :data:`NEAR_VIEWS_MIN`'s second triangulation) 7.35% / 9.15 -> 7.07% /
#: 4.44; 3 x 4 and 3 x 3 unchanged; but on the simulated 3 x 4 camera's layered scene
#: 1.5% -> 3.7% of pixels off by > 5% (a strip between the image circle's edge and a
#: card took the card's parallax in the wider pass), and lower PSNR of novel views and
#: super-resolution there (``tests/test_render.py``, ``tests/test_superres.py``).
FILL_MIN_SUPPORT = 0.002
#: Views (the reference included) from which :func:`depth_from_views` fills with
#: :data:`FILL_MIN_SUPPORT`; below, with 0.
FILL_SUPPORT_MIN_VIEWS = 25
#: With many views (a 9 x 9 light field), the far views' flows fail first near
#: occlusions: content moves furthest there. A pixel that the triangulation over all
#: views leaves unsure (:func:`fill_parallax`'s criteria) takes a second triangulation
#: over the near views (:func:`near_views`) where that one is sure, before any fill;
#: when there are at least this many near views besides the reference. Measured on
#: HCI antinous 9 x 9 (``benchmarks/hci.py``; near views: the inner 5 x 5), BadPix0.07
#: / MSE x 100 10.0% / 11.2 -> 7.1% / 4.4 (both with :data:`FILL_MIN_SUPPORT`). Fewer
#: near views pass mixed pixels as sure: a further step down to the inner 3 x 3 made it
#: 9.3% / 5.6.
NEAR_VIEWS_MIN = 24

#: DIS parameters for depth: fine patches, dense stride, four variational refinement
#: iterations, at full resolution. ``benchmarks/flow_tuning.py`` (Middlebury "other",
#: mean end-point error; CPU ms per flow): 2 / 3 / 4 / 5 iterations 0.263 / 0.259 /
#: 0.255 / 0.254 px, 102 / 103 / 105 / 111 ms, OpenCV's MEDIUM preset 0.333 px; on
#: Venus only 4 or more stay within 0.01 px of MEDIUM (0.389 against 0.384;
#: ``tests/test_flow.py``). HCI antinous 3 x 4 (``benchmarks/hci.py``, BadPix0.07 /
#: MSE x 100, backward flows as :data:`BACKWARD_SCALE`): 2 / 3 / 4 / 5 iterations
#: 8.66% / 4.64, 8.61% / 4.74, 8.69% / 4.74, 8.84% / 4.74; without variational
#: refinement 11.2% / 5.2. Finest scale 1 instead of 0 raises BadPix0.07 from 9.5% to 24%.
DEPTH_FLOW = FlowParams(patch_size=8, patch_stride=3, variational_iterations=4)
#: Without ``flow`` parameters, :func:`depth_from_views` runs :data:`DEPTH_FLOW` at the
#: finest scale (0, 1, ...) whose image has at most this many pixels: full resolution
#: for the simulator's 480 x 360 views (a 0.16 Mpx flow window) and HCI's 512 x 512,
#: half resolution for the full-size camera's 1200 x 900 views (a 0.95 Mpx window).
#: There, measured on the simulator's full-size camera (``benchmarks/pipeline.py
#: --size full``; planes / spheres / layered), half resolution keeps the median
#: |dZ|/Z at 0.04% (0.02-0.03% at full resolution) and the share of pixels off by
#: > 5% at 2.55 / 0.38 / 1.58% (2.55 / 0.32 / 1.06%), for a third of the flow time
#: and a quarter of DIS's memory.
FLOW_MAX_PIXELS = 500_000
#: The flows run over the bounding box of the reference view's data grown by this
#: much of the largest parallax vector (plus 16 px), and each view's only over that
#: box's part where the view has data too (grown the same way: far lenslets' views
#: overlap the reference's by about half); content that moves further out is lost for
#: that view only (its flow does not land; other views may still see it). The area
#: DIS works on (11 flows) and the share of pixels off by > 5% (planes / spheres /
#: layered), the old whole 2.0 windows against 0.5 with each view's overlap: the
#: simulator's 3 x 4 camera 3.16 -> 1.35 Mpx, 2.57 / 1.15 / 1.74% -> 2.55 / 1.62 /
#: 1.65%; the full-size camera 18.5 -> 7.7 Mpx, 2.55 / 0.42 / 2.31% -> 2.55 / 1.05 /
#: 2.12%; coverage unchanged (99.5%). Less is too little for the far corner view,
#: which sees the reference's data only near its edge: at 0.25 (1.22 Mpx) the spheres
#: scene rendered at view 11 (``tests/test_render.py``) fell from 28.1 to 27.9 dB.
#: (The planes scene's 2.55% is a 24 px gap onto a far background that only one to
#: three views see.)
FLOW_MARGIN = 0.5
#: The flow's images are contrast-normalised over Gaussian windows of this sigma
#: (px at full resolution; :func:`lfcam.flow.prepare`).
FLOW_SIGMA = 6.0
#: The backward flows (view -> reference), used only for the forward-backward
#: consistency check, run at this finest scale of the full resolution (1: half
#: resolution) or at the forward flows' scale if that is coarser; a round trip may
#: miss by :data:`FB_THRESHOLD` times the backward flow's pixel size relative to the
#: forward's. Measured on HCI antinous (``benchmarks/hci.py``; BadPix0.07 / MSE x 100,
#: process CPU seconds), scale 0 / 0.75 px against 1 / 1.5 px: 3 x 4 8.93% / 4.61,
#: 3.0 s -> 8.66% / 4.64, 1.6 s (a backward flow costs 22 ms of CPU instead of 108);
#: 5 x 5 7.56% / 4.57 -> 7.54% / 4.39; 3 x 3 11.05% / 5.5 -> 10.5% / 5.6 (and with
#: 0.75 px at scale 1 too much is refilled: 3 x 4 MSE x 100 7.8). On the full-size
#: camera, whose forward flows are already at half resolution, a backward flow at a
#: quarter (2.0 / 1.5 px) let more occlusions through: pixels off by > 5% (planes /
#: spheres / layered) 2.55 / 1.50 / 3.26% against 2.55 / 0.84 / 2.53%. The backward
#: flows skip DIS's variational refinement, half of a flow's cost (128 -> 65 ms of
#: CPU at 512 x 512), at no loss: HCI antinous 3 x 4 / 3 x 3 / 5 x 5 8.69% / 4.74,
#: 10.96% / 5.64, 7.20% / 4.36 -> 8.60% / 4.59, 10.73% / 5.71, 7.14% / 4.26; off by >
#: 5% on the small camera 2.55 / 1.34 / 1.75% -> 2.55 / 1.27 / 1.84%, on the full-size
#: camera 2.55 / 0.97 / 1.85% -> 2.55 / 0.86 / 1.74%.
BACKWARD_SCALE = 1
#: Forward-backward round-trip tolerance, px at full resolution for a backward flow as
#: fine as the forward one (see :data:`BACKWARD_SCALE`).
FB_THRESHOLD = 0.75


def depth_flow(n_pixels: int) -> FlowParams:
    """:data:`DEPTH_FLOW` at the finest scale for a flow window of ``n_pixels``
    (see :data:`FLOW_MAX_PIXELS`)."""
    scale = 0
    while n_pixels > FLOW_MAX_PIXELS * 4**scale:
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
    timings: dict[str, float] = field(default_factory=dict)


def _grid(h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([xx, yy], -1)


def compute_flows(
    views: np.ndarray,
    reference: int,
    *,
    params: FlowParams | None = None,
    fb_threshold: float = FB_THRESHOLD,
    threads: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Flow from the reference view to each view, with forward-backward weights.

    Parameters
    ----------
    views : (N, H, W[, C]) float array
        Rectified views; NaN where a view does not see.
    reference : int
        Reference view index.
    params : FlowParams, optional
        DIS parameters (default :func:`depth_flow` of the flow window's size).
    fb_threshold : float
        Pixels whose forward-backward round trip misses by more than this (px)
        get weight 0 (occlusions, flow failures); doubled for each scale by which
        the backward flows are coarser than the forward ones
        (:data:`BACKWARD_SCALE`).
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
    flows, weights, _, _ = _flows_and_seen(views, reference, params, fb_threshold, threads)
    return flows, weights


def _flows_and_seen(
    views: np.ndarray,
    reference: int,
    params: FlowParams | None,
    fb_threshold: float,
    threads: int,
    *,
    margin: int | None = None,
    backward: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[slice, slice]]:
    """:func:`compute_flows` over a window of the frame, which views see each of its
    pixels (``(N, h, w)`` bool: the forward flow lands inside that view's data,
    consistent or not), and the window (rows, columns); outside it the reference sees
    nothing.

    ``margin``: the window is the bounding box of the reference's data grown by this
    many px (content moves at most about that far), not the whole rectified frame,
    most of which the reference does not see on a lenslet camera, and each view's flow
    covers only the window's part where both it and the reference have data, grown
    the same way (:data:`FLOW_MARGIN`); None: the frame, for every view.
    ``backward=False`` skips the backward flows and the consistency check.
    """
    from .warp import remap_bilinear

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
    params = params or depth_flow(h * w)
    # Finest scale k > 0: the flow runs at 1 / 2**k of the resolution, so everything
    # before the final flows runs there too (the views' block means, their
    # normalisation, DIS at its finest scale 0, the checks), then the flows and the
    # checks' results are interpolated back to the window (pixel centres aligned).
    f = 2**params.finest_scale
    params = replace(params, finest_scale=0)
    # The backward flows at BACKWARD_SCALE of the full resolution unless the forward
    # ones are coarser; the round trip's tolerance grows with their pixel size.
    back_scale = max(0, BACKWARD_SCALE - int(np.log2(f)))
    back_params = replace(params, variational_iterations=0, finest_scale=back_scale)
    fb_low = fb_threshold * 2**back_scale / f  # px at the flow's resolution

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
    ref_prepared = prepare(ref_low, sigma=FLOW_SIGMA / f)
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
        view_prepared = prepare(view, sigma=FLOW_SIGMA / f)
        ref_sub = np.ascontiguousarray(ref_prepared[rows, cols])
        flow = dis_flow(ref_sub, view_prepared, params)
        target = _grid(*flow.shape[:2]) + flow
        lands = remap_bilinear(view_valid.astype(np.float32), target) > 0.999
        ok = lands
        if backward:
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


def guide_image(image: np.ndarray) -> np.ndarray:
    """A view as the colour guide of :func:`fill_parallax`: CIE Lab, float32.

    Brightness is normalised first (the 99.5th percentile of the finite pixels
    maps to 1) so that ``sigma_colour`` means the same under any exposure, gain
    or bit depth. Grey images give an ``(H, W, 1)`` lightness guide. NaN stays NaN.
    """
    img = np.asarray(image, np.float32)
    finite = np.isfinite(img).all(-1) if img.ndim == 3 else np.isfinite(img)
    top = float(np.percentile(img[finite], 99.5)) if finite.any() else 1.0
    scaled = np.clip(np.nan_to_num(img / max(top, 1e-12), nan=0.0), 0.0, 1.0)
    if img.ndim == 2 or img.shape[-1] == 1:
        lab = cv2.cvtColor(scaled.reshape(img.shape[:2]), cv2.COLOR_GRAY2RGB)
        lab = cv2.cvtColor(lab, cv2.COLOR_RGB2Lab)[..., :1]
    elif img.shape[-1] == 3:
        lab = cv2.cvtColor(scaled, cv2.COLOR_RGB2Lab)
    else:
        raise InputError(f"image: expected 1 or 3 channels, got shape {img.shape}")
    return np.where(finite[..., None], lab, np.nan).astype(np.float32)


def _unsure(
    residual: np.ndarray | None,
    n_used: np.ndarray | None,
    n_seen: np.ndarray | None,
    max_residual: float,
    min_used: float,
) -> np.ndarray | bool:
    """Where a triangulation is not to be trusted: the views disagree (``residual >
    max_residual``) or it lost more than ``1 - min_used`` of the views that see it."""
    unsure: np.ndarray | bool = False
    if residual is not None:
        with np.errstate(invalid="ignore"):
            unsure = unsure | (np.asarray(residual, np.float32) > max_residual)
    if n_used is not None and n_seen is not None:
        unsure = unsure | (
            np.asarray(n_used, np.float32) < min_used * np.asarray(n_seen, np.float32)
        )
    return unsure


def near_views(offsets: np.ndarray, reference: int) -> np.ndarray | None:
    """The views of :data:`NEAR_VIEWS`' second triangulation: those within half the
    largest parallax vector of the reference (``|o_i| <= max |o_j| / 2``), reference
    included, as sorted indices; None when fewer than :data:`NEAR_VIEWS_MIN` others."""
    length = np.hypot(offsets[:, 0], offsets[:, 1])
    near = np.nonzero(length <= 0.5 * length.max() * (1 + 1e-9))[0]
    if near.size - 1 < NEAR_VIEWS_MIN or near.size == len(offsets):
        return None
    assert reference in near
    return near


def fill_parallax(
    parallax: np.ndarray,
    confidence: np.ndarray,
    guide: np.ndarray,
    *,
    residual: np.ndarray | None = None,
    n_used: np.ndarray | None = None,
    n_seen: np.ndarray | None = None,
    where: np.ndarray | None = None,
    max_residual: float = FILL_MAX_RESIDUAL,
    min_used: float = FILL_MIN_USED,
    min_support: float = 0.0,
    threshold: float | None = None,
    radius: int = 20,
    stride: int = 2,
    sigma_colour: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replace unreliable parallax by a colour-guided, confidence-weighted median.

    Flow is smooth across depth edges, so along every occlusion boundary the
    triangulated parallax mixes the foreground's and the background's: there the
    views disagree (a large residual) or many of them were dropped. Each such
    pixel (and each unknown one) takes the weighted median of the reliable
    parallaxes within ``radius`` px, each weighted by its confidence, by its colour
    similarity to the pixel in ``guide`` (Gaussian, ``sigma_colour`` in Lab units)
    and by its distance (Gaussian, ``sigma = radius``): a median takes one side's
    value, never a mixture, and the colour weight picks the side the pixel belongs
    to. A pixel whose window holds almost no reliable weight of its own colour
    (``support < min_support``) is not filled from it. Pixels unknown after that
    (unknown ones, and those) get a second, wider pass (twice the radius and colour
    tolerance, weak weights on the first pass's results); an unreliable pixel with
    nothing reliable around keeps its value. Low confidence
    alone (few views see a pixel, as near the edge of a lenslet's image circle) is
    not a reason to refill.
    Runs in the Rust core (``lfcam._lfcam.weighted_median_fill``).

    Parameters
    ----------
    parallax, confidence : (H, W) float arrays
        From :func:`lfcam.triangulate`.
    guide : (H, W, C) float array
        From :func:`guide_image` of the reference view.
    residual, n_used : (H, W) arrays, optional
        From :func:`lfcam.triangulate`: pixels with ``residual > max_residual`` or
        ``n_used < min_used * n_seen`` are refilled.
    n_seen : (H, W) int array, optional
        Views whose flow lands inside their data at each pixel, consistent or not.
    where : (H, W) bool array, optional
        Pixels that may be filled (default: all): where the reference and at least
        one other view see, so that nothing is extrapolated beyond the data.
    max_residual, min_used : float
        See :data:`FILL_MAX_RESIDUAL`, :data:`FILL_MIN_USED`.
    min_support : float
        See :data:`FILL_MIN_SUPPORT`; 0 (default) switches the test off.
    threshold : float, optional
        Also refill pixels whose confidence is below this.
    radius, stride : int
        Window radius and sampling step, px.
    sigma_colour : float
        Colour tolerance, Lab units (L runs 0..100).

    Returns
    -------
    parallax : (H, W) float32
        Filled parallax (NaN where nothing could be filled or outside ``where``).
    confidence : (H, W) float32
        The input confidence; at filled pixels half the share of the window's
        weight that supported the median (so at most 0.5).
    filled : (H, W) bool
        Where the parallax was replaced.
    """
    from . import _lfcam

    s = np.ascontiguousarray(parallax, np.float32)
    c = np.nan_to_num(np.asarray(confidence, np.float32), nan=0.0)
    if s.ndim != 2 or c.shape != s.shape:
        raise InputError(
            f"parallax, confidence: expected two (H, W) arrays of one shape,"
            f" got {s.shape} and {c.shape}"
        )
    g = np.ascontiguousarray(guide, np.float32)
    if g.ndim == 2:
        g = g[..., None]
    allowed = np.ones(s.shape, bool) if where is None else np.asarray(where, bool)
    if g.shape[:2] != s.shape or allowed.shape != s.shape:
        raise InputError(f"guide, where: expected shape {s.shape}, got {g.shape} / {allowed.shape}")
    unsure = ~np.isfinite(s)
    for name, arr in (("residual", residual), ("n_used", n_used), ("n_seen", n_seen)):
        if arr is not None and np.shape(arr) != s.shape:
            raise InputError(f"{name}: expected shape {s.shape}, got {np.shape(arr)}")
    unsure |= _unsure(residual, n_used, n_seen, max_residual, min_used)
    if threshold is not None:
        unsure |= c < threshold
    weights = np.where(unsure, 0.0, c).astype(np.float32)
    todo = (unsure & allowed).astype(np.uint8)
    out, support = _lfcam.weighted_median_fill(
        s, weights, g, todo, int(radius), int(stride), float(sigma_colour), float(radius)
    )
    # Too little reliable weight of the pixel's own colour: the median would be the
    # other side's. Such pixels join the unknown ones in the second pass.
    weak = (todo > 0) & (support < min_support)
    out = np.where(weak, np.nan, out)
    # A second, wider pass only for those and for unknown pixels: an unreliable value
    # with nothing reliable nearby is a better guess than values from further away.
    missing = (~np.isfinite(out) & (~np.isfinite(s) | weak) & allowed).astype(np.uint8)
    if missing.any():
        w2 = np.where(np.isfinite(out), np.maximum(weights, 0.1), 0.0).astype(np.float32)
        out2, support2 = _lfcam.weighted_median_fill(
            out,
            w2,
            g,
            missing,
            2 * int(radius),
            2 * int(stride),
            2 * float(sigma_colour),
            2 * float(radius),
        )
        out, support = out2, np.where(missing > 0, 0.5 * support2, support)
    filled = (todo > 0) & np.isfinite(out)
    # Where nothing could be filled, the unreliable value is still the best guess.
    out = np.where(filled | (todo == 0), out, s)
    out = np.where(allowed, out, np.nan).astype(np.float32)
    conf = np.where(filled, 0.5 * np.clip(support, 0.0, 1.0), c)
    conf = np.where(np.isfinite(out), conf, 0.0).astype(np.float32)
    return out, conf, filled


def depth_from_parallax(s: np.ndarray, z_b: float, z_c: float) -> np.ndarray:
    """``Z = Z_c + (Z_b - Z_c) / (1 - s)``; NaN where ``s >= 1`` (beyond infinity)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z = z_c + (z_b - z_c) / (1.0 - s)
    return np.where(s < 1.0, z, np.nan).astype(np.float32)


def depth_from_views(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    *,
    flow: FlowParams | None = None,
    threads: int = 2,
    fill: bool = True,
    backward: bool = True,
    **triangulation: Any,
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
    flow : FlowParams, optional
        DIS parameters (default :func:`depth_flow` of the flow window's size).
    threads : int
        Concurrent flows.
    fill : bool
        Refill unconfident pixels (occlusion bands, failed flows) with
        :func:`fill_parallax` guided by the reference view (default). False gives
        the bare triangulation.
    backward : bool
        Also compute the flows back from each view for a forward-backward
        consistency check (default; about twice the flow time).
    **triangulation
        Passed to :func:`lfcam.triangulate` (``cutoff``, ``sigma_floor``, ...).

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
    import time

    from .triangulate import triangulate

    views = np.asarray(views)
    if views.ndim not in (3, 4) or views.shape[0] < 2:
        raise InputError(f"views: expected (N, H, W[, C]) with N >= 2, got shape {views.shape}")
    if views.dtype != np.float32:
        views = views.astype(np.float32)
    offsets = np.asarray(offsets, np.float64)
    if offsets.shape != (views.shape[0], 2) or not np.isfinite(offsets).all():
        raise InputError(
            f"offsets: expected finite (N, 2) = ({views.shape[0]}, 2), got {offsets.shape}"
        )
    from .triangulate import MAX_VIEWS

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
    margin = int(np.ceil(FLOW_MARGIN * np.abs(offsets).max())) + 16
    flows, weights, seen, win = _flows_and_seen(
        views, int(reference), flow, FB_THRESHOLD, threads, margin=margin, backward=backward
    )
    t1 = time.perf_counter()
    tri = triangulate(flows, offsets, int(reference), weights, **triangulation)
    n_seen = seen.sum(axis=0, dtype=np.uint8)
    out = {k: getattr(tri, k) for k in _TRI_FIELDS}
    near = near_views(offsets, int(reference))
    if near is not None:
        # Where all views together are unsure, the near views' own triangulation.
        ref_near = int(np.searchsorted(near, int(reference)))
        tri_near = triangulate(flows[near], offsets[near], ref_near, weights[near], **triangulation)
        seen_near = seen[near].sum(axis=0, dtype=np.uint8)
        unsure_all = _unsure(tri.residual, tri.n_used, n_seen, FILL_MAX_RESIDUAL, FILL_MIN_USED)
        unsure_near = _unsure(
            tri_near.residual, tri_near.n_used, seen_near, FILL_MAX_RESIDUAL, FILL_MIN_USED
        )
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
    if fill:
        parallax, confidence, filled = fill_parallax(
            parallax,
            confidence,
            guide_image(views[(int(reference), *win)]),
            residual=out["residual"],
            n_used=out["n_used"],
            n_seen=n_seen,
            where=n_seen > 0,
            min_support=FILL_MIN_SUPPORT if len(offsets) >= FILL_SUPPORT_MIN_VIEWS else 0.0,
        )
        timings["fill"] = time.perf_counter() - t2
    shape = views.shape[1:3]
    return DepthResult(
        parallax=_paste(parallax, win, shape, np.nan),
        confidence=_paste(confidence, win, shape, 0),
        residual=_paste(out["residual"], win, shape, np.nan),
        perpendicular=_paste(out["perpendicular"], win, shape, np.nan),
        n_used=_paste(out["n_used"], win, shape, 0),
        filled=None if filled is None else _paste(filled, win, shape, False),
        timings=timings,
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


def estimate_depth(views: np.ndarray, cal: Calibration, **kwargs: Any) -> DepthResult:
    """Depth of one capture from its rectified views and the camera's calibration.

    Parameters
    ----------
    views : (N, H_rect, W_rect, C) float array
        From :func:`lfcam.rectify`.
    cal : Calibration
        The camera.
    **kwargs
        Passed to :func:`depth_from_views`.

    Returns
    -------
    DepthResult
        With ``depth`` in metres (metric calibrations) or ``relative``
        (``t = s Z_c / Z_b``, triangulated against ``d_i``) otherwise.
    """
    if views.shape[0] != cal.n_views or tuple(views.shape[1:3]) != tuple(cal.rect_shape):
        raise InputError(
            f"views: shape {views.shape} does not match the calibration"
            f" ({cal.n_views}, {cal.rect_shape[0]}, {cal.rect_shape[1]}, C)"
        )
    res = depth_from_views(views, cal.offsets, cal.reference, **kwargs)
    if cal.metric:
        res.depth = depth_from_parallax(res.parallax, cal.z_b, cal.z_c)
    else:
        res.relative = res.parallax
    return res
