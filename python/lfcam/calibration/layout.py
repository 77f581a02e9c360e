"""Calibration step 1: the lenslet layout from white captures (docs/design.md, "Layout").

Finds the R x C lit regions (image circles clipped by each lenslet's baffle),
their sub-pixel bounding boxes, the common crop rectangle and each image
circle's centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import CalibrationError

__all__ = ["Layout", "find_layout"]

#: A pixel brighter than this share of the white capture's 99.5th percentile is lit.
LIT_THRESHOLD = 0.3
#: A white capture whose 99.5th percentile is below this (in [0, 1]) is black.
MIN_WHITE = 0.02
#: A bright region is an image circle when it holds more than this share of an
#: R x C cell's area, and the smallest is at least this share of the median.
MIN_REGION_SHARE = 0.15
MIN_AREA_RATIO = 0.5
#: Side (px) of the square that erodes a lit region before its brightness plateau
#: is fitted, and of the one that grows the fit back over the region's edge.
PLATEAU_ERODE = 9
PLATEAU_DILATE = 7
#: An edge crossing within this many px of the median crossing of its side is on a
#: straight (baffle) edge; a side with more than STRAIGHT_SHARE such crossings has one.
STRAIGHT_EDGE_PX = 0.7
STRAIGHT_SHARE = 0.2
#: Reweighting rounds of the robust circle fit, and the fewest 1-degree bins of the
#: edge it needs.
CIRCLE_ROUNDS = 6
MIN_EDGE_BINS = 30
#: The smallest usable view, px per side.
MIN_VIEW_PX = 16


@dataclass
class Layout:
    """Where the views are on the sensor.

    Attributes
    ----------
    crops : (N, 4) int64
        ``(x0, y0, w, h)`` per view, all of one size, row-major view order.
    centres : (N, 2) float64
        Image-circle centres (raw px).
    radii : (N,) float64
        Image-circle radii (raw px).
    boxes : (N, 4) float64
        Sub-pixel bounding boxes ``(left, top, right, bottom)`` of the lit regions.
    lit : (H, W) float32
        Fraction of each pixel that is lit (0..1), from the white image.
    """

    crops: np.ndarray
    centres: np.ndarray
    radii: np.ndarray
    boxes: np.ndarray
    lit: np.ndarray


def _plateau(gray: np.ndarray, labels: np.ndarray, n: int, stats: np.ndarray) -> np.ndarray:
    """Smooth brightness of each lit region (quadratic fit over its interior), per pixel."""
    out = np.zeros_like(gray)
    for k in range(n):
        x, y, w, h = (int(v) for v in stats[k, :4])
        sub = labels[y : y + h, x : x + w] == k + 1
        inner = cv2.erode(sub.astype(np.uint8), np.ones((PLATEAU_ERODE,) * 2, np.uint8)) > 0
        yy, xx = np.nonzero(inner)
        if len(yy) < 50:
            raise CalibrationError("white capture: a lit region is too small to measure")
        u = (xx - w / 2) / w
        v = (yy - h / 2) / h
        A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
        coef = np.linalg.lstsq(A, gray[y : y + h, x : x + w][inner], rcond=None)[0]
        Y, X = np.mgrid[0:h, 0:w]
        U, V = (X - w / 2) / w, (Y - h / 2) / h
        fit = (
            coef[0]
            + coef[1] * U
            + coef[2] * V
            + coef[3] * U * U
            + coef[4] * U * V
            + coef[5] * V * V
        )
        region = cv2.dilate(sub.astype(np.uint8), np.ones((PLATEAU_DILATE,) * 2, np.uint8)) > 0
        out[y : y + h, x : x + w][region] = fit[region]
    return out


def _crossings(f: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel 50% crossings of a lit-fraction window along ``axis``.

    Returns, per line, the first rising and the last falling crossing (NaN if none).
    A box-integrated step edge at L gives pixel values rising linearly from
    L - 0.5 to L + 0.5, so linear interpolation between pixel centres finds L.
    """
    g = f if axis == 1 else f.T
    above = g >= 0.5
    n_lines, n = g.shape
    first = np.full(n_lines, np.nan)
    last = np.full(n_lines, np.nan)
    idx = np.arange(n)
    for r in range(n_lines):
        a = above[r]
        if not a.any() or a.all():
            continue
        i0 = int(idx[a][0])
        i1 = int(idx[a][-1])
        if i0 > 0:
            lo, hi = g[r, i0 - 1], g[r, i0]
            first[r] = i0 - 1 + (0.5 - lo) / max(hi - lo, 1e-6)
        if i1 < n - 1:
            hi, lo = g[r, i1], g[r, i1 + 1]
            last[r] = i1 + (hi - 0.5) / max(hi - lo, 1e-6)
    return first, last


def _fit_circle(pts: np.ndarray) -> tuple[np.ndarray, float]:
    A = np.column_stack([2 * pts, np.ones(len(pts))])
    sol = np.linalg.lstsq(A, (pts**2).sum(1), rcond=None)[0]
    c = sol[:2]
    r = float(np.sqrt(max(sol[2] + c @ c, 0.0)))
    return c, r


