"""Calibration step 3: dense warp maps from board captures (docs/design.md, "Geometric
registration").

For each view: a coarse global alignment of the pattern (SIFT features and a
RANSAC homography), then OpenCV DIS optical flow between the pattern and the
view resampled through the current map, composed into the map and iterated
until the residual flow vanishes; the maps of several captures are averaged
robustly (per-pixel median) and smoothed, and a validity mask is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import CalibrationError
from ..kernels.flow import FlowParams, dis_flow, prepare
from ..kernels.stats import nan_median
from ..kernels.warp import identity_grid, remap

__all__ = ["ViewRegistration", "coarse_homography", "register_view", "smooth_map"]

#: SIFT features per image, and the fewest keypoints and ratio-test matches (Lowe's
#: ratio ``LOWE_RATIO``) with which the pattern counts as found in a view.
SIFT_FEATURES = 4000
MIN_MATCHES = 20
LOWE_RATIO = 0.8
#: MAGSAC's inlier threshold (px) and the fewest inliers of an accepted homography.
HOMOGRAPHY_THRESHOLD_PX = 3.0
MIN_INLIERS = 15
#: A blank area of the pattern is bridged by a cubic fit over this many px around it,
#: from at least HOLE_FIT_MIN_PIXELS known pixels.
HOLE_FIT_MARGIN = 60
HOLE_FIT_MIN_PIXELS = 200
#: The flow/compose iterations stop when the median update is below this (px); a view
#: whose last update exceeds MAX_LAST_UPDATE_PX did not converge.
CONVERGED_PX = 0.01
MAX_LAST_UPDATE_PX = 0.5


def coarse_homography(pattern: np.ndarray, view: np.ndarray, *, name: str) -> np.ndarray:
    """Homography from pattern (rectified) coordinates to view-crop coordinates.

    SIFT features on contrast-normalised images, Lowe's ratio test, MAGSAC.

    Raises
    ------
    lfcam.CalibrationError
        If the pattern cannot be found in the view.
    """
    sift = cv2.SIFT_create(nfeatures=SIFT_FEATURES)
    a = prepare(pattern, sigma=12.0)
    b = prepare(view, sigma=12.0)
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    if da is None or db is None or len(ka) < MIN_MATCHES or len(kb) < MIN_MATCHES:
        raise CalibrationError(f"{name}: too little texture to find the calibration pattern")
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(db, da, k=2)
    good = [
        m for m, n in (p for p in matches if len(p) == 2) if m.distance < LOWE_RATIO * n.distance
    ]
    if len(good) < MIN_MATCHES:
        raise CalibrationError(
            f"{name}: the calibration pattern is not recognisable ({len(good)} feature matches);"
            " is this a capture of the pattern shown by pattern.png?"
        )
    src = np.float32([ka[m.trainIdx].pt for m in good])
    dst = np.float32([kb[m.queryIdx].pt for m in good])
    H, inl = cv2.findHomography(
        src, dst, cv2.USAC_MAGSAC, HOMOGRAPHY_THRESHOLD_PX, maxIters=5000, confidence=0.9999
    )
    if H is None or int(inl.sum()) < MIN_INLIERS:
        raise CalibrationError(f"{name}: could not align the calibration pattern (too few inliers)")
    return H


def homography_map(H: np.ndarray, h: int, w: int) -> np.ndarray:
    g = identity_grid(h, w).reshape(-1, 2).astype(np.float64)
    p = np.column_stack([g, np.ones(len(g))]) @ H.T
    return (p[:, :2] / p[:, 2:3]).reshape(h, w, 2).astype(np.float32)


def low_texture(
    pattern: np.ndarray, *, sigma: float = 4.0, fraction: float = 0.08, grow: int = 10
) -> np.ndarray:
    """Where the pattern cannot anchor optical flow in both directions.

    The smaller eigenvalue of the local structure tensor (Gaussian window
    ``sigma``) below ``fraction`` of its median: blank areas and straight edges
    (the aperture problem), e.g. the white square and bars of the cross.
    """
    p = pattern.astype(np.float32)
    gx = cv2.Sobel(p, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(p, cv2.CV_32F, 0, 1, ksize=3)
    a = cv2.GaussianBlur(gx * gx, (0, 0), sigma)
    b = cv2.GaussianBlur(gx * gy, (0, 0), sigma)
    c = cv2.GaussianBlur(gy * gy, (0, 0), sigma)
    lam = (a + c) / 2 - np.sqrt(((a - c) / 2) ** 2 + b * b)
    low = (lam < fraction * np.median(lam)).astype(np.uint8)
    low = cv2.morphologyEx(low, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    return cv2.dilate(low, np.ones((2 * grow + 1,) * 2, np.uint8)) > 0


def fill_holes(
    warp: np.ndarray,
    base: np.ndarray,
    hole: np.ndarray,
    has: np.ndarray,
    margin: int = HOLE_FIT_MARGIN,
) -> np.ndarray:
    """Replace ``warp`` inside each ``hole`` by a cubic fit of ``warp - base`` around it.

    Only pixels where the view has data (``has``) support the fit.

    The map is smooth on the scale of a hole (tens of pixels), so a local cubic
    polynomial bridges it with errors far below those of flow on a blank area.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(hole.astype(np.uint8), connectivity=8)
    out = warp.copy()
    H, W = hole.shape
    for k in range(1, n):
        x, y, w, h = (int(v) for v in stats[k, :4])
        x0, y0 = max(x - margin, 0), max(y - margin, 0)
        x1, y1 = min(x + w + margin, W), min(y + h + margin, H)
        win = (slice(y0, y1), slice(x0, x1))
        d = warp[win] - base[win]
        known = ~hole[win] & has[win] & np.isfinite(d).all(-1)
        if known.sum() < HOLE_FIT_MIN_PIXELS:
            out[win][labels[win] == k] = np.nan
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        cx, cy, sc = (x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0, y1 - y0) / 2
        u, v = (xx - cx) / sc, (yy - cy) / sc
        terms = [np.ones_like(u), u, v, u * u, u * v, v * v, u**3, u * u * v, u * v * v, v**3]
        A = np.stack([t[known] for t in terms], 1)
        coef = np.linalg.lstsq(A, d[known].astype(np.float64), rcond=None)[0]
        sel = labels[win] == k
        Ah = np.stack([t[sel] for t in terms], 1)
        fill = (base[win][sel] + Ah @ coef).astype(np.float32)
        # Interpolate, do not extrapolate far: a hole pixel needs known pixels on
        # at least three of its four sides (left, right, above, below).
        kn = known.astype(np.uint8)
        sides = (
            np.maximum.accumulate(kn, axis=1)
            + np.maximum.accumulate(kn[:, ::-1], axis=1)[:, ::-1]
            + np.maximum.accumulate(kn, axis=0)
            + np.maximum.accumulate(kn[::-1], axis=0)[::-1]
        )
        fill[sides[sel] < 3] = np.nan
        out[win][sel] = fill
    return out


