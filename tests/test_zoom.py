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
from lfcam.io import read_metadata, write_image
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


def test_each_capture_gets_the_setting_of_its_focal_length(tmp_path) -> None:
    a, b = _two_settings()
    zoom = lfcam.ZoomCalibration((a, b), "z.lfcal")
    assert zoom.focal_lengths == (50.0, 100.0)
    # The capture's own focal length, within 2%.
    choice = zoom.choose(capture_focal_length=50.9, capture="cap.dng")
    assert choice.calibration is a
    assert choice.chosen_by == "metadata"
    # A focal length given overrides the capture's.
    choice = zoom.choose(100.0, capture_focal_length=50.0)
    assert choice.calibration is b
    assert choice.to_dict() == {
        "focal_length_mm": 100.0,
        "chosen_by": "focal_length",
        "requested_focal_length_mm": 100.0,
        "settings_mm": [50.0, 100.0],
        "z_c_m": b.z_c,
        "z_b_m": b.z_b,
    }
    # Never the nearest setting: 51.5 mm is 3% from 50 mm.
    with pytest.raises(
        lfcam.InputError,
        match=r"cap\.dng \(its metadata\): focal length 51\.5 mm matches none of z\.lfcal's"
        r" zoom settings 50, 100 mm \(within 2%\); --zoom F",
    ):
        zoom.choose(capture_focal_length=51.5, capture="cap.dng")
    with pytest.raises(lfcam.InputError, match=r"^focal_length: focal length 75 mm .* 50, 100 mm"):
        zoom.choose(75.0, capture_focal_length=100.0)
    with pytest.raises(
        lfcam.InputError, match=r"z\.lfcal: has zoom settings 50, 100 mm: cap\.png has no focal"
    ):
        zoom.choose(capture="cap.png")
    for bad in (0.0, -50.0, float("nan"), True, "50"):
        with pytest.raises(lfcam.InputError, match="focal_length: expected a focal length > 0"):
            zoom.choose(bad)  # type: ignore[arg-type]
    with pytest.raises(lfcam.InputError, match="distinct focal lengths"):
        lfcam.ZoomCalibration((a, a))
    # A camera calibrated without zoom settings: every capture, whatever its metadata.
    one = lfcam.Calibration(**make_values(metric=True))
    choice = lfcam.ZoomCalibration.of(one).choose(capture_focal_length=35.0)
    assert choice.calibration is one
    assert choice.chosen_by == "only setting"
    assert choice.to_dict()["focal_length_mm"] is None
    # One setting calibrated at 50 mm: its focal length, or an unknown one; not 100 mm.
    only50 = lfcam.ZoomCalibration.of(a)
    assert only50.choose(capture_focal_length=49.5).calibration is a
    assert only50.choose().chosen_by == "only setting"
    with pytest.raises(lfcam.InputError, match=r"focal length 100 mm matches none of .* 50 mm"):
        only50.choose(capture_focal_length=100.0)
    with pytest.raises(lfcam.InputError, match="focal length 100 mm matches none"):
        lfcam.Calibration.load(save_settings(tmp_path / "one.lfcal", [a]), focal_length=100.0)


def test_process_refuses_a_zoom_matching_no_setting_and_a_capture_without_one(
    tmp_path, capsys
) -> None:
    a, b = _two_settings()
    cal = save_settings(tmp_path / "z.lfcal", [a, b])
    captures = tmp_path / "captures"
    captures.mkdir()
    write_image(captures / "plain.png", np.zeros((*a.raw_shape, 3), np.uint8))
    out = tmp_path / "out"
    args = ["process", str(captures), "-c", str(cal), "-o", str(out)]
    # --zoom matching no setting: refused before any capture is read.
    assert main([*args, "--zoom", "75"]) == 2
    err = capsys.readouterr().err
    assert "--zoom: focal length 75 mm matches none of" in err
    assert "zoom settings 50, 100 mm (within 2%)" in err
    assert not out.exists()
    # A capture without a focal length (a PNG has no EXIF): it fails, naming the settings.
    assert main(args) == 3
    err = capsys.readouterr().err
    assert "failed:" in err
    assert "plain.png" in err
    assert "has zoom settings 50, 100 mm" in err
    assert "has no focal length" in err
    assert not (out / "plain").exists()
    # In Python: an array has no metadata.
    zoom = lfcam.ZoomCalibration.load(cal)
    with pytest.raises(lfcam.InputError, match="raw_or_path has no focal length"):
        lfcam.process_capture(np.zeros((*a.raw_shape, 3), np.uint8), zoom)


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


@pytest.fixture(scope="module")
def zoom_calibration(tmp_path_factory):
    cfg = SimConfig(
        view_size=(200, 150),
        captures_per_distance=2,
        white_captures=2,
        scenes=(),
        zoom=(50.0, 100.0),
        seed=4,
    )
    root = tmp_path_factory.mktemp("zoomcal")
    sim = lfcam.simulate(root / "sim", cfg)
    out = root / "zoom.lfcal"
    assert main(["calibrate", str(sim.calibration_dir), "-o", str(out)]) == 0
    return sim, load_settings(out)


def _offsets_truth(sim, cal):
    """The true o_i in the frame of the warp maps the setting uses (shared: the first's)."""
    truth = load_truth(sim.zoom[cal.focal_length].truth_dir / "camera.npz")
    frame = load_truth(sim.zoom[cal.report["zoom"]["warps_from_mm"]].truth_dir / "camera.npz")
    return truth["offsets"] * float(truth["rect_pitch"]) / float(frame["rect_pitch"]), truth


def test_calibrate_a_zoom_folder_into_one_file(zoom_calibration) -> None:
    _, cals = zoom_calibration
    assert [c.focal_length for c in cals] == [50.0, 100.0]
    assert all(c.metric for c in cals)
    zoom = cals[1].report["zoom"]
    diff = zoom["warp_difference_to_first"]
    assert zoom["warps_from_mm"] == (50.0 if diff["rms_px"] <= 0.5 else 100.0)


@pytest.mark.xfail(
    strict=True,
    reason="measured on this 200 x 150 px camera (2 captures) at 50 mm: Z_c 0.0683 m against"
    " 0.0724 m (-5.7%) with a standard error of 0.0028 m (3.8%), o_i off by up to 1.46%; at"
    " 100 mm Z_c -1.07% (standard error 0.48%), o_i within 0.45%: the flow's noise on views"
    " this small; on the reference size (benchmarks/rig.py zoom) Z_c within 0.17%, o_i 0.17%",
)
def test_zoom_settings_match_their_truth(zoom_calibration) -> None:
    sim, cals = zoom_calibration
    for cal in cals:
        o, truth = _offsets_truth(sim, cal)
        z_c = float(truth["z_c"])
        assert abs(cal.z_c - z_c) <= 0.01 * z_c, f"{cal.focal_length:g} mm: Z_c {cal.z_c:.4f}"
        n = np.linalg.norm(o, axis=1)
        rel = np.linalg.norm(cal.offsets - o, axis=1)[n > 0] / n[n > 0]
        assert rel.max() <= 0.005, f"{cal.focal_length:g} mm: o_i off by {rel.max():.4f}"
