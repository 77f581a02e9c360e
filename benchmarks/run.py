"""Benchmarks of lfcam's functions against the numpy / OpenCV way of doing the same thing.

Each row times lfcam and its reference in the same run, alternating calls, and prints
the medians and the ratio lfcam / reference (below 1: lfcam is faster). Outputs are
compared once before timing, so a row cannot be fast by being wrong.

    python benchmarks/run.py                  # full-size frames, 15 repeats
    python benchmarks/run.py --quick          # 5 repeats
    python benchmarks/run.py --size small     # 1920x1080 frames
    python benchmarks/run.py -k crop          # rows whose name contains "crop"

OpenCV runs on as many threads as lfcam (``cv2.setNumThreads``) in every row.

To add a row (rectify, triangulate, ...), write a function that takes the size name and
returns a :class:`Case`, and decorate it with ``@row("name")``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

import lfcam
import lfcam.kernels.warp

SIZES = ("small", "full")


@dataclass
class Case:
    """One benchmark: lfcam's call and the reference call, on the same inputs."""

    lfcam: Callable[[], Any]
    reference: Callable[[], Any]
    reference_name: str
    shape: str
    # Compares the two outputs; the row fails loudly if they differ.
    same: Callable[[Any, Any], bool] = field(default=lambda a, b: bool(np.array_equal(a, b)))
    threads: int | None = None  # lfcam threads for this row; None: the current setting


@dataclass
class Row:
    name: str
    make: Callable[[str], Case]


ROWS: list[Row] = []


def row(name: str) -> Callable[[Callable[[str], Case]], Callable[[str], Case]]:
    """Register ``make(size) -> Case`` as the benchmark row ``name``."""

    def register(make: Callable[[str], Case]) -> Callable[[str], Case]:
        ROWS.append(Row(name, make))
        return make

    return register


# --- rows ---------------------------------------------------------------------------


def _crop_case(size: str, threads: int | None, preallocated: bool = False) -> Case:
    # The paper's 3x4 lenslet array: ~1 Mpx views on the full-size sensor.
    frame, view = {"full": ((2700, 4800), (1200, 900)), "small": ((1080, 1920), (480, 360))}[size]
    (fh, fw), (vw, vh) = frame, view
    raw = np.random.default_rng(0).integers(0, 256, (fh, fw, 3), dtype=np.uint8)
    rects = np.array([[c * vw, r * vh, vw, vh] for r in range(3) for c in range(4)])

    def stack() -> np.ndarray:
        return np.stack([np.ascontiguousarray(raw[y : y + h, x : x + w]) for x, y, w, h in rects])

    def assign() -> np.ndarray:
        out = np.empty((len(rects), vh, vw, 3), raw.dtype)
        for view, (x, y, w, h) in zip(out, rects):
            view[...] = raw[y : y + h, x : x + w]
        return out

    return Case(
        lfcam=lambda: lfcam.crop_lenslets(raw, rects),
        reference=assign if preallocated else stack,
        reference_name="numpy empty + assign" if preallocated else "numpy stack of slices",
        shape=f"{fw}x{fh}x3 u8 -> 12x{vw}x{vh}",
        threads=threads,
    )


@row("crop_lenslets")
def crop_default_threads(size: str) -> Case:
    return _crop_case(size, threads=None)


@row("crop_lenslets, 1 thread")
def crop_one_thread(size: str) -> Case:
    return _crop_case(size, threads=1)


@row("crop_lenslets vs one copy")
def crop_vs_preallocated(size: str) -> Case:
    # The best plain-numpy way: one output allocation, one copy per view.
    return _crop_case(size, threads=None, preallocated=True)


# The paper's 3x4 lenslet array. Raw frame (W, H), view crop (w, h), rectified frame.
_RECTIFY_SIZES = {
    "small": ((1920, 1080), (480, 360), (810, 540)),
    "full": ((4800, 2700), (1200, 900), (2000, 1350)),
}