@dataclass
class ViewRegistration:
    """The pattern-to-view map of one view from one or more captures."""

    warp: np.ndarray  # (H, W, 2) float32, NaN where unknown
    mask: np.ndarray  # (H, W) bool
    residual: np.ndarray  # (H, W) float32: photometric residual (contrast units)
    iterations: int
    last_update: float  # median |flow| of the last iteration, px


def _refine(
    pattern_u8: np.ndarray,
    view: np.ndarray,
    warp: np.ndarray,
    params: FlowParams,
    iterations: int,
    base: np.ndarray,
    hole: np.ndarray,
) -> tuple[np.ndarray, float, int]:
    grid = identity_grid(*warp.shape[:2])
    last = np.inf
    done = 0
    for _ in range(iterations):
        done += 1
        resampled = remap(view, warp)
        # Where the view has no data, show the flow the pattern itself: at
        # convergence this is what the view would show there, so patches that
        # straddle the edge of the view's data are not biased by a blank.
        has = np.isfinite(resampled).all(-1) if resampled.ndim == 3 else np.isfinite(resampled)
        flow = dis_flow(pattern_u8, np.where(has, prepare(resampled), pattern_u8), params)
        new = fill_holes(remap(warp, grid + flow), base, hole, has)
        valid = np.isfinite(resampled).all(-1) if resampled.ndim == 3 else np.isfinite(resampled)
        valid &= ~hole
        last = float(np.median(np.linalg.norm(flow[valid], axis=-1))) if valid.any() else np.inf
        warp = new
        if last < CONVERGED_PX:
            break
    return warp, last, done


