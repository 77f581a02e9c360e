"""Shared fixtures: the reference simulated camera, simulated and calibrated once."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

import lfcam
from lfcam.calibration.calibrate import CalibrationRun, run_calibration
from lfcam.sim import SimConfig, SimulationResult, load_truth


@dataclass
class Camera:
    sim: SimulationResult
    run: CalibrationRun
    truth: dict[str, np.ndarray]

    @property
    def cal(self) -> lfcam.Calibration:
        return self.run.calibration


@pytest.fixture(scope="session")
def reference_camera(tmp_path_factory) -> Camera:
    """The reference camera: 3 x 4, 480 x 360 px views, 8-bit, noise,
    3 board distances x 5 captures, and four scenes (one a flat board at a
    distance not used in calibration)."""
    root = tmp_path_factory.mktemp("reference")
    cfg = SimConfig(scenes=("planes", "spheres", "layered", "board"))
    sim = lfcam.simulate(root / "sim", cfg)
    run = run_calibration(sim.calibration_dir)
    return Camera(sim, run, load_truth(sim.truth_dir / "camera.npz"))
