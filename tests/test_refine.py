"""Depth refinement by a plane sweep along the parallax lines: the Rust kernel against
its numpy reference, the driver on synthetic scenes, parameter checks."""

from __future__ import annotations

import numpy as np
import pytest

import lfcam
import lfcam._lfcam as _lfcam
from lfcam import InputError, RefineParams
from lfcam.processing.refine import (
    candidates_for,
    half_planes,
    plane_sweep_numpy,
    refine_parallax,
    sweep_costs,
)
from test_depth import _two_layers


@pytest.fixture(scope="module")
def small_scene():
    """3 x 3 views of a square at 3 px per step in front of a wall at 0.5 (120 x 160),
    and the true parallax."""
    views, offsets, ref, truth = _two_layers(size=(120, 160), d_back=0.5, d_front=3.0)
    views = views.copy()
    views[2, :3, :5] = np.nan  # a corner one view does not see
    return views, offsets, ref, truth


@pytest.mark.parametrize(
    ("radius", "cubic", "relative"),
    [(0, False, False), (3, False, False), (3, True, False), (3, True, True), (0, True, True)],
)
def test_kernel_matches_the_numpy_reference(small_scene, radius, cubic, relative) -> None:
    views, offsets, ref, truth = small_scene
    params = RefineParams(radius=radius, cubic=cubic)
    subsets = half_planes(offsets, ref, 2)
    assert subsets.shape == (5, 9)
    base = active = None
    if relative:
        # A band around a perturbed truth, some pixels without a base, a mask.
        rng = np.random.default_rng(3)
        base = (truth + rng.normal(0, 0.2, truth.shape)).astype(np.float32)
        base[50:54, 20:90] = np.nan
        active = np.zeros(truth.shape, bool)
        active[10:70, 30:150] = True
        cands = np.linspace(-0.6, 0.6, 7).astype(np.float32)
    else:
        cands = np.linspace(-0.5, 4.0, 19).astype(np.float32)
    got = sweep_costs(views, offsets, ref, cands, subsets, params, base=base, active=active)
    want = plane_sweep_numpy(views, offsets, ref, cands, subsets, params, base, active)
    assert got.shape == want.shape == (120, 160, 5, 5)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    if relative:
        assert np.isnan(got[~active]).all()
        assert np.isnan(got[52, 40]).all()
        assert np.isfinite(got[active & np.isfinite(base)]).all()
    got = np.nan_to_num(got, nan=-1.0, posinf=np.inf)
    want = np.nan_to_num(want, nan=-1.0, posinf=np.inf)
    np.testing.assert_allclose(got[..., 4], want[..., 4], atol=2e-5)
    # Costs agree to float32 rounding (the core sums box windows in float32).
    np.testing.assert_allclose(got[..., 1], want[..., 1], atol=2e-5)
    finite = np.isfinite(want[..., 3])
    np.testing.assert_array_equal(np.isfinite(got[..., 3]), finite)
    np.testing.assert_allclose(got[..., 3][finite], want[..., 3][finite], atol=2e-5)
    # The minimum's position: identical but for ties (equal minimum costs, asserted
    # above, at two candidates, which float32 rounding orders either way; measured
    # 0.15% of the pixel-subsets without aggregation, where truncated costs saturate).
    same = np.abs(got[..., 0] - want[..., 0]) <= 1e-4
    assert same.mean() >= 0.995, same.mean()
    np.testing.assert_allclose(got[..., 2][same], want[..., 2][same], rtol=1e-3, atol=1e-2)


def test_half_planes() -> None:
    offsets = np.array([[1, 1], [0, 1], [-1, 1], [1, 0], [0, 0], [-1, 0]], np.float64)
    s = half_planes(offsets, 4, 2).astype(bool)
    assert s[0].tolist() == [True, True, True, True, False, True]
    # x > 0, y > 0, x < 0, y < 0 (the last is empty: no view below the reference).
    assert [np.flatnonzero(r).tolist() for r in s[1:]] == [[0, 3], [0, 1, 2], [2, 5]]
    assert half_planes(offsets, 4, 0).shape == (1, 6)


def test_sweep_finds_both_layers(small_scene) -> None:
    views, offsets, ref, truth = small_scene
    # An initial estimate that only gives the range: the wall, and a few rows at 3,
    # marked unsure everywhere, so every pixel is swept over the whole range.
    s0 = np.full(truth.shape, 0.5, np.float32)
    s0[:3] = 3.0
    unsure = np.ones(truth.shape, bool)
    res = refine_parallax(views, offsets, ref, s0, RefineParams(), unsure)
    err = np.abs(res.parallax - truth)[6:-6, 6:-6]
    # Measured: 0.47% of the inner pixels off by more than 0.25 px (along the
    # square's outline, 3.4% of the inner image).
    assert np.mean(~(err <= 0.25)) <= 0.008
    # Not marked unsure, the band around the wall misses most of the square (its
    # cost has minima inside the band there): measured 6.6%.
    missed = refine_parallax(views, offsets, ref, s0, RefineParams())
    assert np.mean(~(np.abs(missed.parallax - truth)[6:-6, 6:-6] <= 0.25)) > 0.03
    assert res.confidence.dtype == np.float32
    assert res.confidence.min() >= 0
    assert res.confidence.max() <= 1
    assert res.swept.mean() > 0.1