def smooth_map(warp: np.ndarray, base: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Mask-aware Gaussian smoothing of ``warp - base`` (the part beyond ``base``).

    ``base`` (a homography map) carries the large, nearly linear part, so
    smoothing the remainder biases the map very little, even at mask borders.
    """
    if sigma <= 0:
        return warp
    d = np.where(mask[..., None], warp - base, 0.0).astype(np.float32)
    m = mask.astype(np.float32)
    num = cv2.GaussianBlur(d, (0, 0), sigma)
    den = cv2.GaussianBlur(m, (0, 0), sigma)[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = base + num / den
    return np.where(mask[..., None], out, np.nan).astype(np.float32)


def register_view(
    pattern: np.ndarray,
    captures: list[np.ndarray],
    *,
    name: str,
    params: FlowParams | None = None,
    iterations: int = 4,
    smoothing: float = 3.0,
    max_residual: float = 1.0,
    erode: int = 0,
) -> ViewRegistration:
    """Register the pattern to one view from several captures of the board.

    Parameters
    ----------
    pattern : (H, W) float array
        The pattern resampled to the rectified frame, in [0, 1].
    captures : list of (h, w[, C]) float arrays
        The view's crop in each capture after photometric gains; NaN where masked.
    name : str
        For error messages (the view and folder).
    params : FlowParams, optional
        DIS parameters.
    iterations : int
        Flow/compose iterations on the mean of the captures.
    smoothing : float
        Sigma (px) of the final mask-aware smoothing.
    max_residual : float
        Pixels whose local photometric residual (contrast units) exceeds this are masked.
    erode : int
        Pixels this close to the edge of the view's data are masked.

    Returns
    -------
    ViewRegistration
    """
    params = params or FlowParams()
    mean = np.mean(np.stack(captures), axis=0)
    H = coarse_homography(pattern, mean, name=name)
    base = homography_map(H, *pattern.shape[:2])
    pat_u8 = prepare(pattern)
    hole = low_texture(pattern)
    warp, last, k = _refine(pat_u8, mean, base, params, iterations, base, hole)
    if not last < MAX_LAST_UPDATE_PX:
        raise CalibrationError(
            f"{name}: optical flow did not converge (last update {last:.2f} px);"
            " is the board flat and the pattern fully visible?"
        )
    # One more flow per capture, then the per-pixel median: robust to a capture
    # in which the board moved or something passed in front of it.
    if len(captures) > 1:
        maps = [_refine(pat_u8, c, warp, params, 1, base, hole)[0] for c in captures]
        warp = nan_median(np.stack(maps).astype(np.float32))[0]
    resampled = remap(mean, warp)
    valid = np.isfinite(resampled).all(-1) if resampled.ndim == 3 else np.isfinite(resampled)
    valid &= np.isfinite(warp).all(-1)
    res = np.abs(prepare(resampled).astype(np.float32) - pat_u8.astype(np.float32)) / 40.0
    res = cv2.GaussianBlur(res, (0, 0), 4.0)
    res[hole] = 0.0  # bridged by fill_holes; blank areas have no photometric residual
    mask = valid & (res < max_residual)
    if erode > 0:
        mask = cv2.erode(valid.astype(np.uint8), np.ones((2 * erode + 1,) * 2, np.uint8)) > 0
        mask &= res < max_residual
    warp = smooth_map(warp, base, mask, smoothing)
    return ViewRegistration(warp, mask, res.astype(np.float32), k, last)
