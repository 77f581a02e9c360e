"""Calibration step 4: the depth model, ``o_i`` and ``Z_c``, from the board's parallax.

A fronto-parallel board at distance ``Z_k`` shifts view i, in the reference distance's
rectified frame, by ``P_ik = o_i s_k`` with ``s_k = (Z_k - Z_b) / (Z_k - Z_c)``
(docs/design.md, "Parallax fit"). The shifts are measured by optical flow from
the reference view and checked against the lenslet lattice; ``o_i`` and ``Z_c`` are
then fitted by least squares.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

import lfcam._lfcam as _lfcam

from ..kernels.flow import FlowParams, dis_flow, prepare
from ..kernels.warp import identity_grid, remap

#: Newton iterations (at most) of :func:`invert_map`, and the step (px) that ends them.
NEWTON_ITERATIONS = 20
NEWTON_TOLERANCE_PX = 1e-4
#: :func:`fit_depth_model` scans ``Z_c`` on this many points, then refines by this many
#: golden-section steps.
Z_C_SCAN = 400
GOLDEN_STEPS = 80
#: :func:`measure_parallax`: the views' common area is eroded by a square of this side
#: (px); a flow passes where its forward-backward round trip misses by less than
#: FB_THRESHOLD_PX, and a view needs MIN_GOOD_PIXELS passing pixels.
ERODE_PX = 9
FB_THRESHOLD_PX = 0.5
MIN_GOOD_PIXELS = 500
#: :func:`measure_parallax`'s cells (px) and the passing pixels a cell needs.
CELL_PX = 32
CELL_MIN_PIXELS = 256

__all__ = [
    "LATTICE_TOLERANCE_PX",
    "LATTICE_TOLERANCE_REL",
    "MAX_TILT_DEG",
    "ParallaxMeasurement",
    "depth_change",
    "fit_board_poses",
    "fit_depth_model",
    "invert_map",
    "lattice_check",
    "less_reference",
    "measure_parallax",
    "tilt_degrees",
]


def invert_map(warp: np.ndarray, mask: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The rectified position ``(u, v)`` whose warp is ``xy`` (Newton on the map).

    Returns NaN if ``xy`` is not inside the masked map.
    """
    ok = mask & np.isfinite(warp).all(-1)
    if not ok.any():
        return np.full(2, np.nan)
    vv, uu = np.nonzero(ok)
    d = np.linalg.norm(warp[vv, uu] - xy, axis=1)
    k = int(np.argmin(d))
    u, v = float(uu[k]), float(vv[k])
    H, W = warp.shape[:2]
    for _ in range(NEWTON_ITERATIONS):
        iu, iv = min(max(int(u), 1), W - 2), min(max(int(v), 1), H - 2)
        J = np.column_stack(
            [
                (warp[iv, iu + 1] - warp[iv, iu - 1]) / 2.0,
                (warp[iv + 1, iu] - warp[iv - 1, iu]) / 2.0,
            ]
        ).astype(np.float64)
        cur = remap(warp, np.array([[[u, v]]], np.float32))[0, 0].astype(np.float64)
        if not np.isfinite(cur).all() or not np.isfinite(J).all():
            return np.full(2, np.nan)
        step = np.linalg.solve(J, xy - cur)
        u, v = u + step[0], v + step[1]
        if np.abs(step).max() < NEWTON_TOLERANCE_PX:
            break
    return np.array([u, v])


