"""Confidence-weighted, edge-aware filling of the parallax (lfcam.processing.fill.fill_parallax)."""

from __future__ import annotations

import numpy as np
import pytest

import lfcam
from lfcam import _lfcam
from lfcam.processing.fill import fill_parallax, guide_image


def _naive_wmf(values, weights, guide, todo, radius, stride, sc, ss):
    """Per-pixel loop: the weighted median of the stride-grid neighbours."""
    h, w = values.shape
    out = values.copy()
    sup = weights.copy()
    offs = range(-radius, radius + 1, stride)
    slots = len(offs) ** 2
    for y in range(h):
        for x in range(w):
            if not todo[y, x]:
                continue
            cand = []
            for dy in offs:
                for dx in offs:
                    qy, qx = y + dy, x + dx
                    if not (0 <= qy < h and 0 <= qx < w):
                        continue
                    v, wq = values[qy, qx], weights[qy, qx]
                    if not np.isfinite(v) or not wq > 0:
                        continue
                    d2 = float(((guide[qy, qx] - guide[y, x]) ** 2).sum())
                    wt = wq * np.exp(-d2 / (2 * sc**2) - (dx * dx + dy * dy) / (2 * ss**2))
                    if wt > 0:
                        cand.append((v, wt))
            if not cand:
                out[y, x], sup[y, x] = np.nan, 0.0
                continue
            cand.sort(key=lambda t: t[0])
            vals = np.array([c[0] for c in cand])
            cw = np.cumsum([c[1] for c in cand])
            out[y, x] = vals[np.searchsorted(cw, 0.5 * cw[-1])]
            sup[y, x] = min(cw[-1] / slots, 1.0)
    return out, sup


@pytest.mark.parametrize(("radius", "stride"), [(2, 1), (4, 2), (5, 3)])
def test_kernel_equals_naive_weighted_median(radius, stride) -> None:
    rng = np.random.default_rng(radius)
    h, w = 17, 23
    values = (rng.random((h, w)) * 4).astype(np.float32)
    values[rng.random((h, w)) < 0.1] = np.nan
    weights = rng.random((h, w)).astype(np.float32)
    weights[rng.random((h, w)) < 0.2] = 0
    guide = rng.random((h, w, 3)).astype(np.float32) * 10
    todo = (rng.random((h, w)) < 0.5).astype(np.uint8)
    got, sup = _lfcam.weighted_median_fill(values, weights, guide, todo, radius, stride, 3.0, 2.5)
    want, wsup = _naive_wmf(values, weights, guide, todo, radius, stride, 3.0, 2.5)
    # The same candidates, sums in a different order: the median is one of the values
    # (exactly equal); the support agrees to float32 rounding.
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(sup, wsup, rtol=1e-5, atol=1e-7)


def test_fill_restores_a_depth_edge_at_the_colour_edge() -> None:
    """A smeared, unconfident band across a depth step snaps back to the step."""
    h, w = 40, 60
    xx = np.arange(w)[None, :].repeat(h, 0)
    image = np.where(xx < 30, 0.2, 0.8).astype(np.float32)[..., None].repeat(3, -1)
    truth = np.where(xx < 30, 1.5, -0.5).astype(np.float32)
    band = np.abs(xx - 29.5) < 6
    smeared = truth.copy()
    smeared[band] = np.interp(xx[band], [23.5, 35.5], [1.5, -0.5]).astype(np.float32)
    conf = np.where(band, 0.3, 0.95).astype(np.float32)
    s, c, filled = fill_parallax(smeared, conf, guide_image(image), threshold=0.85, radius=8)
    np.testing.assert_array_equal(s, truth)
    assert filled[band].all()
    assert not filled[~band].any()
    np.testing.assert_array_equal(c[~band], conf[~band])
    assert (c[band] > 0).all()
    assert (c[band] < 0.85).all()