def _rectify_inputs(size: str) -> dict[str, Any]:
    """A raw RGB u8 frame, vignetting gains (0 on a few dead pixels), 12 crops, and
    realistic warps: each view sees a shifted (parallax), slightly scaled and smoothly
    distorted part of the rectified frame; outside its image circle the warp is NaN and
    the mask False (about 2/3 of each rectified frame)."""
    (fw, fh), (vw, vh), (rw, rh) = _RECTIFY_SIZES[size]
    rng = np.random.default_rng(1)
    raw = rng.integers(0, 256, (fh, fw, 3), dtype=np.uint8)
    yy, xx = np.mgrid[0:fh, 0:fw].astype(np.float32)
    gains = np.empty((fh, fw, 3), np.float32)
    gains[...] = (1 + 0.5 * ((xx % vw - vw / 2) ** 2 + (yy % vh - vh / 2) ** 2) / vw**2)[..., None]
    gains[rng.random((fh, fw)) < 1e-4] = 0
    ox, oy = (fw - 4 * vw) // 2, (fh - 3 * vh) // 2
    crops = np.array([[ox + c * vw, oy + r * vh, vw, vh] for r in range(3) for c in range(4)])
    v, u = np.mgrid[0:rh, 0:rw].astype(np.float32)
    warps = np.empty((12, rh, rw, 2), np.float32)
    masks = np.empty((12, rh, rw), bool)
    s = vw / 1200
    for i in range(12):
        r, c = divmod(i, 4)
        x = (u - rw / 2 - (c - 1.5) * 120 * s) * 0.9 + vw / 2 + 5 * s * np.sin(v / (300 * s))
        y = (v - rh / 2 - (r - 1) * 120 * s) * 0.9 + vh / 2 + 5 * s * np.cos(u / (400 * s))
        m = (np.hypot(x - vw / 2, y - vh / 2) < 0.5 * vh) & (x >= 0) & (x <= vw - 1)
        m &= (y >= 0) & (y <= vh - 1)
        x[~m] = np.nan
        y[~m] = np.nan
        warps[i, ..., 0], warps[i, ..., 1], masks[i] = x, y, m
    return {"raw": raw, "gains": gains, "crops": crops, "warps": warps, "masks": masks}


def _same_where_defined(atol: float) -> Callable[[Any, Any], bool]:
    """lfcam's output agrees with the reference wherever lfcam has data (NaN: no data;
    OpenCV fills such places with 0 or values from beyond the crop)."""

    def same(ours: Any, theirs: Any) -> bool:
        theirs = np.asarray(theirs).reshape(np.shape(ours))
        ok = ~np.isnan(ours)
        return bool(ok.any()) and bool(np.allclose(ours[ok], theirs[ok], rtol=0, atol=atol))

    return same


def _rectify_case(
    size: str, interp: str, flag: int, per_view: bool = False, plan: bool = True
) -> Case:
    d = _rectify_inputs(size)
    (fw, fh), _, (rw, rh) = _RECTIFY_SIZES[size]
    raw, gains, crops, warps, masks = d["raw"], d["gains"], d["crops"], d["warps"], d["masks"]

    def opencv_way() -> list[np.ndarray]:
        # The gains applied to the whole frame at once: the faster of the two ways.
        g = raw.astype(np.float32) * np.float32(1 / 255) * gains
        return [
            cv2.remap(g[y : y + h, x : x + w], warps[i], None, flag)
            for i, (x, y, w, h) in enumerate(crops)
        ]

    def opencv_way_per_view() -> list[np.ndarray]:
        outs = []
        for i, (x, y, w, h) in enumerate(crops):
            crop = raw[y : y + h, x : x + w].astype(np.float32) * np.float32(1 / 255)
            crop *= gains[y : y + h, x : x + w]
            outs.append(cv2.remap(crop, warps[i], None, flag))
        return outs

    kind = "cubic" if flag == cv2.INTER_CUBIC else "linear"
    if plan:
        # A capture's rectification: the plan is prepared once per calibration (timed
        # in the row "rectify plan preparation"), as lfcam.rectify(raw, cal) does.
        prepared = lfcam.kernels.warp.RectifyPlan(gains, crops, warps, masks, interp=interp)  # type: ignore[arg-type]
        ours: Callable[[], Any] = lambda: prepared.rectify(raw)  # noqa: E731
    else:
        ours = lambda: lfcam.kernels.warp.rectify(raw, gains, crops, warps, masks, interp=interp)  # type: ignore[arg-type]  # noqa: E731
    return Case(
        lfcam=ours,
        reference=opencv_way_per_view if per_view else opencv_way,
        reference_name=f"{'per view: ' if per_view else ''}gain*raw, crop, cv2.remap {kind}",
        shape=f"{fw}x{fh}x3 u8 -> 12x{rw}x{rh}x3, {masks.mean():.0%} kept"
        + (", plan prepared once" if plan else ""),
        same=_same_where_defined(1e-5),
    )


# rectify: target lfcam/OpenCV <= 0.5 (history: benchmarks/NOTES.md).
@row("rectify")
def rectify_bilinear(size: str) -> Case:
    # A capture's rectification with the calibration's prepared plan.
    return _rectify_case(size, "bilinear", cv2.INTER_LINEAR)


@row("rectify vs per-view gains")
def rectify_per_view(size: str) -> Case:
    # The OpenCV way view by view: each crop gained, then remapped.
    return _rectify_case(size, "bilinear", cv2.INTER_LINEAR, per_view=True)


@row("rectify, no plan")
def rectify_no_plan(size: str) -> Case:
    # One-off: lfcam.kernels.warp.rectify from the maps, nothing prepared.
    return _rectify_case(size, "bilinear", cv2.INTER_LINEAR, plan=False)


