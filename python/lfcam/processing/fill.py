"""Refilling unreliable parallax: a colour-guided, confidence-weighted median of the
reliable neighbours (the Rust core's ``weighted_median_fill``).

Flow is smooth across depth edges, so along every occlusion boundary the triangulated
parallax mixes the foreground's and the background's; those pixels, and the unknown
ones, take the value of the side whose colour they share.
"""

from __future__ import annotations

import cv2
import numpy as np

import lfcam._lfcam as _lfcam

from ..errors import InputError

__all__ = ["FILL_MAX_RESIDUAL", "FILL_MIN_USED", "fill_parallax", "guide_image", "unsure"]

#: Default of :attr:`DepthParams.fill_max_residual` (px).
FILL_MAX_RESIDUAL = 0.2
#: Default of :attr:`DepthParams.fill_min_used`.
FILL_MIN_USED = 0.75


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


def unsure(
    residual: np.ndarray | None,
    n_used: np.ndarray | None,
    n_seen: np.ndarray | None,
    max_residual: float,
    min_used: float,
) -> np.ndarray | bool:
    """Where a triangulation is not to be trusted: the views disagree (``residual >
    max_residual``) or it lost more than ``1 - min_used`` of the views that see it."""
    out: np.ndarray | bool = False
    if residual is not None:
        with np.errstate(invalid="ignore"):
            out = out | (np.asarray(residual, np.float32) > max_residual)
    if n_used is not None and n_seen is not None:
        out = out | (np.asarray(n_used, np.float32) < min_used * np.asarray(n_seen, np.float32))
    return out


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
        See :class:`~lfcam.processing.depth.DepthParams` (``fill_max_residual``,
        ``fill_min_used``).
    min_support : float
        See :attr:`DepthParams.fill_min_support`; 0 (default) switches the test off.
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
    bad = ~np.isfinite(s)
    for name, arr in (("residual", residual), ("n_used", n_used), ("n_seen", n_seen)):
        if arr is not None and np.shape(arr) != s.shape:
            raise InputError(f"{name}: expected shape {s.shape}, got {np.shape(arr)}")
    bad |= unsure(residual, n_used, n_seen, max_residual, min_used)
    if threshold is not None:
        bad |= c < threshold
    weights = np.where(bad, 0.0, c).astype(np.float32)
    todo = (bad & allowed).astype(np.uint8)
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
