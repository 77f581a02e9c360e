"""The depth chain on bare views (lfcam.depth_from_views): occlusion handling on a
synthetic two-layer light field with exact truth, and argument checks."""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np
import pytest

import lfcam
from lfcam.calibration.pattern import procedural_texture
from lfcam.processing.triangulate import MAX_VIEWS


def _two_layers(grid=(3, 3), size=(160, 200), d_back=0.5, d_front=5.0, seed=0):
    """A textured square (disparity d_front) in front of a textured wall (d_back).

    The reference pixel p appears at p + o_i s in view i, so view i shows at q the
    front texture at q - o_i d_front where that falls in the square, else the back
    texture at q - o_i d_back. Returns views, offsets, reference, true parallax.
    """
    rng = np.random.default_rng(seed)
    h, w = size
    back = cv2.GaussianBlur(procedural_texture(h, w, rng).astype(np.float32), (0, 0), 0.7)
    front = cv2.GaussianBlur(procedural_texture(h, w, rng).astype(np.float32), (0, 0), 0.7)
    front = front[..., ::-1].copy()  # other colours than the wall
    y0, y1, x0, x1 = 50, 110, 70, 140
    rows, cols = grid
    rr, rc = (rows - 1) // 2, (cols - 1) // 2
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    views, offsets = [], []
    for r in range(rows):
        for c in range(cols):
            o = np.array([-(c - rc), -(r - rr)], np.float64)
            fx = (xx - o[0] * d_front).astype(np.float32)
            fy = (yy - o[1] * d_front).astype(np.float32)
            inside = (fx >= x0) & (fx < x1) & (fy >= y0) & (fy < y1)
            fv = cv2.remap(front, fx, fy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
            bv = cv2.remap(
                back,
                (xx - o[0] * d_back).astype(np.float32),
                (yy - o[1] * d_back).astype(np.float32),
                cv2.INTER_CUBIC,
                borderMode=cv2.BORDER_REFLECT,
            )
            views.append(np.where(inside[..., None], fv, bv))
            offsets.append(o)
    truth = np.full((h, w), d_back, np.float32)
    truth[y0:y1, x0:x1] = d_front
    return np.stack(views).astype(np.float32), np.array(offsets), rr * cols + rc, truth


def test_occlusion_bands_are_filled_from_the_right_side() -> None:
    views, offsets, ref, truth = _two_layers()
    inner = np.s_[12:-12, 12:-12]  # frame borders: content leaves the views
    bad = {}
    for fill in (False, True):
        s = lfcam.depth_from_views(views, offsets, ref, lfcam.DepthParams(fill=fill)).parallax
        err = np.abs(s - truth)[inner]
        bad[fill] = float(np.mean(~(err <= 0.25)))
    # Measured: 4.8% without the fill, 0.65% with it (the square's outline is 4.6%
    # of the inner image, its occlusion band about twice that).
    assert bad[True] <= 0.015, bad
    assert bad[True] < 0.5 * bad[False], bad


def test_too_many_views_are_refused_before_any_flow() -> None:
    n = MAX_VIEWS + 1
    views = np.zeros((n, 64, 64), np.float32)
    t0 = time.perf_counter()
    with pytest.raises(lfcam.InputError, match=rf"views: {n} views; at most"):
        lfcam.depth_from_views(views, np.zeros((n, 2)), 0)
    assert time.perf_counter() - t0 < 1.0


def _crafted_flows(monkeypatch, grid, s_true, s_wrong, bad_rows, far_radius):
    """Replace the optical flows by exact ones, ``o_i * s_true``, except that views
    further than ``far_radius`` from the reference (in grid steps) move by
    ``o_i * s_wrong`` in ``bad_rows``: far views' flows failing together, as they do
    near occlusions on a 9 x 9 light field. Returns views, offsets, reference."""
    rows, cols = grid
    rr, rc = rows // 2, cols // 2
    offsets = np.array([[c - rc, r - rr] for r in range(rows) for c in range(cols)], np.float64)
    reference = rr * cols + rc
    h, w = 30, 40
    n = len(offsets)

    def fake(views, ref, params, threads, *, margin=None):
        s = np.full((n, h, w), s_true, np.float32)
        far = np.hypot(offsets[:, 0], offsets[:, 1]) > far_radius
        s[np.ix_(far, bad_rows, np.arange(w))] = s_wrong
        flows = (offsets[:, None, None, :] * s[..., None]).astype(np.float32)
        flows[ref] = np.nan
        weights = np.ones((n, h, w), np.float32)
        weights[ref] = 0
        seen = np.ones((n, h, w), bool)
        seen[ref] = False
        return flows, weights, seen, (slice(0, h), slice(0, w))

    monkeypatch.setattr(lfcam.processing.depth, "_flows_and_seen", fake)
    views = np.random.default_rng(0).random((n, h, w, 3)).astype(np.float32)
    return views, offsets, reference


def test_many_views_fall_back_to_the_near_views_where_far_ones_fail(monkeypatch) -> None:
    # 9 x 9: the 56 views outside the inner 5 x 5 agree on a wrong parallax in rows
    # 10..19; all of them together outvote the 24 near views there (and lose more than
    # a quarter of the views: unsure); the near views' own triangulation is exact.
    bad = np.arange(10, 20)
    views, offsets, ref = _crafted_flows(monkeypatch, (9, 9), 0.5, 1.5, bad, 2.9)
    near = lfcam.processing.depth.near_views(offsets, ref)
    assert near is not None
    assert near.tolist() == [r * 9 + c for r in range(2, 7) for c in range(2, 7)]
    res = lfcam.depth_from_views(views, offsets, ref, lfcam.DepthParams(fill=False))
    np.testing.assert_allclose(res.parallax, 0.5, atol=1e-4)
    assert (res.n_used[bad] == 24).all()
    assert (res.n_used[:10] == 80).all()
    # Without the second triangulation (too few near views to trust), the far views win.
    params = lfcam.DepthParams(fill=False, near_views_min=25)
    res = lfcam.depth_from_views(views, offsets, ref, params)
    assert abs(float(np.median(res.parallax[bad])) - 1.5) < 1e-3


def test_few_views_have_no_near_set() -> None:
    # 3 x 4 (the reference camera), 3 x 3 and 5 x 5: too few near views to trust alone.
    for rows, cols in ((3, 4), (3, 3), (5, 5)):
        rr, rc = (rows - 1) // 2, (cols - 1) // 2
        off = np.array([[c - rc, r - rr] for r in range(rows) for c in range(cols)], np.float64)
        assert lfcam.processing.depth.near_views(off, rr * cols + rc) is None


def test_flow_resolution_follows_the_window_size(monkeypatch) -> None:
    # Full resolution up to flow_max_pixels (the simulator's and HCI's views), half
    # resolution for the full-size camera's 0.95 Mpx window, and so on.
    from lfcam.processing.depth import DEPTH_FLOW

    defaults = lfcam.DepthParams()
    assert defaults.flow_max_pixels == 500_000
    scales = [defaults.flow_for(n).finest_scale for n in (300_000, 500_000, 950_000, 2_000_001)]
    assert scales == [0, 0, 1, 2]
    assert defaults.flow_for(950_000) == dataclasses.replace(DEPTH_FLOW, finest_scale=1)
    # depth_from_views uses it for its window unless told otherwise.
    used = []
    real = lfcam.processing.depth.dis_flow

    def spy(a, b, params=None, init=None):
        used.append((a.shape, params.finest_scale))
        return real(a, b, params, init)

    monkeypatch.setattr(lfcam.processing.depth, "dis_flow", spy)
    params = lfcam.DepthParams(flow_max_pixels=10000, fill=False)
    views, offsets, ref, _ = _two_layers()  # 160 x 200: a 32000 px window
    lfcam.depth_from_views(views, offsets, ref, params)
    # Scale 1: the views are reduced to 80 x 100 first, DIS runs at its finest scale
    # forward and backward (backward_scale is not finer than that); one of each per view.
    n = len(views) - 1
    assert params.backward_scale == 1
    assert sorted(used) == [((80, 100), 0)] * (2 * n)
    used.clear()
    lfcam.depth_from_views(views, offsets, ref, dataclasses.replace(params, flow=DEPTH_FLOW))
    # Full resolution: the backward flows one scale coarser.
    assert sorted(used) == [((160, 200), 0)] * n + [((160, 200), 1)] * n
    used.clear()
    no_back = dataclasses.replace(params, flow=DEPTH_FLOW, backward=False)
    lfcam.depth_from_views(views, offsets, ref, no_back)
    assert used == [((160, 200), 0)] * n


@pytest.mark.parametrize("size", [(320, 400), (321, 399)])
def test_half_resolution_flow_keeps_the_parallax(size) -> None:
    # The flow at half resolution (views block-averaged, flows and checks interpolated
    # back, pixel centres aligned; odd sizes padded): the parallax away from the
    # square's outline is as exact as at full resolution, and the outline's band is
    # no more than about twice as wide. Measured (320 x 400, disparities 1 and 10 px):
    # median |s - truth| 0.003 (0.002 at full resolution), off by > 0.25: 1.0% (0.5%).
    views, offsets, ref, truth = _two_layers(size=size, d_back=1.0, d_front=10.0)
    views = np.ascontiguousarray(views[:, :, :, :])
    h, w = size
    y0, y1, x0, x1 = 50, 110, 70, 140
    near_edge = np.zeros(size, bool)
    near_edge[y0 - 14 : y1 + 14, x0 - 14 : x1 + 14] = True
    near_edge[y0 + 14 : y1 - 14, x0 + 14 : x1 - 14] = False
    keep = np.zeros(size, bool)
    keep[24:-24, 24:-24] = True
    keep &= ~near_edge
    errs = {}
    for max_pixels in (10**6, h * w // 2):
        params = lfcam.DepthParams(flow_max_pixels=max_pixels)
        s = lfcam.depth_from_views(views, offsets, ref, params).parallax
        err = np.abs(s - truth)
        errs[max_pixels] = (
            float(np.nanmedian(err[keep])),
            float(np.mean(~(err[24:-24, 24:-24] <= 0.25))),
        )
    full, half = errs[10**6], errs[h * w // 2]
    assert half[0] <= 0.01, errs
    assert half[1] <= max(2 * full[1], 0.01) + 0.005, errs