def test_candidates_follow_the_layout() -> None:
    s0 = np.linspace(-1, 2, 1000, dtype=np.float32).reshape(20, 50)
    near = candidates_for(s0, np.array([[0, 0], [1, 0]], float), RefineParams())
    far = candidates_for(s0, np.array([[0, 0], [4, 0]], float), RefineParams())
    assert near is not None
    assert far is not None
    # 0.5 px at the farthest view per step, 1 px of margin each side.
    assert near[1] - near[0] == pytest.approx(0.5, rel=1e-6)
    assert far[1] - far[0] == pytest.approx(0.125, rel=1e-6)
    assert near[0] == pytest.approx(np.percentile(s0, 0.5) - 1.0, abs=1e-5)
    nothing = np.full((4, 4), np.nan, np.float32)
    assert candidates_for(nothing, np.array([[0, 0], [1, 0]], float), RefineParams()) is None


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"step_px": 0}, r"refine\.step_px"),
        ({"alpha": 1.5}, r"refine\.alpha"),
        ({"radius": -1}, r"refine\.radius"),
        ({"directions": 2.0}, r"refine\.directions"),
        ({"subset_ratio": 0}, r"refine\.subset_ratio"),
        ({"agree_px": float("nan")}, r"refine\.agree_px"),
    ],
)
def test_refine_params_are_checked(kw, message) -> None:
    with pytest.raises(InputError, match=message):
        RefineParams(**kw)
    with pytest.raises(InputError, match=r"params\.refine"):
        lfcam.DepthParams(refine={})  # type: ignore[arg-type]


def test_kernel_errors_name_the_argument() -> None:
    views = np.zeros((2, 8, 8, 1), np.float32)
    off = np.array([[0, 0], [1, 0]], np.float64)
    cands = np.array([0, 1, 2], np.float32)
    subs = np.array([[0, 1]], np.uint8)
    args = (0.1, 0.1, 0.5, 1, 1e-4)
    with pytest.raises(InputError, match="views"):
        _lfcam.plane_sweep(views[0], off, 0, cands, subs, *args)
    with pytest.raises(InputError, match="offsets"):
        _lfcam.plane_sweep(views, off[:1], 0, cands, subs, *args)
    with pytest.raises(InputError, match="candidates"):
        _lfcam.plane_sweep(views, off, 0, cands[[0, 2, 1]], subs, *args)
    with pytest.raises(InputError, match="subsets"):
        _lfcam.plane_sweep(views, off, 0, cands, np.array([[1, 0]], np.uint8), *args)
    with pytest.raises(InputError, match="reference"):
        _lfcam.plane_sweep(views, off, 2, cands, subs, *args)
    with pytest.raises(InputError, match="alpha"):
        _lfcam.plane_sweep(views, off, 0, cands, subs, 0.1, 0.1, 2.0, 1, 1e-4)
    out = _lfcam.plane_sweep(views, off, 0, cands, subs, *args)
    assert out.shape == (8, 8, 1, 5)
    assert out.dtype == np.float32


def test_depth_from_views_with_refine(small_scene) -> None:
    views, offsets, ref, truth = small_scene
    res = lfcam.depth_from_views(views, offsets, ref, lfcam.DepthParams(refine=RefineParams()))
    assert res.swept is not None
    assert res.swept.shape == truth.shape
    assert "refine" in res.timings
    err = np.abs(res.parallax - truth)[6:-6, 6:-6]
    assert np.mean(~(err <= 0.25)) <= 0.03


def test_refinement_keeps_an_exact_estimate_and_the_data_edge(small_scene) -> None:
    views, offsets, ref, truth = small_scene
    exact = refine_parallax(views, offsets, ref, truth.astype(np.float32))
    assert not exact.swept.any()
    np.testing.assert_array_equal(exact.parallax, truth)
    # An estimate 0.4 off everywhere: the band finds the truth inside, but within
    # 2 radius of the data's edge (here the image border) the estimate is kept.
    p = RefineParams()
    off = refine_parallax(views, offsets, ref, truth.astype(np.float32) + 0.4, p)
    e = 2 * p.radius
    assert not off.swept[:e].any()
    assert not off.swept[:, -e:].any()
    inner = np.abs(off.parallax - truth)[e:-e, e:-e]
    # Measured: 99.8% of the inner pixels swept and within 0.05 px of the truth.
    assert np.mean(inner <= 0.05) >= 0.99