def fit_depth_model(
    parallax: dict[float, np.ndarray], z_b: float, centres_rect: np.ndarray | None = None
) -> dict[str, Any]:
    """Least-squares ``o_i`` and ``Z_c`` from measured parallax (docs/design.md, "Parallax fit").

    ``parallax[Z_k]`` is ``(N, 2)``: view i's board shift at distance ``Z_k`` in the
    reference distance's rectified frame, ``P_ik = o_i s_k`` with
    ``s_k = (Z_k - Z_b) / (Z_k - Z_c)``. ``centres_rect`` (``d_i = o_i Z_b / Z_c``)
    adds equations (needed with only two distances).

    A one-dimensional problem in ``Z_c`` (``o_i`` is linear given it), solved by a
    dense scan and golden-section refinement; the system is ``2N x K``, far too
    small for a sparse or iterative solver.
    """
    zs = np.array(sorted(parallax))
    P = np.stack([parallax[z] for z in zs])  # (K, N, 2)

    def solve(z_c: float) -> tuple[float, np.ndarray]:
        s = (zs - z_b) / (zs - z_c)  # (K,)
        num = np.einsum("k,kni->ni", s, P)
        den = float(s @ s)
        if centres_rect is not None:
            r = z_b / z_c
            num = num + r * centres_rect
            den = den + r * r
        o = num / den
        res = (P - s[:, None, None] * o[None]) ** 2
        cost = float(res.sum())
        if centres_rect is not None:
            cost += float(((centres_rect - o * z_b / z_c) ** 2).sum())
        return cost, o

    hi = min(min(zs), z_b) * 0.98
    grid = np.linspace(hi * 0.01, hi, Z_C_SCAN)
    costs = [solve(z)[0] for z in grid]
    k = int(np.argmin(costs))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    g = (math.sqrt(5) - 1) / 2
    for _ in range(GOLDEN_STEPS):
        c, d = b - g * (b - a), a + g * (b - a)
        if solve(c)[0] < solve(d)[0]:
            b = d
        else:
            a = c
    z_c = (a + b) / 2
    _, o = solve(z_c)
    s = (zs - z_b) / (zs - z_c)
    resid = P - s[:, None, None] * o[None]
    return {
        "z_c": float(z_c),
        "offsets": o,
        "s": {f"{z:g}": float(v) for z, v in zip(zs, s)},
        "residual_rms_px": float(np.sqrt((resid**2).mean())),
        "residual_max_px": float(np.abs(resid).max()),
    }


@dataclass
class ParallaxMeasurement:
    """The board's parallax from the reference view to every view (:func:`measure_parallax`)."""

    #: ``(N, 2)`` median shift of each view (NaN: not measured), rectified px.
    shift: np.ndarray
    #: ``(N,)`` share of the views' common area where the flow passed its checks.
    coverage: np.ndarray
    #: ``(N,)`` robust spread of the flow about the median, px.
    spread: np.ndarray
    #: View index -> ``(pos (M, 2), shift (M, 2))``: the median shift over each cell of
    #: CELL_PX x CELL_PX rectified px with at least CELL_MIN_PIXELS passing pixels, at
    #: their mean position (the samples of :func:`fit_board_poses`).
    cells: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


