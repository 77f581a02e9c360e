"""Depth refinement: a plane sweep along the calibrated parallax lines over all views
at once (docs/design.md, "Depth refinement").

The flow + triangulation estimate ``s0`` gives the scene's parallax range; the Rust
core's ``plane_sweep`` compares the reference with every view at candidate parallaxes
``s`` (pixel ``p`` against ``view_i(p + o_i s)``), with a truncated colour + gradient
cost aggregated by a guided filter (edge-aware), for all views together and for the
views on each side of the reference (half-planes: near an occluding edge only one
side sees the background). Per pixel the all-views result is kept unless a half-plane
fits clearly better; where the sweep and ``s0`` agree, ``s0`` (the flow's finer
sub-pixel value) is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import lfcam._lfcam as _lfcam

from ..errors import InputError

__all__ = ["RefineParams", "RefineResult", "half_planes", "refine_parallax", "sweep_costs"]


@dataclass(frozen=True)
class RefineParams:
    """Settings of the plane-sweep refinement. Lengths in px are measured at the view
    farthest from the reference, so that one set of values fits any layout; why each
    default is what it is: docs/tuning.md, "Depth refinement"."""

    #: Candidate spacing, px at the farthest view.
    step_px: float = 0.5
    #: The search range: ``s0``'s 0.5th .. 99.5th percentiles grown by this, px at the
    #: farthest view.
    margin_px: float = 1.0
    #: Truncation of the colour difference, in units of the reference's 99.5th
    #: percentile brightness.
    trunc_colour: float = 0.03
    #: Truncation of the grey gradient difference (same units per px).
    trunc_gradient: float = 0.01
    #: Weight of the gradient term (the colour term weighs ``1 - alpha``).
    alpha: float = 0.7
    #: Guided filter radius (px) and regularisation (squared brightness units).
    radius: int = 4
    eps: float = 1e-4
    #: Directions of the half-planes of views (0: all views only); ``2 * directions``
    #: half-planes, each the views with ``o_i . n > 0`` for a normal ``n``.
    directions: int = 2
    #: A half-plane's result replaces the all-views one where its minimum cost is below
    #: this share of the all-views minimum.
    subset_ratio: float = 0.9
    #: ``s0`` is kept where it lies within this of the sweep's result (px at the
    #: farthest view); 0: the sweep's result everywhere.
    agree_px: float = 0.5

    def __post_init__(self) -> None:
        for name in ("step_px", "trunc_colour", "trunc_gradient", "eps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (
                isinstance(v, (int, float)) and math.isfinite(v) and v > 0
            ):
                raise InputError(f"refine.{name}: expected a finite number > 0, got {v!r}")
        for name in ("margin_px", "agree_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (
                isinstance(v, (int, float)) and math.isfinite(v) and v >= 0
            ):
                raise InputError(f"refine.{name}: expected a finite number >= 0, got {v!r}")
        if not (0.0 <= self.alpha <= 1.0):
            raise InputError(f"refine.alpha: expected 0 .. 1, got {self.alpha!r}")
        if not (0.0 < self.subset_ratio <= 1.0):
            raise InputError(f"refine.subset_ratio: expected 0 < x <= 1, got {self.subset_ratio!r}")
        for name, hi in (("radius", 64), ("directions", 8)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not (0 <= v <= hi):
                raise InputError(f"refine.{name}: expected an integer 0 .. {hi}, got {v!r}")


@dataclass
class RefineResult:
    """The refined parallax and what it came from.

    Attributes
    ----------
    parallax : (H, W) float32
        Refined ``s``; NaN where the reference has no data.
    confidence : (H, W) float32
        0 .. 1 from the cost curve: the margin between its minimum and its lowest value
        at least two candidates away, relative to the latter.
    swept : (H, W) bool
        Pixels whose parallax comes from the sweep (not from ``s0``).
    """

    parallax: np.ndarray
    confidence: np.ndarray
    swept: np.ndarray


def half_planes(offsets: np.ndarray, reference: int, directions: int) -> np.ndarray:
    """(S, N) uint8 view subsets: all views but the reference, then for each of
    ``2 * directions`` normals ``n`` at angles ``pi k / directions`` the views with
    ``o_i . n > 0`` (empty ones and repeats left out)."""
    n = len(offsets)
    rows = [np.arange(n) != reference]
    for k in range(2 * directions):
        th = math.pi * k / directions
        side = offsets @ np.array([math.cos(th), math.sin(th)]) > 1e-9 * np.abs(offsets).max()
        side[reference] = False
        if side.any() and not any((side == r).all() for r in rows):
            rows.append(side)
    return np.array(rows, np.uint8)


def _scale(image: np.ndarray) -> float:
    """The reference's 99.5th percentile brightness (the cost's unit)."""
    finite = image[np.isfinite(image)]
    top = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    return top if top > 0 else 1.0


def candidates_for(s0: np.ndarray, offsets: np.ndarray, params: RefineParams) -> np.ndarray | None:
    """The candidate parallaxes: ``s0``'s 0.5 .. 99.5th percentiles grown by
    ``margin_px``, every ``step_px`` (px at the farthest view); None without ``s0``."""
    finite = s0[np.isfinite(s0)]
    reach = float(np.hypot(offsets[:, 0], offsets[:, 1]).max())
    if finite.size == 0 or reach <= 0:
        return None
    lo, hi = np.percentile(finite, [0.5, 99.5])
    lo -= params.margin_px / reach
    hi += params.margin_px / reach
    ds = params.step_px / reach
    k = max(3, math.ceil((hi - lo) / ds) + 1)
    return (lo + ds * np.arange(k)).astype(np.float32)


def sweep_costs(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    candidates: np.ndarray,
    subsets: np.ndarray,
    params: RefineParams,
) -> np.ndarray:
    """The Rust core's plane sweep over views already scaled to the cost's units:
    (H, W, S, 4) float32 with the parallax, minimum cost, curvature and second-best
    cost per pixel and subset."""
    v = np.ascontiguousarray(views, np.float32)
    if v.ndim == 3:
        v = v[..., None]
    out: np.ndarray = _lfcam.plane_sweep(
        v,
        np.ascontiguousarray(offsets, np.float64),
        int(reference),
        np.ascontiguousarray(candidates, np.float32),
        np.ascontiguousarray(subsets, np.uint8),
        params.trunc_colour,
        params.trunc_gradient,
        params.alpha,
        params.radius,
        params.eps,
    )
    return out


def refine_parallax(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    s0: np.ndarray,
    params: RefineParams | None = None,
) -> RefineResult:
    """Refine ``s0`` by a plane sweep along the parallax lines (module notes).

    Parameters
    ----------
    views : (N, H, W[, C]) float array
        Rectified views, NaN where a view has no data.
    offsets : (N, 2) array
        ``o_i``, px per unit ``s``.
    reference : int
        The reference view.
    s0 : (H, W) float array
        The flow + triangulation estimate (NaN: unknown).
    params : RefineParams, optional

    Returns
    -------
    RefineResult
    """
    p = params if params is not None else RefineParams()
    offsets = np.asarray(offsets, np.float64)
    s0 = np.asarray(s0, np.float32)
    cands = candidates_for(s0, offsets, p)
    ref_valid = (
        np.isfinite(views[reference]).all(-1) if views.ndim == 4 else np.isfinite(views[reference])
    )
    if cands is None:
        return RefineResult(s0.copy(), np.zeros_like(s0), np.zeros(s0.shape, bool))
    scale = _scale(views[reference])
    scaled = np.asarray(views, np.float32) / np.float32(scale)
    subsets = half_planes(offsets, reference, p.directions)
    out = sweep_costs(scaled, offsets, reference, cands, subsets, p)
    s_sub, cost, second = out[..., 0], out[..., 1], out[..., 3]
    # The all-views result unless a half-plane's minimum is clearly lower.
    pick = np.zeros(s0.shape, np.intp)
    if s_sub.shape[-1] > 1:
        ratio = cost[..., 1:] / np.maximum(cost[..., :1], 1e-12)
        best = ratio.argmin(-1)
        clearly = np.take_along_axis(ratio, best[..., None], -1)[..., 0] < p.subset_ratio
        pick = np.where(clearly, best + 1, 0)
    take = pick[..., None]
    s = np.take_along_axis(s_sub, take, -1)[..., 0]
    c_min = np.take_along_axis(cost, take, -1)[..., 0]
    c_2nd = np.take_along_axis(second, take, -1)[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        conf = np.clip((c_2nd - c_min) / np.maximum(c_2nd, 1e-12), 0.0, 1.0)
    conf = np.where(np.isfinite(conf), conf, 0.0).astype(np.float32)
    reach = float(np.hypot(offsets[:, 0], offsets[:, 1]).max())
    with np.errstate(invalid="ignore"):
        agree = np.abs(s - s0) <= p.agree_px / reach
    swept = ~agree & ref_valid
    parallax = np.where(swept, s, s0).astype(np.float32)
    parallax[~ref_valid] = np.nan
    return RefineResult(parallax, conf, swept)


def plane_sweep_numpy(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    candidates: np.ndarray,
    subsets: np.ndarray,
    params: RefineParams,
) -> np.ndarray:
    """The numpy reference of the Rust core's ``plane_sweep`` (:func:`sweep_costs`):
    the same cost, aggregation and minimum, computed over the whole cost volume. For
    tests and benchmarks; slow and memory-hungry (``K x S x H x W`` floats).

    Returns
    -------
    (H, W, S, 4) float32
        Parallax, minimum cost, curvature and second-best cost per pixel and subset.
    """
    v = np.asarray(views, np.float32)
    if v.ndim == 3:
        v = v[..., None]
    n, h, w, c = v.shape
    cands = np.asarray(candidates, np.float32)
    masks = np.asarray(subsets, bool)
    grey = v.mean(-1, dtype=np.float32)
    feats = np.concatenate(
        [v, np.gradient(grey, axis=2)[..., None], np.gradient(grey, axis=1)[..., None]], -1
    ).astype(np.float32)
    ref = feats[reference]
    ref_ok = np.isfinite(ref).all(-1)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    tc, tg, a = np.float32(params.trunc_colour), np.float32(params.trunc_gradient), params.alpha
    vol = np.ones((len(cands), len(masks), h, w), np.float32)
    for k, s in enumerate(cands):
        per = np.full((n, h, w), np.nan, np.float32)
        for i in range(n):
            if i == reference:
                continue
            x = xx + np.float32(offsets[i, 0] * float(s))
            y = yy + np.float32(offsets[i, 1] * float(s))
            inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
            xc, yc = np.where(inside, x, 0), np.where(inside, y, 0)
            x0, y0 = np.floor(xc).astype(np.intp), np.floor(yc).astype(np.intp)
            fx, fy = (xc - x0)[..., None], (yc - y0)[..., None]
            x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
            f = feats[i]
            smp = (
                (1 - fx) * (1 - fy) * f[y0, x0]
                + fx * (1 - fy) * f[y0, x1]
                + (1 - fx) * fy * f[y1, x0]
                + fx * fy * f[y1, x1]
            )
            ok = inside & np.isfinite(smp).all(-1)
            colour = np.abs(smp[..., :c] - ref[..., :c]).mean(-1)
            grad = np.abs(smp[..., c] - ref[..., c]) + np.abs(smp[..., c + 1] - ref[..., c + 1])
            cost = (1 - a) * np.minimum(colour, tc) / tc + a * np.minimum(grad, tg) / tg
            per[i] = np.where(ok, cost, np.nan)
        for j, m in enumerate(masks):
            m = m.copy()
            m[reference] = False
            sub = per[m]
            cnt = np.isfinite(sub).sum(0)
            mean = np.nansum(sub, 0) / np.maximum(cnt, 1)
            vol[k, j] = np.where((cnt > 0) & ref_ok, mean, 1.0)
    if params.radius > 0:
        guide = np.where(np.isfinite(grey[reference]), grey[reference], 0).astype(np.float64)
        r = params.radius

        def box(img: np.ndarray) -> np.ndarray:
            pad = np.zeros((img.shape[0] + 1, img.shape[1] + 1), np.float64)
            pad[1:, 1:] = img.cumsum(0).cumsum(1)
            y_lo, y_hi = np.maximum(np.arange(h) - r, 0), np.minimum(np.arange(h) + r + 1, h)
            x_lo, x_hi = np.maximum(np.arange(w) - r, 0), np.minimum(np.arange(w) + r + 1, w)
            total = (
                pad[y_hi][:, x_hi] - pad[y_lo][:, x_hi] - pad[y_hi][:, x_lo] + pad[y_lo][:, x_lo]
            )
            return total / np.outer(y_hi - y_lo, x_hi - x_lo)

        mean_i = box(guide)
        var_i = box(guide * guide) - mean_i**2
        for k in range(len(cands)):
            for j in range(len(masks)):
                p = vol[k, j].astype(np.float64)
                mp = box(p)
                av = (box(guide * p) - mean_i * mp) / (var_i + params.eps)
                bv = mp - av * mean_i
                vol[k, j] = box(av) * guide + box(bv)
    kb = vol.argmin(0)
    best = np.take_along_axis(vol, kb[None], 0)[0]
    n_k = len(cands)
    lo = np.take_along_axis(vol, np.maximum(kb - 1, 0)[None], 0)[0]
    hi = np.take_along_axis(vol, np.minimum(kb + 1, n_k - 1)[None], 0)[0]
    curv = lo - 2 * best + hi
    inner = (kb > 0) & (kb < n_k - 1) & (curv > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where(inner, np.clip(0.5 * (lo - hi) / curv, -0.5, 0.5), 0.0)
    ds = float(cands[1] - cands[0])
    far = np.abs(np.arange(n_k)[:, None, None, None] - kb[None]) >= 2
    second = np.where(far, vol, np.inf).min(0)
    out = np.stack(
        [
            cands[kb] + shift * ds,
            best,
            np.where((kb > 0) & (kb < n_k - 1), curv / ds**2, 0.0),
            second,
        ],
        -1,
    )
    return np.moveaxis(out, 0, 2).astype(np.float32)