@row("rectify plan preparation")
def rectify_plan_preparation(size: str) -> Case:
    # Once per calibration: preparing the plan, against one capture the OpenCV way
    # (the ratio is the number of captures' worth it costs).
    d = _rectify_inputs(size)
    (fw, fh), _, (rw, rh) = _RECTIFY_SIZES[size]
    raw, gains, crops, warps, masks = d["raw"], d["gains"], d["crops"], d["warps"], d["masks"]
    reference = _rectify_case(size, "bilinear", cv2.INTER_LINEAR, plan=False)

    def same(plan: Any, theirs: Any) -> bool:
        return reference.same(plan.rectify(raw), theirs)

    return Case(
        lfcam=lambda: lfcam.kernels.warp.RectifyPlan(gains, crops, warps, masks),
        reference=reference.reference,
        reference_name="one capture the OpenCV way, as in rectify",
        shape=f"12x{rw}x{rh} maps, {fw}x{fh}x3 gains",
        same=same,
    )


@row("rectify, outputs reused")
def rectify_reused(size: str) -> Case:
    # Many captures in a row: both sides write into buffers allocated once, so neither
    # pays the page faults of fresh outputs.
    d = _rectify_inputs(size)
    (fw, fh), _, (rw, rh) = _RECTIFY_SIZES[size]
    raw, gains, crops, warps, masks = d["raw"], d["gains"], d["crops"], d["warps"], d["masks"]
    out = np.empty((12, rh, rw, 3), np.float32)
    g = np.empty(raw.shape, np.float32)
    dst = [np.empty((rh, rw, 3), np.float32) for _ in range(12)]
    plan = lfcam.kernels.warp.RectifyPlan(gains, crops, warps, masks)

    def opencv_way() -> list[np.ndarray]:
        np.multiply(raw, np.float32(1 / 255), out=g)
        np.multiply(g, gains, out=g)
        for i, (x, y, w, h) in enumerate(crops):
            cv2.remap(g[y : y + h, x : x + w], warps[i], None, cv2.INTER_LINEAR, dst=dst[i])
        return dst

    return Case(
        lfcam=lambda: plan.rectify(raw, out=out),
        reference=opencv_way,
        reference_name="the same, out= / dst= reused",
        shape=f"{fw}x{fh}x3 u8 -> 12x{rw}x{rh}x3, {masks.mean():.0%} kept",
        same=_same_where_defined(1e-5),
    )


@row("rectify bicubic")
def rectify_bicubic(size: str) -> Case:
    # No plan: plans are bilinear.
    return _rectify_case(size, "bicubic", cv2.INTER_CUBIC, plan=False)


@row("rectify output only")
def rectify_all_masked(size: str) -> Case:
    # The floor: every rectified pixel masked, so only the output is written (NaN).
    d = _rectify_inputs(size)
    _, _, (rw, rh) = _RECTIFY_SIZES[size]
    none = np.zeros_like(d["masks"])
    plan = lfcam.kernels.warp.RectifyPlan(d["gains"], d["crops"], d["warps"], none)

    def fill() -> np.ndarray:
        out = np.empty((12, rh, rw, 3), np.float32)
        out.fill(np.nan)
        return out

    return Case(
        lfcam=lambda: plan.rectify(d["raw"]),
        reference=fill,
        reference_name="numpy empty + fill(nan)",
        shape=f"12x{rw}x{rh}x3 f32, all masked",
        same=lambda a, b: bool(np.isnan(a).all() and np.isnan(b).all()),
    )


@row("remap_bilinear")
def remap_vs_opencv(size: str) -> Case:
    # One view's image resampled to the rectified frame (the warps above).
    d = _rectify_inputs(size)
    _, (vw, vh), (rw, rh) = _RECTIFY_SIZES[size]
    src = np.random.default_rng(2).random((vh, vw, 3), dtype=np.float32)
    xy = d["warps"][5]
    return Case(
        lfcam=lambda: lfcam.remap_bilinear(src, xy),
        reference=lambda: cv2.remap(src, xy, None, cv2.INTER_LINEAR),
        reference_name="cv2.remap linear",
        shape=f"{vw}x{vh}x3 f32 -> {rw}x{rh}",
        same=_same_where_defined(1e-6),
    )


@row("nan_median")
def nan_median_vs_numpy(size: str) -> Case:
    # The robust average of 5 captures' warp maps, 10% NaN.
    _, _, (rw, rh) = _RECTIFY_SIZES[size]
    rng = np.random.default_rng(3)
    stack = rng.normal(0, 300, (5, rh, rw, 2)).astype(np.float32)
    stack[rng.random(stack.shape) < 0.1] = np.nan

    def numpy_way() -> np.ndarray:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices
            return np.nanmedian(stack, axis=0)

    return Case(
        lfcam=lambda: lfcam.nan_median(stack)[0],
        reference=numpy_way,
        reference_name="np.nanmedian",
        shape=f"5x{rw}x{rh}x2 f32",
        same=lambda a, b: bool(np.array_equal(a, b, equal_nan=True)),
    )


