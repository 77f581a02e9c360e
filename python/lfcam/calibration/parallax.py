"""Calibration step 4: the depth model, ``o_i`` and ``Z_c``, from the board's parallax.

A fronto-parallel board at distance ``Z_k`` shifts view i, in the reference distance's
rectified frame, by ``P_ik = o_i s_k`` with ``s_k = (Z_k - Z_b) / (Z_k - Z_c)``
(docs/design.md, "Parallax fit"). The shifts are measured by optical flow from
the reference view and checked against the lenslet lattice; ``o_i`` and ``Z_c`` are
then fitted by least squares.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

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

__all__ = [
    "LATTICE_TOLERANCE_PX",
    "LATTICE_TOLERANCE_REL",
    "fit_depth_model",
    "invert_map",
    "lattice_check",
    "measure_parallax",
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


def measure_parallax(
    views: np.ndarray,
    masks: np.ndarray,
    ref: int,
    params: FlowParams,
    init: dict[int, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Median flow from the reference to each view (rectified board images).

    ``init`` maps a view index to an expected shift ``(2,)`` that starts its flow
    (and restricts the measurement to those views; the others get NaN).
    Returns the parallax ``(N, 2)``, the valid fraction ``(N,)`` and the flows'
    robust spread ``(N,)``.
    """
    N = views.shape[0]
    a = prepare(views[ref])
    grid = identity_grid(*a.shape[:2])
    out = np.full((N, 2), np.nan) if init else np.zeros((N, 2))
    cover = np.zeros(N)
    spread = np.zeros(N)
    for i in range(N):
        if i == ref:
            out[i] = 0.0
            cover[i] = 1.0
            continue
        if init and i not in init:
            continue
        both = (
            masks[i] & masks[ref] & np.isfinite(views[i]).all(-1) & np.isfinite(views[ref]).all(-1)
        )
        both = cv2.erode(both.astype(np.uint8), np.ones((ERODE_PX,) * 2, np.uint8)) > 0
        start = None
        if init:
            start = np.broadcast_to(np.asarray(init[i], np.float32), (*a.shape[:2], 2))
        v = prepare(views[i])
        f = dis_flow(a, v, params, init=start)
        b = dis_flow(v, a, params, init=None if start is None else -start)
        # Forward-backward check: follow the flow and come back.
        back = remap(b, grid + f)
        fb = np.linalg.norm(f + back, axis=-1)
        # The board must land inside view i's mask too.
        land = remap(masks[i].astype(np.float32), grid + f)
        good = both & (fb < FB_THRESHOLD_PX) & (land > 0.99)
        cover[i] = good.sum() / max(both.sum(), 1)
        if good.sum() < MIN_GOOD_PIXELS:
            out[i] = np.nan
            continue
        out[i] = np.median(f[good], axis=0)
        spread[i] = float(np.median(np.abs(f[good] - out[i]))) * 1.4826
    return out, cover, spread


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