def test_a_pixel_without_reliable_neighbours_of_its_colour_looks_further() -> None:
    """A background band whose own-coloured neighbours within ``radius`` are all
    unreliable must not take the foreground's parallax (a median sees only relative
    weights, so tiny colour weights would still decide): with ``min_support`` (off by
    default) it reaches its own colour in the wider second pass; without it, it takes
    the foreground's 1.5."""
    h, w, radius = 30, 100, 10
    xx = np.arange(w)[None, :].repeat(h, 0)
    # Lightness 10 Lab units apart: a colour weight of exp(-5.6), small but not 0.
    image = np.where(xx < 30, 0.6, 0.5).astype(np.float32)[..., None].repeat(3, -1)
    image[0, 0] = 1.0  # guide_image scales the 99.5th percentile to 1
    truth = np.where(xx < 30, 1.5, -0.5).astype(np.float32)
    band = (xx >= 30) & (xx < 45)  # background, all unreliable, 15 px > radius wide
    s = np.where(band, 0.5, truth).astype(np.float32)
    conf = np.where(band, 0.0, 0.9).astype(np.float32)
    guide = guide_image(image)
    out, _, filled = fill_parallax(s, conf, guide, threshold=0.5, radius=radius, min_support=0.002)
    assert filled[band].all()
    np.testing.assert_array_equal(out[band], -0.5)
    np.testing.assert_array_equal(out[~band], truth[~band])
    # The default, for contrast: the pixels next to the edge take 1.5.
    old, _, _ = fill_parallax(s, conf, guide, threshold=0.5, radius=radius)
    assert (old[:, 30:35] == 1.5).all()


def test_fill_stays_inside_where_and_keeps_unfillable_values() -> None:
    h, w = 20, 20
    s = np.full((h, w), 0.5, np.float32)
    conf = np.full((h, w), 0.9, np.float32)
    s[5, 5], conf[5, 5] = 3.0, 0.1  # an outlier with confident neighbours
    s[:, 15:] = np.nan  # nobody sees these
    where = np.ones((h, w), bool)
    where[:, 15:] = False
    guide = np.zeros((h, w, 1), np.float32)
    out, _, filled = fill_parallax(s, conf, guide, where=where, threshold=0.5, radius=3)
    assert out[5, 5] == 0.5
    assert filled[5, 5]
    assert np.isnan(out[:, 15:]).all()
    assert not filled[:, 15:].any()
    # An unconfident pixel without any confident neighbour keeps its value.
    conf2 = np.zeros((h, w), np.float32)
    out2, _, filled2 = fill_parallax(np.full((h, w), 0.25, np.float32), conf2, guide, threshold=0.5)
    assert (out2 == 0.25).all()
    assert not filled2.any()


def test_what_is_refilled() -> None:
    """Large residuals and lost views are refilled; low confidence alone (few views
    see the pixel, as near an image circle's edge) is not."""
    h, w = 30, 30
    s = np.full((h, w), 1.0, np.float32)
    conf = np.full((h, w), 0.9, np.float32)
    residual = np.full((h, w), 0.05, np.float32)
    n_used = np.full((h, w), 8, np.uint8)
    n_seen = np.full((h, w), 8, np.uint8)
    s[5, 5], residual[5, 5] = 4.0, 0.5  # views disagree
    s[10, 10], n_used[10, 10] = 4.0, 5  # 3 of 8 views dropped
    s[20:, 20:], conf[20:, 20:], n_used[20:, 20:], n_seen[20:, 20:] = 4.0, 0.2, 2, 2
    out, c, filled = fill_parallax(
        s, conf, np.zeros((h, w, 1), np.float32), residual=residual, n_used=n_used, n_seen=n_seen
    )
    assert out[5, 5] == 1.0
    assert out[10, 10] == 1.0
    assert filled.sum() == 2
    np.testing.assert_array_equal(out[20:, 20:], 4.0)  # kept: few views, but consistent
    assert c[5, 5] <= 0.5
    np.testing.assert_array_equal(c[~filled], conf[~filled])


def test_fill_errors_name_the_argument() -> None:
    s = np.zeros((5, 5), np.float32)
    with pytest.raises(lfcam.InputError, match="confidence"):
        fill_parallax(s, np.zeros((4, 5), np.float32), np.zeros((5, 5, 1), np.float32))
    with pytest.raises(lfcam.InputError, match="guide"):
        fill_parallax(s, s, np.zeros((4, 5, 1), np.float32))
    with pytest.raises(lfcam.InputError, match="residual"):
        fill_parallax(s, s, np.zeros((5, 5, 1), np.float32), residual=np.zeros((4, 4)))
    with pytest.raises(lfcam.InputError, match="radius"):
        fill_parallax(s, s, np.zeros((5, 5, 1), np.float32), radius=0)
    with pytest.raises(lfcam.InputError, match="sigma_colour"):
        fill_parallax(s, s, np.zeros((5, 5, 1), np.float32), sigma_colour=-1.0)
    with pytest.raises(lfcam.InputError, match="todo"):
        _lfcam.weighted_median_fill(s, s, s[..., None], np.zeros((5, 4), np.uint8), 2, 1, 1.0, 1.0)
    with pytest.raises(lfcam.InputError, match="values"):
        _lfcam.weighted_median_fill(s[0], s, s[..., None], s.astype(np.uint8), 2, 1, 1.0, 1.0)
