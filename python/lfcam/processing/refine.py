"""Depth refinement: a plane sweep along the calibrated parallax lines over all views
at once (docs/design.md, "Depth refinement").

The Rust core's ``plane_sweep`` compares the reference with every view at candidate
parallaxes ``s`` (pixel ``p`` against ``view_i(p + o_i s)``, bicubic), with a truncated
colour + gradient cost aggregated by a guided filter (edge-aware), for all views
together and for the views on each side of the reference (half-planes: near an
occluding edge only one side sees the background). First a narrow band around the flow
+ triangulation estimate ``s0`` (candidates relative to it, so windows follow its
surface), then the whole range only where ``s0`` is unsure (filled, missing, or the
band's minimum at its end). ``s0`` stays where the sweep agrees with it, where the
sweep's cost is not clearly lower than ``s0``'s own, and near the data's edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
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
    #: Half-width of the band swept around ``s0`` (px at the farthest view); where its
    #: minimum lies at the band's end, or ``s0`` failed, the whole range is swept.
    band_px: float = 1.0
    #: ``s0`` is replaced only where the sweep's minimum cost is at least this much
    #: below ``s0``'s own cost (cost units, 0 .. 1): not where the curve is flat.
    min_gain: float = 0.02
    #: Bicubic samples of the views (bilinear if False).
    cubic: bool = True

    def __post_init__(self) -> None:
        for name in ("step_px", "trunc_colour", "trunc_gradient", "eps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (
                isinstance(v, (int, float)) and math.isfinite(v) and v > 0
            ):
                raise InputError(f"refine.{name}: expected a finite number > 0, got {v!r}")
        for name in ("margin_px", "agree_px", "band_px", "min_gain"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (
                isinstance(v, (int, float)) and math.isfinite(v) and v >= 0
            ):
                raise InputError(f"refine.{name}: expected a finite number >= 0, got {v!r}")
        if not (0.0 <= self.alpha <= 1.0):
            raise InputError(f"refine.alpha: expected 0 .. 1, got {self.alpha!r}")
        if not (0.0 < self.subset_ratio <= 1.0):
            raise InputError(f"refine.subset_ratio: expected 0 < x <= 1, got {self.subset_ratio!r}")
        if not isinstance(self.cubic, bool):
            raise InputError(f"refine.cubic: expected True or False, got {self.cubic!r}")
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
    base: np.ndarray | None = None,
    active: np.ndarray | None = None,
) -> np.ndarray:
    """The Rust core's plane sweep over views already scaled to the cost's units:
    (H, W, S, 5) float32 with the parallax, minimum cost, curvature, second-best cost
    and cost at the candidate nearest 0 per pixel and subset; with ``base`` the
    candidates are offsets from it, with ``active`` only those pixels are wanted
    (others NaN)."""
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
        base=None if base is None else np.ascontiguousarray(base, np.float32),
        active=None if active is None else np.ascontiguousarray(active, np.uint8),
        cubic=params.cubic,
    )
    return out


def _pick(out: np.ndarray, ratio_limit: float) -> np.ndarray:
    """(H, W, 1) index of the subset kept per pixel: the all-views one (0) unless a
    half-plane's minimum cost is below ``ratio_limit`` of its."""
    cost = out[..., 1]
    pick = np.zeros(out.shape[:2], np.intp)
    if out.shape[2] > 1:
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = cost[..., 1:] / np.maximum(cost[..., :1], 1e-12)
        ratio = np.where(np.isfinite(ratio), ratio, np.inf)
        best = ratio.argmin(-1)
        clearly = np.take_along_axis(ratio, best[..., None], -1)[..., 0] < ratio_limit
        pick = np.where(clearly, best + 1, 0)
    return pick[..., None]


def _near_edge(valid: np.ndarray, r: int) -> np.ndarray:
    """Pixels within ``r`` px (square) of a pixel without data or of the image's border."""
    if r <= 0:
        return np.zeros(valid.shape, bool)
    pad = np.pad(valid, r, constant_values=False)
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return ~cv2.erode(pad.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)[
        r:-r, r:-r
    ].astype(bool)