# Plane sweep of the depth refinement: a 3 x 4 grid of textured views at a smooth
# parallax, 16 candidates, all views and 4 half-planes (the numpy reference holds the
# whole cost volume, hence the modest sizes).
_SWEEP_SIZES = {"small": (192, 256), "full": (384, 512)}


def _sweep_scene(size: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """12 views (3 x 4, reference 5) of a texture at a smooth parallax, their offsets and
    the true parallax."""
    from lfcam.calibration.pattern import procedural_texture

    h, w = _SWEEP_SIZES[size]
    rng = np.random.default_rng(5)
    tex = procedural_texture(h + 40, w + 40, rng).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    s_true = (0.5 + 0.8 * np.sin(xx / 60.0) * np.cos(yy / 45.0)).astype(np.float32)
    grid = [(r, c) for r in range(3) for c in range(4)]
    offsets = np.array([[-(c - 1), -(r - 1)] for r, c in grid], np.float64)
    views = np.stack(
        [
            cv2.remap(
                tex,
                (xx + 20 - o[0] * s_true).astype(np.float32),
                (yy + 20 - o[1] * s_true).astype(np.float32),
                cv2.INTER_LINEAR,
            )
            for o in offsets
        ]
    )
    return views, offsets, s_true


@row("plane_sweep")
def plane_sweep_vs_numpy(size: str) -> Case:
    from lfcam.processing.refine import RefineParams, half_planes, plane_sweep_numpy, sweep_costs

    views, offsets, s_true = _sweep_scene(size)
    h, w = s_true.shape
    cands = np.linspace(-0.8, 1.8, 16).astype(np.float32)
    subsets = half_planes(offsets, 5, 2)
    params = RefineParams()

    def same(ours: Any, theirs: Any) -> bool:
        return bool(np.mean(np.abs(ours[..., 0] - theirs[..., 0]) <= 1e-4) >= 0.999)

    return Case(
        lfcam=lambda: sweep_costs(views, offsets, 5, cands, subsets, params),
        reference=lambda: plane_sweep_numpy(views, offsets, 5, cands, subsets, params),
        reference_name="numpy, same cost",
        shape=f"12x{w}x{h}x3 f32, 16 s, 5 subsets, bicubic",
        same=same,
    )


# The refinement's own call: a narrow band (5 candidates, +-1 px at the farthest view)
# around a noisy estimate of the same scene, bicubic samples, all pixels wanted.
@row("plane_sweep_band")
def plane_sweep_band_vs_numpy(size: str) -> Case:
    from lfcam.processing.refine import RefineParams, half_planes, plane_sweep_numpy, sweep_costs

    views, offsets, s_true = _sweep_scene(size)
    rng = np.random.default_rng(6)
    base = (s_true + rng.normal(0, 0.15, s_true.shape)).astype(np.float32)
    cands = np.linspace(-0.5, 0.5, 5).astype(np.float32)
    subsets = half_planes(offsets, 5, 2)
    params = RefineParams()
    h, w = s_true.shape

    def same(ours: Any, theirs: Any) -> bool:
        return bool(np.mean(np.abs(ours[..., 0] - theirs[..., 0]) <= 1e-4) >= 0.999)

    return Case(
        lfcam=lambda: sweep_costs(views, offsets, 5, cands, subsets, params, base=base),
        reference=lambda: plane_sweep_numpy(views, offsets, 5, cands, subsets, params, base),
        reference_name="numpy, same cost",
        shape=f"12x{w}x{h}x3 f32, 5 s around a base, 5 subsets, bicubic",
        same=same,
    )


# Triangulation: 11 flows from the reference (row 1, column 1 of the 3x4 grid) at 1 Mpx,
# the target size; the rectified frame of the rectify row is 2.7 Mpx.
_TRIANGULATE_SIZES = {"small": (360, 480), "full": (1000, 1000)}


def _triangulate_inputs(size: str) -> dict[str, Any]:
    """Flows ``o_i s + noise`` for a smooth parallax field: 0.2 px noise, 10% occluded
    flow vectors (2 to 8 px off), 5% holes (NaN, weight 0), 0/1 weights as the
    forward-backward check gives."""
    h, w = _TRIANGULATE_SIZES[size]
    rng = np.random.default_rng(4)
    r, c = np.divmod(np.arange(12), 4)
    offsets = 25.0 * np.stack([c - 1, r - 1], axis=1).astype(np.float64)
    yy, xx = np.mgrid[0:h, 0:w]
    s = (0.4 * np.sin(xx / 97) * np.cos(yy / 61)).astype(np.float32)
    flows = offsets[:, None, None, :].astype(np.float32) * s[None, :, :, None]
    flows += rng.normal(0, 0.2, flows.shape).astype(np.float32)
    roll = rng.random((12, h, w), dtype=np.float32)
    occluded = roll < 0.1
    flows[occluded] += rng.uniform(2, 8, (int(occluded.sum()), 1)).astype(np.float32) * [1, -0.5]
    holes = (roll >= 0.1) & (roll < 0.15)
    flows[holes] = np.nan
    flows[5] = np.nan
    weights = (~holes).astype(np.float32)
    weights[5] = 0
    return {"flows": flows, "offsets": offsets, "weights": weights, "truth": s}


def _triangulate_case(size: str, threads: int | None) -> Case:
    d = _triangulate_inputs(size)
    flows, offsets, weights, truth = d["flows"], d["offsets"], d["weights"], d["truth"]
    h, w = _TRIANGULATE_SIZES[size]

    def plain_least_squares() -> np.ndarray:
        # s = sum(w o.u) / sum(w |o|^2) over the finite flows: one pass, no robustness.
        ok = np.isfinite(flows).all(-1) & (weights > 0)
        dot = np.einsum("nhwc,nc->nhw", np.where(ok[..., None], flows, 0), offsets)
        den = np.einsum("nhw,n->hw", np.where(ok, weights, 0), (offsets**2).sum(1))
        with np.errstate(invalid="ignore", divide="ignore"):
            return (np.einsum("nhw,nhw->hw", weights, dot) / den).astype(np.float32)

    def same(ours: Any, theirs: Any) -> bool:
        # Not equal by design: both estimate the truth, lfcam better (occlusions).
        ours_err = np.nanmedian(np.abs(ours.parallax - truth))
        theirs_err = np.nanmedian(np.abs(theirs - truth))
        return bool(ours_err < 0.01 and ours_err <= theirs_err)

    return Case(
        lfcam=lambda: lfcam.triangulate(flows, offsets, 5, weights),
        reference=plain_least_squares,
        reference_name="numpy plain weighted LS (less work: not robust)",
        shape=f"11 flows {w}x{h} f32 + 0/1 weights",
        same=same,
        threads=threads,
    )


@row("triangulate")
def triangulate_vs_least_squares(size: str) -> Case:
    return _triangulate_case(size, threads=None)


@row("triangulate, 1 thread")
def triangulate_one_thread(size: str) -> Case:
    return _triangulate_case(size, threads=1)


# Super-resolution: 12 views of about 1 Mpx (1200 x 900 cells, a 1104 x 828
# rectified frame, 0.91 Mpx) fused at 2x. Warps as in the rectify rows (a shifted,
# scaled, smoothly distorted part of the frame per view), offsets 25 px per lenslet
# and a smooth parallax field.
_SR_SIZES = {
    "small": ((1920, 1080), (480, 360), (440, 330)),
    "full": ((4800, 2700), (1200, 900), (1104, 828)),
}


def _sr_inputs(size: str) -> dict[str, Any]:
    from lfcam.calibration import Calibration

    (fw, fh), (vw, vh), (rw, rh) = _SR_SIZES[size]
    rng = np.random.default_rng(2)
    raw = rng.integers(0, 256, (fh, fw, 3), dtype=np.uint8)
    gains = np.ones((fh, fw, 3), np.float32)
    ox, oy = (fw - 4 * vw) // 2, (fh - 3 * vh) // 2
    crops = np.array([[ox + c * vw, oy + r * vh, vw, vh] for r in range(3) for c in range(4)])
    v, u = np.mgrid[0:rh, 0:rw].astype(np.float32)
    warps = np.empty((12, rh, rw, 2), np.float32)
    masks = np.empty((12, rh, rw), bool)
    k = vw / 1200
    for i in range(12):
        r, c = divmod(i, 4)
        x = (u - rw / 2 - (c - 1) * 40 * k) * 1.05 + vw / 2 + 5 * k * np.sin(v / (300 * k))
        y = (v - rh / 2 - (r - 1) * 40 * k) * 1.05 + vh / 2 + 5 * k * np.cos(u / (400 * k))
        m = (np.hypot(x - vw / 2, y - vh / 2) < 0.62 * vw) & (x >= 0) & (x <= vw - 1)
        m &= (y >= 0) & (y <= vh - 1)
        x[~m] = np.nan
        y[~m] = np.nan
        warps[i, ..., 0], warps[i, ..., 1], masks[i] = x, y, m
    r, c = np.divmod(np.arange(12), 4)
    offsets = 25.0 * k * np.stack([c - 1, r - 1], axis=1).astype(np.float64)
    cal = Calibration(
        grid=(3, 4),
        reference=5,
        raw_shape=(fh, fw),
        rect_shape=(rh, rw),
        pattern_shape=(rh, rw),
        scale=1.0,
        crops=crops,
        centres=crops[:, :2] + np.array([vw / 2, vh / 2]),
        warps=warps,
        masks=masks,
        offsets=offsets,
        z_b=1.0,
        z_c=0.18,
        metric=True,
        distances=np.array([1.0]),
        pattern_pitch=float("nan"),
        gains=gains,
        bayer=None,
        report={},
        software_version=lfcam.__version__,
    )
    s = (0.3 * np.sin(u / 97) * np.cos(v / 61)).astype(np.float32)
    return {"raw": raw, "cal": cal, "parallax": s}


# super_resolve 2x: target <= 1.5 s on 2 cores (history: benchmarks/NOTES.md).
@row("super_resolve 2x")
def superres_2x(size: str) -> Case:
    from lfcam.products.superres import inverse_maps

    d = _sr_inputs(size)
    raw, cal, s = d["raw"], d["cal"], d["parallax"]
    inverse_maps(cal)  # once per calibration (cached), as in `lfcam process`
    (rh, rw) = cal.rect_shape
    ref = np.ascontiguousarray(lfcam.rectify(raw, cal)[cal.reference])

    def bicubic() -> np.ndarray:
        return cv2.resize(np.nan_to_num(ref), (2 * rw, 2 * rh), interpolation=cv2.INTER_CUBIC)

    return Case(
        lfcam=lambda: lfcam.super_resolve(raw, cal, parallax=s, factor=2),
        reference=bicubic,
        reference_name="cv2.resize bicubic x2 of the reference view (no SR)",
        shape=f"12 views {rw}x{rh} -> {2 * rw}x{2 * rh}",
        same=lambda a, b: a.shape == b.shape and bool(np.isfinite(a).all()),
    )


# shift_and_add: target >= 50x np.add.at, lfcam/ref <= 0.02 (history: benchmarks/NOTES.md).
def _splat_case(size: str, reuse: bool) -> Case:
    """The fusion core alone: one view's worth of samples (1.08 Mpx full size) splatted
    with a 3 x 3 Gaussian kernel onto the 2x grid, against the same with np.add.at.
    The samples come in raw scan order, as the placement of a view's raw pixels gives
    them: its pixel grid slightly rotated and scaled (0.95), with 0.2 px jitter.
    ``reuse``: both write into arrays allocated once (numpy zeroes its own before each
    call; lfcam overwrites every element), as a loop over captures can."""
    from lfcam.products.superres import shift_and_add

    (_, _), (vw, vh), (rw, rh) = _SR_SIZES[size]
    rng = np.random.default_rng(3)
    m = vw * vh
    yy, xx = np.mgrid[0:vh, 0:vw].astype(np.float32)
    a, c = 0.95 * np.cos(0.01), 0.95 * np.sin(0.01)
    px = a * (xx - vw / 2) - c * (yy - vh / 2) + rw / 2
    py = c * (xx - vw / 2) + a * (yy - vh / 2) + rh / 2
    pos = np.stack([px, py], -1).reshape(m, 2) + rng.normal(0, 0.2, (m, 2))
    pos = np.ascontiguousarray(pos, np.float32)
    val = rng.random((m, 3), dtype=np.float32)
    shape, factor, sigma = (2 * rh, 2 * rw), 2, 0.4
    ours, theirs = (
        [(np.empty((*shape, 3), np.float32), np.empty(shape, np.float32)) for _ in range(2)]
        if reuse
        else (None, None)
    )

    def numpy_add_at() -> tuple[np.ndarray, np.ndarray]:
        fx = (pos[:, 0] + 0.5) * factor - 0.5
        fy = (pos[:, 1] + 0.5) * factor - 0.5
        xc = np.floor(fx + 0.5)
        yc = np.floor(fy + 0.5)
        if theirs is not None:
            sums, wsum = theirs
            sums.fill(0)
            wsum.fill(0)
        else:
            sums = np.zeros((*shape, 3), np.float32)
            wsum = np.zeros(shape, np.float32)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                xx, yy = xc + dx, yc + dy
                ok = (xx >= 0) & (xx < shape[1]) & (yy >= 0) & (yy < shape[0])
                g = np.exp(-((xx - fx) ** 2 + (yy - fy) ** 2) / (2 * sigma**2))[ok]
                iy, ix = yy[ok].astype(np.intp), xx[ok].astype(np.intp)
                np.add.at(wsum, (iy, ix), g.astype(np.float32))
                np.add.at(sums, (iy, ix), (g[:, None] * val[ok]).astype(np.float32))
        return sums, wsum

    def same(a: Any, b: Any) -> bool:
        return bool(np.allclose(a[0], b[0], atol=1e-4) and np.allclose(a[1], b[1], atol=1e-4))

    into = " into arrays allocated once" if reuse else ""
    return Case(
        lfcam=lambda: shift_and_add(pos, val, shape, factor, sigma=sigma, radius=1, out=ours),
        reference=numpy_add_at,
        reference_name=f"numpy np.add.at, same 3x3 Gaussian splat{into}",
        shape=f"{m} RGB samples -> {2 * rw}x{2 * rh}",
        same=same,
    )


@row("shift_and_add vs np.add.at")
def shift_and_add_vs_add_at(size: str) -> Case:
    """Fresh outputs in every call, on both sides."""
    return _splat_case(size, reuse=False)


@row("shift_and_add vs np.add.at, out=")
def shift_and_add_into_out(size: str) -> Case:
    """Outputs allocated once, on both sides: the fusion without the operating system's
    zeroing of 58 MB of fresh pages per call."""
    return _splat_case(size, reuse=True)


# Rendering: target <= 100 ms on 2 cores (history: benchmarks/NOTES.md).
# The reference view's grid mesh at 1 Mpx (1200 x 900, the full-size camera's
# views; two triangles per pixel quad) seen from a lenslet's pose: projected vertices
# p + o s(Z) with a smooth depth field, per-vertex RGB.
_RENDER_SIZES = {"small": (450, 600), "full": (900, 1200)}


def _render_inputs(size: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    h, w = _RENDER_SIZES[size]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 1.0 + 0.4 * np.sin(xx / 97) * np.cos(yy / 61) + 0.3 * (xx > w / 2)
    s = 1 - (1.0 - 0.18) / (z - 0.18)  # Z_b = 1 m, Z_c = 0.18 m
    o = np.array([17.3, -11.9])  # a lenslet's o_i, px
    verts = np.stack([xx + o[0] * s, yy + o[1] * s, z - 0.18], -1).reshape(-1, 3)
    ids = np.arange(h * w).reshape(h, w)
    a, b, c, d = ids[:-1, :-1], ids[:-1, 1:], ids[1:, :-1], ids[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    za = z.ravel()[faces]
    faces = faces[za.max(1) <= 1.03 * za.min(1)]  # cut at the depth step, as lfcam.products.mesh
    cols = np.random.default_rng(5).random((h * w, 3), dtype=np.float32)
    return (
        verts.astype(np.float32),
        cols,
        np.ascontiguousarray(faces, dtype=np.int32),
        (h, w),
    )


def numpy_rasterize(
    verts: np.ndarray, cols: np.ndarray, faces: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised numpy z-buffer for small triangles (bounding box <= 3 x 3 pixel
    centres, as a grid mesh seen from near its own pose): every candidate pixel of
    every triangle, barycentrics, perspective-correct, nearest per pixel by sorting."""
    h, w = shape
    p = verts[faces].astype(np.float64)  # (K, 3, 3)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    x0, y0 = np.ceil(x.min(1)), np.ceil(y.min(1))
    if (x.max(1) - x0 >= 3).any() or (y.max(1) - y0 >= 3).any():
        raise ValueError("a triangle is too large for this reference")
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (y[:, 1] - y[:, 0]) * (x[:, 2] - x[:, 0])
    best_key, best_z, best_rgb = [], [], []
    for dy in range(3):
        for dx in range(3):
            px, py = x0 + dx, y0 + dy
            e = []
            for k in range(3):
                a, b = (k + 1) % 3, (k + 2) % 3
                e.append(
                    (x[:, b] - x[:, a]) * (py - y[:, a]) - (y[:, b] - y[:, a]) * (px - x[:, a])
                )
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = [ek / area for ek in e]
                inside = (lam[0] >= 0) & (lam[1] >= 0) & (lam[2] >= 0) & (area != 0)
                inside &= (px >= 0) & (px < w) & (py >= 0) & (py < h)
                wgt = [lam[k] / z[:, k] for k in range(3)]
                sw = wgt[0] + wgt[1] + wgt[2]
            idx = np.nonzero(inside)[0]
            f = faces[idx]
            rgb = sum(wgt[k][idx, None] * cols[f[:, k]] for k in range(3)) / sw[idx, None]
            best_key.append((py[idx] * w + px[idx]).astype(np.int64))
            best_z.append(1 / sw[idx])
            best_rgb.append(rgb)
    key, zz, rgb = np.concatenate(best_key), np.concatenate(best_z), np.concatenate(best_rgb)
    order = np.lexsort((zz, key))
    first = np.ones(len(order), bool)
    first[1:] = key[order][1:] != key[order][:-1]
    sel = order[first]
    img = np.full((h * w, 3), np.nan, np.float32)
    dep = np.full(h * w, np.nan, np.float32)
    img[key[sel]] = rgb[sel]
    dep[key[sel]] = zz[sel]
    return img.reshape(h, w, 3), dep.reshape(h, w)


@row("rasterize depth mesh")
def rasterize_vs_numpy(size: str) -> Case:
    import lfcam.products.render

    verts, cols, faces, shape = _render_inputs(size)

    def same(ours: Any, theirs: Any) -> bool:
        # Equal up to the edge rule (pixel centres exactly on an edge) and lfcam's
        # 1/256 px vertex snapping: random per-vertex colours change by up to ~1.5 per
        # px, so a snap of <= 1/512 px moves a colour by < 1/128.
        (img, dep, mask), (img2, dep2) = ours, theirs
        both = mask & np.isfinite(dep2)
        agree = np.mean(mask == np.isfinite(dep2))
        close = np.mean(np.abs(img[both] - img2[both]) <= 1 / 128)
        close_z = np.mean(np.abs(dep[both] - dep2[both]) <= 1e-4)
        return bool(agree > 0.999 and close > 0.999 and close_z > 0.999)

    return Case(
        lfcam=lambda: lfcam.products.render.rasterize(verts, cols, faces, shape),
        reference=lambda: numpy_rasterize(verts, cols, faces, shape),
        reference_name="numpy vectorised z-buffer (small triangles only)",
        shape=f"{len(faces) / 1e6:.2f} M triangles -> {shape[1]}x{shape[0]} RGB",
        same=same,
    )


# --- harness ------------------------------------------------------------------------


@dataclass
class Result:
    name: str
    shape: str
    threads: int
    lfcam_ms: float
    reference_name: str
    reference_ms: float
    # Lowest and highest lfcam / reference ratio of the alternating call pairs.
    ratio_range: tuple[float, float] = (float("nan"), float("nan"))

    @property
    def ratio(self) -> float:
        return self.lfcam_ms / self.reference_ms


def _time_ms(fn: Callable[[], Any]) -> float:
    start = time.perf_counter()
    fn()
    return (time.perf_counter() - start) * 1e3


def run_row(r: Row, size: str, repeats: int) -> Result:
    case = r.make(size)
    default_threads = lfcam.get_num_threads()
    default_cv2_threads = cv2.getNumThreads()
    if case.threads is not None:
        lfcam.set_num_threads(case.threads)
    try:
        threads = lfcam.get_num_threads()
        cv2.setNumThreads(threads)
        if not case.same(case.lfcam(), case.reference()):  # also the warm-up call
            raise AssertionError(f"{r.name}: lfcam and {case.reference_name} disagree")
        ours, theirs = [], []
        for _ in range(repeats):
            ours.append(_time_ms(case.lfcam))
            theirs.append(_time_ms(case.reference))
    finally:
        lfcam.set_num_threads(default_threads)
        cv2.setNumThreads(default_cv2_threads)
    return Result(
        r.name,
        case.shape,
        threads,
        statistics.median(ours),
        case.reference_name,
        statistics.median(theirs),
        (min(a / b for a, b in zip(ours, theirs)), max(a / b for a, b in zip(ours, theirs))),
    )


def format_table(results: list[Result]) -> str:
    header = [
        "benchmark",
        "input",
        "threads",
        "lfcam ms",
        "reference",
        "ref ms",
        "lfcam/ref",
        "range",
    ]
    body = [
        [
            res.name,
            res.shape,
            str(res.threads),
            f"{res.lfcam_ms:.2f}",
            res.reference_name,
            f"{res.reference_ms:.2f}",
            f"{res.ratio:.2f}",
            f"{res.ratio_range[0]:.3f}-{res.ratio_range[1]:.3f}",
        ]
        for res in results
    ]
    numeric = {2, 3, 5, 6, 7}
    widths = [max(len(line[i]) for line in [header, *body]) for i in range(len(header))]

    def fmt(line: list[str]) -> str:
        cells = [
            cell.rjust(w) if i in numeric else cell.ljust(w)
            for i, (cell, w) in enumerate(zip(line, widths))
        ]
        return "  ".join(cells).rstrip()

    rule = "  ".join("-" * w for w in widths)
    return "\n".join([fmt(header), rule, *(fmt(line) for line in body)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="5 repeats instead of 15")
    parser.add_argument("--size", choices=SIZES, default="full", help="input size")
    parser.add_argument("--repeats", type=int, help="timed calls per row (overrides --quick)")
    parser.add_argument("-k", metavar="TEXT", help="only rows whose name contains TEXT")
    args = parser.parse_args(argv)
    repeats = args.repeats or (5 if args.quick else 15)

    rows = [r for r in ROWS if not args.k or args.k in r.name]
    print(
        f"lfcam {lfcam.__version__}, numpy {np.__version__}, OpenCV {cv2.__version__}, "
        f"Python {sys.version.split()[0]}; size {args.size}, median of {repeats}"
    )
    results = [run_row(r, args.size, repeats) for r in rows]
    print(format_table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
