"""Depth accuracy on simulated cameras other than the reference one, as users have them
(smaller views to keep CI short)."""

from __future__ import annotations

import pytest

import lfcam
from accuracy import accuracy, truth
from lfcam.calibration.calibrate import run_calibration
from lfcam.pipeline import process_capture
from lfcam.sim import SimConfig

VARIANTS = {
    "3x3-16bit-tiff": SimConfig(
        grid=(3, 3),
        view_size=(320, 240),
        bit_depth=16,
        raw_format="tiff",
        captures_per_distance=3,
        scenes=("layered",),
        seed=31,
    ),
    "4x4-strong-distortion-cast": SimConfig(
        grid=(4, 4),
        view_size=(280, 210),
        distortion=1.6,
        colour_cast=(0.6, 1.0, 0.9),
        captures_per_distance=3,
        scenes=("spheres",),
        seed=32,
    ),
    "3x4-bayer-png": SimConfig(
        view_size=(320, 240),
        bayer="RGGB",
        captures_per_distance=3,
        scenes=("planes",),
        seed=33,
    ),
}


# Measured gaps, as strict xfails (none at present: the 3x3 layered and 4x4 strong-
# distortion cameras, 6.9% and 8.6% off by > 5% before the parallax fill, now pass).
KNOWN_GAPS: dict[str, str] = {}


@pytest.mark.parametrize(
    ("name", "cfg"),
    [
        pytest.param(
            k,
            v,
            marks=[pytest.mark.xfail(strict=True, reason=KNOWN_GAPS[k])] if k in KNOWN_GAPS else [],
        )
        for k, v in VARIANTS.items()
    ],
)
def test_other_cameras(name, cfg, tmp_path) -> None:
    sim = lfcam.simulate(tmp_path / "sim", cfg)
    # scale=1: compare in the ground truth's frame (the pattern's own grid).
    cal = run_calibration(sim.calibration_dir, scale=1.0).calibration
    assert cal.grid == cfg.grid
    assert cal.metric
    scene = cfg.scenes[0]
    res = process_capture(sim.captures[scene], cal)
    depth, labels = truth(sim, scene)
    med, cover, bad = accuracy(res.depth.depth, depth, labels, cal.masks[cal.reference])
    assert med <= 0.01, f"{name}: median relative error {med:.4f}"
    assert cover >= 0.95, f"{name}: coverage {cover:.3f}"
    assert bad <= 0.05, f"{name}: {100 * bad:.1f}% off by > 5%"
