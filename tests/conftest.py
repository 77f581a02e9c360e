"""Shared fixtures: the reference simulated camera, simulated and calibrated once."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

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


def _printable(text: str) -> str:
    """Text with any unpaired surrogate (a non-UTF-8 file name decoded by
    ``os.fsdecode``) written as an escape, so the report can be sent as UTF-8."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """pytest-xdist's ``--dist loadfile`` (each test file whole on one worker, so its
    module fixtures are built once), with every file that uses the reference camera in
    one unit, so the session's most expensive fixture is built once."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    here = Path(__file__).parent
    shared = {
        path.relative_to(config.rootpath).as_posix()
        for path in here.glob("test_*.py")
        if "reference_camera" in path.read_text(encoding="utf-8")
    }

    class Scheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            scope = super()._split_scope(nodeid)
            return "reference_camera" if scope in shared else scope

    return Scheduling(config, log)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):
    # The hostile-input tests log file names with bytes that are not UTF-8; pytest-xdist
    # sends each report to the controller as UTF-8 and stops on such text.
    outcome = yield
    report = outcome.get_result()
    report.sections = [(title, _printable(text)) for title, text in report.sections]
