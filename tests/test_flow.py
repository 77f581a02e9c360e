"""The optical flow alone (lfcam.kernels.flow): sub-pixel accuracy on known motion and on
Middlebury's ground truth (read in place from ../shared/data; skipped without it)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import lfcam
from lfcam.calibration.pattern import procedural_texture
from lfcam.io import read_flo
from lfcam.kernels.flow import dis_flow, end_point_error, prepare
from lfcam.processing.depth import DEPTH_FLOW
from shared_data import SHARED_DATA

MIDDLEBURY = SHARED_DATA / "middlebury_flow_other"


def _fourier_shift(img, dx, dy):
    """``img`` moved by (dx, dy) px exactly (band-limited, periodic)."""
    h, w = img.shape
    fx, fy = np.fft.fftfreq(w)[None], np.fft.fftfreq(h)[:, None]
    ramp = np.exp(-2j * np.pi * (fx * dx + fy * dy))
    return np.real(np.fft.ifft2(np.fft.fft2(img) * ramp)).astype(np.float32)


@pytest.mark.parametrize("shift", [(1.3, -0.6), (0.25, 0.0), (0.1, 2.7)])
def test_subpixel_translation_of_a_texture(shift) -> None:
    """A band-limited texture moved exactly by a sub-pixel shift: DEPTH_FLOW recovers
    it to 0.015 px (median; measured <= 0.01). A sharp texture moved by cubic
    interpolation instead shows ~0.03 px of aliasing bias: the test image must be
    band-limited for the truth to be exact."""
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(
        procedural_texture(200, 260, rng).mean(-1).astype(np.float32), (0, 0), 0.8
    )
    moved = _fourier_shift(tex, *shift)
    flow = dis_flow(prepare(tex), prepare(moved), DEPTH_FLOW)
    inner = flow[30:-30, 30:-30].reshape(-1, 2)
    err = np.abs(np.median(inner, 0) - shift)
    assert (err < 0.015).all(), err
    assert np.percentile(np.hypot(*(inner - shift).T), 90) < 0.1


def _middlebury(name):
    if not MIDDLEBURY.is_dir():
        pytest.skip(f"{MIDDLEBURY} not present")
    a = cv2.imread(str(MIDDLEBURY / "other-data" / name / "frame10.png"))[..., ::-1]
    b = cv2.imread(str(MIDDLEBURY / "other-data" / name / "frame11.png"))[..., ::-1]
    return a, b, read_flo(MIDDLEBURY / "other-gt-flow" / name / "flow10.flo")


@pytest.mark.parametrize(
    ("name", "bound"),
    # Measured (benchmarks/flow_tuning.py): 0.115, 0.120, 0.385; MEDIUM preset on grey
    # 0.225, 0.156, 0.384.
    [("RubberWhale", 0.14), ("Dimetrodon", 0.14), ("Venus", 0.42)],
)
def test_depth_flow_against_middlebury_ground_truth(name, bound) -> None:
    a, b, gt = _middlebury(name)
    ours = end_point_error(
        dis_flow(prepare(a.astype(np.float32)), prepare(b.astype(np.float32)), DEPTH_FLOW), gt
    )
    grey = [cv2.cvtColor(np.ascontiguousarray(x), cv2.COLOR_RGB2GRAY) for x in (a, b)]
    medium = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(*grey, None)
    assert ours <= bound, f"{name}: EPE {ours:.3f} px"
    assert ours <= end_point_error(medium, gt) + 0.01, f"{name}: EPE {ours:.3f} vs MEDIUM"


def test_read_flo_errors(tmp_path) -> None:
    bad = tmp_path / "x.flo"
    bad.write_bytes(b"nope")
    with pytest.raises(lfcam.InputError, match=r"x\.flo"):
        read_flo(bad)
    good = tmp_path / "y.flo"
    flow = np.arange(24, dtype=np.float32).reshape(3, 4, 2)
    flow[1, 2] = 1.6666668e9
    good.write_bytes(
        np.float32(202021.25).tobytes() + np.array([4, 3], "<i4").tobytes() + flow.tobytes()
    )
    got = read_flo(good)
    assert np.isnan(got[1, 2]).all()
    ok = np.ones((3, 4), bool)
    ok[1, 2] = False
    np.testing.assert_array_equal(got[ok], flow[ok])
    good.write_bytes(good.read_bytes()[:-4])
    with pytest.raises(lfcam.InputError, match="does not match"):
        read_flo(good)
