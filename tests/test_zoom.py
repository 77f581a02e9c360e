"""Zoom settings in the simulator: a parfocal zoom's settings, each with its own
calibration boards, captures and ground truth."""

from __future__ import annotations

import numpy as np
import pytest

import lfcam
from lfcam.cli import main
from lfcam.io import read_metadata
from lfcam.sim import SimConfig, load_truth


def test_parfocal_settings_keep_the_reference_image_in_place() -> None:
    cfg = SimConfig(zoom=(50, 75, 100))
    z = cfg.z_b
    gap = cfg.lens_to_lenslet - cfg.focal_length * z / (z - cfg.focal_length)
    for f in cfg.zoom:
        s = cfg.zoom_setting(f)
        assert s.focal_length == pytest.approx(f / 1000)
        assert s.lens_to_lenslet - s.focal_length * z / (z - s.focal_length) == pytest.approx(gap)
        assert s.zoom == ()
    # The reference camera is the 100 mm setting.
    assert cfg.zoom_setting(100).lens_to_lenslet == pytest.approx(SimConfig().lens_to_lenslet)
    with pytest.raises(lfcam.InputError, match="zoom"):
        SimConfig(zoom=(50, 50))


def test_simulate_zoom_writes_one_setting_per_focal_length(tmp_path, capsys) -> None:
    out = tmp_path / "zoom"
    code = main(
        [
            "simulate",
            str(out),
            "--zoom",
            "50,100",
            "--format",
            "dng",
            "--bayer",
            "RGGB",
            "--view-size",
            "96x72",
            "--captures",
            "1",
            "--distances",
            "0.7,1.0",
            "--scenes",
            "layered",
        ]
    )
    assert code == 0, capsys.readouterr().err
    cal = out / "calibration"
    assert sorted(p.name for p in cal.iterdir()) == ["white", "zoom_100mm", "zoom_50mm"]
    for f in (50, 100):
        setting = cal / f"zoom_{f}mm"
        assert (setting / "pattern.png").is_file()
        assert (setting / "camera.toml").is_file()
        assert sorted(p.name for p in setting.glob("board_*")) == ["board_0.70m", "board_1.00m"]
        capture = out / "captures" / f"layered_{f}mm.dng"
        assert read_metadata(capture).focal_length_mm == pytest.approx(f)
        truth = load_truth(out / "truth" / f"zoom_{f}mm" / "camera.npz")
        f_m, d_m = float(truth["f"]), float(truth["D"])
        assert f_m == pytest.approx(f / 1000)
        assert float(truth["z_c"]) == pytest.approx(f_m * d_m / (d_m - f_m))
        assert (out / "truth" / f"zoom_{f}mm" / "layered" / "depth.tiff").is_file()
    # Shorter focal lengths: the lenslet centres nearer the lens.
    z_c = [
        float(load_truth(out / "truth" / f"zoom_{f}mm" / "camera.npz")["z_c"]) for f in (50, 100)
    ]
    assert z_c[0] < z_c[1]
    assert np.isclose(z_c[1], SimConfig().z_c)