def _circle_from_edge(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Robust circle through edge points; drops straight (baffle) edges and outliers.

    Points are re-weighted to be uniform in angle around the centre (averaged in
    1-degree bins), so the fit does not depend on how the edge was scanned.
    """
    keep = np.ones(len(pts), bool)
    c, r = _fit_circle(pts)
    for _ in range(CIRCLE_ROUNDS):
        res = np.abs(np.linalg.norm(pts - c, axis=1) - r)
        keep = res < max(1.0, 3.0 * np.median(res[keep]) * 1.4826)
        ang = np.arctan2(pts[keep, 1] - c[1], pts[keep, 0] - c[0])
        bins = np.floor((ang + np.pi) / (2 * np.pi) * 360).astype(int)
        sums = np.zeros((360, 2))
        cnt = np.zeros(360)
        np.add.at(sums, bins, pts[keep])
        np.add.at(cnt, bins, 1)
        binned = sums[cnt > 0] / cnt[cnt > 0, None]
        if len(binned) < MIN_EDGE_BINS:
            raise CalibrationError("white capture: too little of an image circle's edge is visible")
        c, r = _fit_circle(binned)
    return c, r


def find_layout(white: np.ndarray, grid: tuple[int, int], *, name: str = "white") -> Layout:
    """Find the R x C views in a white image.

    Parameters
    ----------
    white : (H, W) or (H, W, C) float array
        The mean of the white captures, in [0, 1].
    grid : (int, int)
        Expected lenslet rows and columns.
    name : str
        What to call the image in error messages (e.g. its folder).

    Returns
    -------
    Layout

    Raises
    ------
    lfcam.CalibrationError
        If the image does not show R x C bright regions of similar size.
    """
    R, C = grid
    gray = (white.max(axis=2) if white.ndim == 3 else white).astype(np.float32)
    top = float(np.percentile(gray, 99.5))
    if not top > MIN_WHITE:
        raise CalibrationError(f"{name}: the white capture is black (max {top:.3f})")
    binary = (gray > LIT_THRESHOLD * top).astype(np.uint8)
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    n, labels, stats, cent = cv2.connectedComponentsWithStats(binary, connectivity=4)
    big = [k for k in range(1, n) if stats[k, 4] > MIN_REGION_SHARE * gray.size / (R * C)]
    if len(big) != R * C:
        raise CalibrationError(
            f"{name}: found {len(big)} bright regions, expected {R} x {C} = {R * C} image circles"
            " (is this a white-target capture? is the grid right?)"
        )
    # Relabel 1..N in row-major order of the grid.
    order = sorted(big, key=lambda k: cent[k, 1])
    rows = [sorted(order[r * C : (r + 1) * C], key=lambda k: cent[k, 0]) for r in range(R)]
    ordered = [k for row in rows for k in row]
    ys = np.array([[cent[k, 1] for k in row] for row in rows])
    if R > 1 and not (ys.max(axis=1)[:-1] < ys.min(axis=1)[1:]).all():
        raise CalibrationError(f"{name}: the bright regions do not form a {R} x {C} grid")
    remap = np.zeros(n, np.int32)
    for new, k in enumerate(ordered):
        remap[k] = new + 1
    labels = remap[labels]
    stats = stats[ordered]
    areas = stats[:, 4].astype(float)
    if areas.min() < MIN_AREA_RATIO * np.median(areas):
        raise CalibrationError(f"{name}: the image circles differ too much in size")
    plateau = _plateau(gray, labels, R * C, stats)
    with np.errstate(invalid="ignore", divide="ignore"):
        lit = np.where(plateau > 0, gray / plateau, 0.0).astype(np.float32)
    boxes = np.empty((R * C, 4))
    centres = np.empty((R * C, 2))
    radii = np.empty(R * C)
    for k in range(R * C):
        x, y, w, h = (int(v) for v in stats[k, :4])
        x0, y0 = max(x - 3, 0), max(y - 3, 0)
        x1, y1 = min(x + w + 3, gray.shape[1]), min(y + h + 3, gray.shape[0])
        sub = lit[y0:y1, x0:x1] * (
            cv2.dilate((labels[y0:y1, x0:x1] == k + 1).astype(np.uint8), np.ones((5, 5), np.uint8))
            > 0
        )
        left, right = _crossings(sub, axis=1)
        up, down = _crossings(sub, axis=0)

        def lo(v: np.ndarray) -> float:
            return float(np.sort(v[np.isfinite(v)])[:3].mean())

        def hi(v: np.ndarray) -> float:
            return float(np.sort(v[np.isfinite(v)])[-3:].mean())

        boxes[k] = [x0 + lo(left), y0 + lo(up), x0 + hi(right), y0 + hi(down)]
        ry = np.arange(y0, y1, dtype=float)
        rx = np.arange(x0, x1, dtype=float)
        sets = []
        for along, across, vertical in (
            (left, ry, True),
            (right, ry, True),
            (up, rx, False),
            (down, rx, False),
        ):
            ok = np.isfinite(along)
            e, t = along[ok], across[ok]
            # A baffle edge is a straight run: many crossings at the same position.
            straight = np.abs(e - np.median(e)) < STRAIGHT_EDGE_PX
            if straight.mean() > STRAIGHT_SHARE:
                e, t = e[~straight], t[~straight]
            off = x0 if vertical else y0
            sets.append(
                np.column_stack([off + e, t]) if vertical else np.column_stack([t, off + e])
            )
        pts = np.concatenate(sets)
        centres[k], radii[k] = _circle_from_edge(pts)
    w = int(np.floor((boxes[:, 2] - boxes[:, 0]).min())) - 1
    h = int(np.floor((boxes[:, 3] - boxes[:, 1]).min())) - 1
    if w < MIN_VIEW_PX or h < MIN_VIEW_PX:
        raise CalibrationError(f"{name}: the lit regions are too small ({w} x {h} px)")
    x0s = np.round((boxes[:, 0] + boxes[:, 2]) / 2 - (w - 1) / 2).astype(np.int64)
    y0s = np.round((boxes[:, 1] + boxes[:, 3]) / 2 - (h - 1) / 2).astype(np.int64)
    crops = np.stack([x0s, y0s, np.full_like(x0s, w), np.full_like(y0s, h)], 1)
    return Layout(crops, centres, radii, boxes, lit)