def _cell_medians(good: np.ndarray, flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.nonzero(good)
    ncx = -(-good.shape[1] // CELL_PX)
    cell = (ys // CELL_PX) * ncx + xs // CELL_PX
    order = np.argsort(cell, kind="stable")
    cell, ys, xs = cell[order], ys[order], xs[order]
    f = flow[ys, xs]
    starts = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    ends = np.r_[starts[1:], len(cell)]
    pos, shift = [], []
    for a, b in zip(starts, ends):
        if b - a >= CELL_MIN_PIXELS:
            pos.append((xs[a:b].mean(), ys[a:b].mean()))
            shift.append(np.median(f[a:b], axis=0))
    return np.asarray(pos, np.float64).reshape(-1, 2), np.asarray(shift, np.float64).reshape(-1, 2)


#: A view resampled at ``p + shift`` (and its mask) for the second pass of
#: :func:`measure_parallax`: ``resample(i, shift)``.
Resample = Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]


def _flow_pass(
    a: np.ndarray,
    grid: np.ndarray,
    view: np.ndarray,
    mask: np.ndarray,
    both: np.ndarray,
    params: FlowParams,
    start: np.ndarray | None,
    round_trip: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Flow from the prepared reference ``a`` (pixel grid ``grid``) to ``view`` and the
    pixels it passes at: inside ``both``, landing inside ``mask`` and (``round_trip``)
    with a forward-backward round trip within FB_THRESHOLD_PX."""
    v = prepare(view)
    f = dis_flow(a, v, params, init=start)
    good = both & (remap(mask.astype(np.float32), grid + f) > 0.99)
    if round_trip:
        b = dis_flow(v, a, params, init=None if start is None else -start)
        good &= np.linalg.norm(f + remap(b, grid + f), axis=-1) < FB_THRESHOLD_PX
    return f, good


def measure_parallax(
    views: np.ndarray,
    masks: np.ndarray,
    ref: int,
    params: FlowParams,
    init: dict[int, np.ndarray] | None = None,
    resample: Resample | None = None,
) -> ParallaxMeasurement:
    """Median flow from the reference to each view (rectified board images), overall
    and per cell.

    ``init`` maps a view index to an expected shift ``(2,)`` that starts its flow
    (and restricts the measurement to those views; the others get NaN).

    With ``resample`` (view ``i`` rectified at ``p + shift`` from its raw crop, and
    its mask), the flow is measured twice: the second time against view ``i``
    resampled at its first median shift, so that the flow left is near zero, and the
    shift is that median plus the second flow. DIS's sub-pixel estimate is biased
    towards half-pixel shifts (by up to 0.006 px on an exactly shifted pattern, 0.02
    px on the simulator's boards), which on the shifts of about a pixel of a short
    focal length is a bias of 1% in the parallax (docs/design.md, "Parallax fit").
    """
    N = views.shape[0]
    a = prepare(views[ref])
    grid = identity_grid(*a.shape[:2])
    out = np.full((N, 2), np.nan) if init else np.zeros((N, 2))
    cover = np.zeros(N)
    spread = np.zeros(N)
    cells: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    finite_ref = masks[ref] & np.isfinite(views[ref]).all(-1)
    kernel = np.ones((ERODE_PX,) * 2, np.uint8)

    def common(view: np.ndarray, mask: np.ndarray) -> np.ndarray:
        both = mask & finite_ref & np.isfinite(view).all(-1)
        return cv2.erode(both.astype(np.uint8), kernel) > 0

    for i in range(N):
        if i == ref:
            out[i] = 0.0
            cover[i] = 1.0
            continue
        if init and i not in init:
            continue
        both = common(views[i], masks[i])
        start = None
        if init:
            start = np.broadcast_to(np.asarray(init[i], np.float32), (*a.shape[:2], 2))
        f, good = _flow_pass(a, grid, views[i], masks[i], both, params, start)
        if resample is not None and good.sum() >= MIN_GOOD_PIXELS:
            # The pixels the first flow passed at, measured again (forward only: its
            # round trip was checked).
            first = np.median(f[good], axis=0).astype(np.float32)
            view, mask = resample(i, first)
            both = common(view, mask)
            f, second = _flow_pass(a, grid, view, mask, both, params, None, round_trip=False)
            f, good = f + first, good & second
        cover[i] = good.sum() / max(both.sum(), 1)
        if good.sum() < MIN_GOOD_PIXELS:
            out[i] = np.nan
            continue
        out[i] = np.median(f[good], axis=0)
        spread[i] = float(np.median(np.abs(f[good] - out[i]))) * 1.4826
        cells[i] = _cell_medians(good, f)
    return ParallaxMeasurement(out, cover, spread, cells)


def less_reference(meas: ParallaxMeasurement, zero: ParallaxMeasurement) -> ParallaxMeasurement:
    """A board's parallax less the residual parallax ``zero`` of the reference board.

    On the reference board the parallax is zero by construction; what the flow
    measures there is the warp maps' registration error (and the flow's own bias on
    these images), which a board at any other distance shows too, at the same
    rectified position, to first order (docs/design.md, "Parallax fit"). Subtracted
    view by view and cell by cell (CELL_PX cells); a cell the reference board's flow
    did not pass is dropped, a view it did not measure keeps its shift.
    """
    shift = meas.shift - np.where(np.isfinite(zero.shift), zero.shift, 0.0)
    cells: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for i, (pos, par) in meas.cells.items():
        if i not in zero.cells:
            cells[i] = (pos, par)
            continue
        zpos, zpar = zero.cells[i]
        at = {(int(x), int(y)): v for (x, y), v in zip(zpos // CELL_PX, zpar)}
        keys = [(int(x), int(y)) for x, y in pos // CELL_PX]
        keep = np.array([k in at for k in keys], bool)
        if not keep.any():
            continue
        less = np.array([at[k] for k, ok in zip(keys, keep) if ok]).reshape(-1, 2)
        cells[i] = (pos[keep], par[keep] - less)
    return ParallaxMeasurement(shift, meas.coverage, meas.spread, cells)


#: A view's board shift may differ from the lenslet lattice's prediction by this
#: much (px, or this share of the largest shift, whichever is larger) before it is
#: measured again from the prediction (:func:`lattice_check`).
LATTICE_TOLERANCE_PX = 3.0
LATTICE_TOLERANCE_REL = 0.1


def lattice_check(P: np.ndarray, grid: tuple[int, int], ref: int) -> tuple[np.ndarray, np.ndarray]:
    """Views whose measured board shift breaks the lenslet lattice.

    A fronto-parallel board shifts view i by ``o_i s``, and on a lenslet grid ``o_i``
    is nearly affine in the view's column and row: ``P_i ~ A dc_i + B dr_i``. Fits the
    two 2-vectors by least squares, dropping the worst view while it is off by more
    than the tolerance (flow on a large shift can lock onto a wrong match: the
    full-size camera's far corner view at 0.7 m measured (-2, -51) px instead of
    (52, -19), and the whole depth model went wrong). Returns the prediction
    ``(N, 2)`` and the outliers ``(N,)`` (all False with too few views to tell).
    """
    R, C = grid
    rows, cols = np.divmod(np.arange(R * C), C)
    X = np.column_stack([cols - cols[ref], rows - rows[ref]]).astype(np.float64)
    finite = np.isfinite(P).all(1)
    inl = finite & (np.arange(len(P)) != ref)
    pred = np.zeros_like(P)  # too few views to fit: no prediction, no outliers
    tol = max(LATTICE_TOLERANCE_PX, LATTICE_TOLERANCE_REL * float(np.nanmax(np.abs(P))))
    while inl.sum() >= 4:
        coef, *_ = np.linalg.lstsq(X[inl], P[inl], rcond=None)
        pred = X @ coef
        err = np.where(finite, np.linalg.norm(P - pred, axis=1), np.inf)
        err[ref] = 0.0
        worst = int(np.argmax(np.where(inl, err, -1.0)))
        if err[worst] <= tol:
            out = ~inl & (err > tol)
            out[ref] = False
            return pred, out
        inl[worst] = False
    return pred, np.zeros(len(P), bool)


#: The nominal noise of a cell's median shift (px): the cells' weight, against which
#: the tilt prior below is set.
CELL_NOISE_PX = 0.05
#: Prior standard deviation of each board's tilt, degrees (with a known pattern pitch;
#: else GRADIENT_PRIOR_PX on the gradient): holds a tilt the views cannot see (across a
#: one-row grid) at zero, and is too wide to pull on one they see.
TILT_PRIOR_DEG = 10.0
GRADIENT_PRIOR_PX = 1e-4
#: The fit handles boards tilted by at most MAX_TILT_DEG degrees (with a known pattern
#: pitch; else, whose depth from the lenslet centres changes by at most
#: MAX_TILT_DEPTH_CHANGE across the frame): the frame is the tilted reference board's,
#: foreshortened by cos(tilt) (0.4% at 5 degrees), which the model leaves out.
MAX_TILT_DEG = 5.0
MAX_TILT_DEPTH_CHANGE = 0.03
#: A board whose cells miss the fitted model by more than this (px RMS) is a board
#: whose captures disagree (it moved, bent or was not flat).
MAX_BOARD_RMS_PX = 0.25


def fit_board_poses(
    measured: dict[float, ParallaxMeasurement],
    z_b: float,
    ref: int,
    centre: np.ndarray,
    start: dict[str, Any],
    *,
    centres_rect: np.ndarray | None = None,
    rect_pitch: float | None = None,
) -> dict[str, Any]:
    """``o_i``, ``Z_c`` and every board's tilt by nonlinear least squares (Rust core).

    ``measured[Z_k]`` holds board ``k``'s per-cell parallax; ``start`` is a
    fronto-parallel :func:`fit_depth_model` (the starting point); ``centre`` is where
    the reference lenslet's axis crosses the rectified frame (its image-circle centre
    there); ``centres_rect`` adds the optical-centre equations (two distances);
    ``rect_pitch`` (metres per rectified px at ``Z_b``) gives the tilts in degrees.
    A tilt is a board's depth gradient ``g`` (per rectified px, relative to ``Z_b -
    Z_c``): the board is ``w = w_k + g . (x - centre)`` in units of ``Z_b - Z_c``
    (docs/design.md, "Parallax fit"). The reference board is the frame's
    fronto-parallel plane: the others' tilts are relative to it (its own shows only
    through an effect too weak to measure under the flow's noise). The cells are
    weighted by a Cauchy loss (a cell whose flow locked onto a wrong match would tilt a
    least-squares fit, and with the tilt ``o_i`` and ``Z_c``).

    Returns
    -------
    dict
        ``z_c``, ``offsets`` ``(N, 2)``, their standard errors ``z_c_se``,
        ``offsets_se``, ``gradient_ref`` (the reference board), ``gradients`` (one per
        other board, ``zs`` order), their standard errors, ``board_rms_px``,
        ``board_downweighted`` (the share of each board's cells the robust loss weighs
        at less than half), ``rms_px``, ``iterations``, ``zs``.
    """
    zs = sorted(measured)
    board, view, pos, par = [], [], [], []
    for k, z in enumerate(zs):
        for i, (p, s) in sorted(measured[z].cells.items()):
            board.append(np.full(len(p), k))
            view.append(np.full(len(p), i))
            pos.append(p)
            par.append(s)
    n_samples = sum(len(b) for b in board)
    N = len(start["offsets"])
    z_c0 = float(start["z_c"])
    if rect_pitch is not None:
        prior = math.tan(math.radians(TILT_PRIOR_DEG)) * rect_pitch / (z_b - z_c0)
    else:
        prior = GRADIENT_PRIOR_PX
    # The optical centres weigh as much as one distance's cells of a view.
    per_view = n_samples / max(1, len(zs) * (N - 1)) / CELL_NOISE_PX**2
    fit = _lfcam.fit_board_tilts(
        np.concatenate(board).astype(np.int64),
        np.concatenate(view).astype(np.int64),
        np.ascontiguousarray(np.concatenate(pos), np.float64),
        np.ascontiguousarray(np.concatenate(par), np.float64),
        np.full(n_samples, 1.0 / CELL_NOISE_PX**2),
        np.asarray(zs, np.float64),
        float(z_b),
        int(ref),
        np.ascontiguousarray(start["offsets"], np.float64),
        z_c0,
        (float(centre[0]), float(centre[1])),
        float(prior),
        None if centres_rect is None else np.ascontiguousarray(centres_rect, np.float64),
        float(per_view),
        robust=True,
    )
    fit["offsets"] = np.asarray(fit["offsets"])
    fit["offsets_se"] = np.asarray(fit["offsets_se"])
    fit["zs"] = zs
    return fit


def tilt_degrees(gradient: np.ndarray, z_b: float, z_c: float, rect_pitch: float) -> list[float]:
    """A board's slope along x and y, degrees, from its depth gradient (per rectified px)."""
    g = np.asarray(gradient, np.float64) * (z_b - z_c) / rect_pitch
    return [math.degrees(math.atan(float(v))) for v in g]


def depth_change(gradient: np.ndarray, centre: np.ndarray, shape: tuple[int, int]) -> float:
    """The largest relative change of a board's depth (from the lenslet centres) over the
    rectified frame of ``shape`` (H, W), for its gradient (per px) about ``centre``."""
    H, W = shape
    corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], np.float64)
    return float(np.abs((corners - np.asarray(centre)) @ np.asarray(gradient)).max())
