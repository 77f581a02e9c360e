"""The calibration pattern: deterministic, textured at every scale, a cross at the centre."""

from __future__ import annotations

import numpy as np
import pytest

import lfcam
from lfcam.calibration.pattern import make_pattern


def test_shape_dtype_and_determinism() -> None:
    a = make_pattern(640, 480, seed=3)
    assert a.shape == (480, 640)
    assert a.dtype == np.uint8
    np.testing.assert_array_equal(a, make_pattern(640, 480, seed=3))
    assert (a != make_pattern(640, 480, seed=4)).mean() > 0.5


def test_cross_at_the_centre() -> None:
    p = make_pattern(801, 601, seed=0).astype(int)
    cy, cx = 300, 400
    assert p[cy, cx] < 20  # the crossing is black
    assert p[cy, cx + 20] < 20
    assert p[cy + 20, cx] < 20
    assert p[cy - 12, cx - 12] > 235
    assert p[cy + 12, cx + 12] > 235
    # The cross is symmetric about the centre: a mirror-image test.
    win = p[cy - 40 : cy + 41, cx - 40 : cx + 41]
    np.testing.assert_array_equal(win, win[::-1, ::-1])


def test_texture_at_every_scale() -> None:
    """Energy in every octave of spatial frequency from 2 to 256 px periods."""
    p = make_pattern(1024, 1024, seed=1).astype(np.float64)
    p -= p.mean()
    spec = np.abs(np.fft.fftshift(np.fft.fft2(p))) ** 2
    fy, fx = np.meshgrid(
        np.fft.fftshift(np.fft.fftfreq(1024)), np.fft.fftshift(np.fft.fftfreq(1024)), indexing="ij"
    )
    f = np.hypot(fx, fy)
    bands = [(1 / 256, 1 / 128), (1 / 64, 1 / 32), (1 / 16, 1 / 8), (1 / 8, 1 / 4), (1 / 4, 1 / 2)]
    energy = np.array([spec[(f >= lo) & (f < hi)].sum() for lo, hi in bands])
    share = energy / energy.sum()
    assert share.min() > 0.01, share  # no octave is empty
    # Local contrast everywhere (flow needs texture in every window).
    std = np.array(
        [p[y : y + 16, x : x + 16].std() for y in range(0, 1024, 64) for x in range(0, 1024, 64)]
    )
    assert np.quantile(std, 0.05) > 8


@pytest.mark.parametrize("bad", [0, 10, -5, 3.5, "640", True])
def test_bad_sizes_name_the_argument(bad) -> None:
    with pytest.raises(lfcam.InputError, match="width"):
        make_pattern(bad, 480)
