"""Zoom settings: the simulator's parfocal zoom (each setting with its own calibration
boards, captures and ground truth) and a calibration file of several settings."""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest

import lfcam
from lfcam.calibration.file import info, load_settings, save_settings
from lfcam.cli import main
from lfcam.io import read_metadata
from lfcam.sim import SimConfig, load_truth
from test_calibration_file import make_values


def _two_settings() -> tuple[lfcam.Calibration, lfcam.Calibration]:
    a = dataclasses.replace(lfcam.Calibration(**make_values(metric=True)), focal_length=50.0)
    b = dataclasses.replace(a, focal_length=100.0, z_c=a.z_c * 1.5, offsets=a.offsets * 2)
    return a, b


def test_settings_file_stores_what_differs_and_picks_by_focal_length(tmp_path) -> None:
    a, b = _two_settings()
    path = save_settings(tmp_path / "z.lfcal", [a, b])
    with h5py.File(path, "r") as f:
        # The warp maps (equal) are stored once, at the root.
        assert sorted(f["zoom/1"].keys()) == ["focal_length", "offsets", "z_c"]
    first, second = load_settings(path)
    np.testing.assert_array_equal(second.warps, a.warps)
    np.testing.assert_array_equal(second.offsets, b.offsets)
    assert (first.focal_length, second.focal_length) == (50.0, 100.0)
    assert second.z_c == b.z_c
    # Within 2% of a setting's focal length.
    assert lfcam.Calibration.load(path, focal_length=99.0).focal_length == 100.0
    with pytest.raises(lfcam.InputError, match=r"has zoom settings 50, 100 mm"):
        lfcam.Calibration.load(path)
    with pytest.raises(lfcam.InputError, match=r"focal length 75 mm matches none of .*50, 100 mm"):
        lfcam.Calibration.load(path, focal_length=75.0)
    text = info(path)
    assert "zoom settings" in text
    assert "100 mm" in text
    with pytest.raises(lfcam.CalibrationError, match="two zoom settings"):
        save_settings(tmp_path / "bad.lfcal", [a, a])
    # One setting: the file of today, every focal length served.
    one = lfcam.Calibration(**make_values(metric=True))
    single = one.save(tmp_path / "one.lfcal")
    assert np.isnan(lfcam.Calibration.load(single, focal_length=35.0).focal_length)


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