def refine_parallax(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    s0: np.ndarray,
    params: RefineParams | None = None,
    unsure: np.ndarray | None = None,
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
    unsure : (H, W) bool array, optional
        Pixels where ``s0`` is known to be unsure (e.g. filled): swept over the whole
        range as well.

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
    reach = float(np.hypot(offsets[:, 0], offsets[:, 1]).max())
    ds = p.step_px / reach
    # 1. A narrow band around s0 (windows follow s0's surface).
    nb = max(1, math.ceil(p.band_px / p.step_px))
    rel = (ds * np.arange(-nb, nb + 1)).astype(np.float32)
    known = ref_valid & np.isfinite(s0)
    band = sweep_costs(scaled, offsets, reference, rel, subsets, p, base=s0, active=known)
    take = _pick(band, p.subset_ratio)
    s_b = np.take_along_axis(band[..., 0], take, -1)[..., 0]
    c_b = np.take_along_axis(band[..., 1], take, -1)[..., 0]
    at_s0 = band[..., 4]
    # 2. The whole range where s0 failed, is unsure or the band's minimum is at its end.
    with np.errstate(invalid="ignore"):
        at_end = np.abs(s_b - s0) >= (nb - 0.5) * ds
    wide_px = ref_valid & (~known | at_end)
    if unsure is not None:
        wide_px |= ref_valid & np.asarray(unsure, bool)
    s_new, c_new = s_b, c_b
    conf = np.zeros(s0.shape, np.float32)
    c_ref = np.take_along_axis(at_s0, take, -1)[..., 0]
    if wide_px.any():
        wide = sweep_costs(scaled, offsets, reference, cands, subsets, p, active=wide_px)
        tw = _pick(wide, p.subset_ratio)
        s_w = np.take_along_axis(wide[..., 0], tw, -1)[..., 0]
        c_w = np.take_along_axis(wide[..., 1], tw, -1)[..., 0]
        c_2nd = np.take_along_axis(wide[..., 3], tw, -1)[..., 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            better = wide_px & ~(c_w >= c_b)
            cw = np.clip((c_2nd - c_w) / np.maximum(c_2nd, 1e-12), 0.0, 1.0)
        s_new = np.where(better, s_w, s_new)
        c_new = np.where(better, c_w, c_new)
        c_ref = np.where(better, np.take_along_axis(at_s0, tw, -1)[..., 0], c_ref)
        conf = np.where(wide_px & np.isfinite(cw), cw, conf).astype(np.float32)
    # 3. s0 stays where the two agree, where the sweep's minimum is not clearly below
    # s0's own cost (a flat curve), and within the aggregation's reach (2 radius) of the
    # data's edge, where the views that see a sample change with the candidate.
    with np.errstate(invalid="ignore"):
        agree = np.abs(s_new - s0) <= p.agree_px / reach
        clear = ~known | ~(c_ref - c_new < p.min_gain)
    edge = _near_edge(ref_valid, 2 * p.radius)
    swept = ref_valid & np.isfinite(s_new) & ~agree & clear & (~edge | ~known)
    parallax = np.where(swept, s_new, s0).astype(np.float32)
    parallax[~ref_valid] = np.nan
    return RefineResult(parallax, conf, swept)


def plane_sweep_numpy(
    views: np.ndarray,
    offsets: np.ndarray,
    reference: int,
    candidates: np.ndarray,
    subsets: np.ndarray,
    params: RefineParams,
    base: np.ndarray | None = None,
    active: np.ndarray | None = None,
) -> np.ndarray:
    """The numpy reference of the Rust core's ``plane_sweep`` (:func:`sweep_costs`):
    the same cost, aggregation and minimum, computed over the whole cost volume. For
    tests and benchmarks; slow and memory-hungry (``K x S x H x W`` floats).

    Returns
    -------
    (H, W, S, 5) float32
        Parallax, minimum cost, curvature, second-best cost and the cost at the
        candidate nearest 0 per pixel and subset.
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
    b = np.zeros((h, w), np.float32) if base is None else np.asarray(base, np.float32)
    for k, s in enumerate(cands):
        s_px = (b + s).astype(np.float64)
        per = np.full((n, h, w), np.nan, np.float32)
        for i in range(n):
            if i == reference:
                continue
            x = xx + (offsets[i, 0] * s_px).astype(np.float32)
            y = yy + (offsets[i, 1] * s_px).astype(np.float32)
            inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
            xc, yc = np.where(inside, x, 0), np.where(inside, y, 0)
            x0, y0 = np.floor(xc).astype(np.intp), np.floor(yc).astype(np.intp)
            fx, fy = (xc - x0)[..., None], (yc - y0)[..., None]
            f = feats[i]
            if params.cubic:
                wx, wy = _cubic_weights(fx), _cubic_weights(fy)
                smp = np.zeros((h, w, f.shape[-1]), np.float32)
                for a_ in range(4):
                    ya_ = np.clip(y0 + a_ - 1, 0, h - 1)
                    for b_ in range(4):
                        smp += wy[a_] * wx[b_] * f[ya_, np.clip(x0 + b_ - 1, 0, w - 1)]
            else:
                x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
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
            vol[k, j] = np.where((cnt > 0) & ref_ok & np.isfinite(b), mean, 1.0)
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
            b + cands[kb] + shift * ds,
            best,
            np.where((kb > 0) & (kb < n_k - 1), curv / ds**2, 0.0),
            second,
            vol[int(np.abs(cands).argmin())],
        ],
        -1,
    )
    out = np.moveaxis(out, 0, 2).astype(np.float32)
    out[~np.isfinite(b)] = np.nan
    if active is not None:
        out[~np.asarray(active, bool)] = np.nan
    return out


def _cubic_weights(t: np.ndarray) -> list[np.ndarray]:
    """OpenCV's bicubic weights (a = -0.75) of the four taps for offsets ``t`` in 0..1."""
    a = np.float32(-0.75)
    x = t + 1
    w0 = ((a * x - 5 * a) * x + 8 * a) * x - 4 * a
    w1 = ((a + 2) * t - (a + 3)) * t * t + 1
    u = 1 - t
    w2 = ((a + 2) * u - (a + 3)) * u * u + 1
    return [w0, w1, w2, 1 - w0 - w1 - w2]
