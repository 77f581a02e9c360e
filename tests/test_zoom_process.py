"""``lfcam process`` with a calibration of several zoom settings, on the simulator's
parfocal zoom: each capture of a folder gets the setting its DNG's EXIF focal length
picks (or ``--zoom``), and its depth matches that setting's ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import lfcam
from lfcam.cli import main
from lfcam.io import CaptureMetadata, read_image, write_dng
from lfcam.io.raw import read_camera_raw
from lfcam.sim import SimConfig, load_truth

pytest.importorskip("rawpy")
pytest.importorskip("exifread")

FOCAL_MM = (75.0, 100.0)
SCENE = "planes"
#: Median |Z - Z_true| / Z_true over the reference view, per setting: the issue's target
#: (1%), as for today's calibration; measured on this 200 x 150 px Bayer camera (seed 4):
#: 0.48% at 75 mm, 0.32% at 100 mm.
MAX_DEPTH_ERROR = {75.0: 0.01, 100.0: 0.01}


@pytest.fixture(scope="module")
def zoomcam(tmp_path_factory):
    root = tmp_path_factory.mktemp("zoomprocess")
    cfg = SimConfig(
        view_size=(200, 150),
        bayer="RGGB",
        raw_format="dng",
        captures_per_distance=2,
        white_captures=2,
        scenes=(SCENE,),
        zoom=FOCAL_MM,
        seed=4,
    )
    sim = lfcam.simulate(root / "sim", cfg)
    cal = root / "zoom.lfcal"
    assert main(["calibrate", str(sim.calibration_dir), "-o", str(cal)]) == 0
    return sim, cal


def _capture(sim, f: float) -> Path:
    return Path(sim.zoom[f].captures[SCENE])


def _rewrite(src: Path, dst: Path, focal_length_mm: float | None) -> Path:
    """``src``'s raw mosaic in a DNG whose metadata says ``focal_length_mm`` (None: no
    metadata at all)."""
    # Read back black-subtracted and scaled to 16 bits: written as a 16-bit sensor's.
    mosaic, cfa = read_camera_raw(src, mosaic=True)
    assert cfa is not None
    meta = None if focal_length_mm is None else CaptureMetadata(focal_length_mm=focal_length_mm)
    write_dng(dst, mosaic, cfa, black_level=0, white_level=65535, metadata=meta)
    return dst


def _truth_in_frame(sim, f: float, frame_f: float) -> np.ndarray:
    """Setting ``f``'s true depth of the scene in the rectified frame of setting
    ``frame_f`` (whose warp maps it shares): both frames are the board plane at Z_b,
    centred, at their settings' pitches."""
    own = load_truth(sim.zoom[f].truth_dir / "camera.npz")
    frame = load_truth(sim.zoom[frame_f].truth_dir / "camera.npz")
    z = read_image(sim.zoom[f].truth_dir / SCENE / "depth.tiff").astype(np.float32)
    h, w = read_image(sim.zoom[frame_f].truth_dir / SCENE / "depth.tiff").shape
    k = float(frame["rect_pitch"]) / float(own["rect_pitch"])
    xs = (np.arange(w) - (w - 1) / 2) * k + (z.shape[1] - 1) / 2
    ys = (np.arange(h) - (h - 1) / 2) * k + (z.shape[0] - 1) / 2
    mx, my = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32))
    return cv2.remap(z, mx, my, cv2.INTER_NEAREST, borderValue=float("nan"))


def _depth_error(sim, out: Path, cal: lfcam.Calibration) -> float:
    """Median relative depth error over the reference view (``--frame full`` output)."""
    depth = read_image(out / "depth.tiff")
    frame_f = cal.report["zoom"]["warps_from_mm"]
    truth = _truth_in_frame(sim, cal.focal_length, frame_f)
    assert depth.shape == truth.shape
    rel = np.abs(depth - truth) / truth
    return float(np.nanmedian(rel[cal.masks[cal.reference]]))


def _result(out: Path) -> dict:
    return json.loads((out / "result.json").read_text())


def test_a_folder_mixing_settings(zoomcam, tmp_path, capsys) -> None:
    sim, cal_path = zoomcam
    settings = {c.focal_length: c for c in lfcam.ZoomCalibration.load(cal_path).settings}
    assert sorted(settings) == list(FOCAL_MM)
    out = tmp_path / "out"
    captures = sim.root / "captures"
    code = main(["process", str(captures), "-c", str(cal_path), "-o", str(out), "--frame", "full"])
    assert code == 0, capsys.readouterr().err
    for f in FOCAL_MM:
        folder = out / _capture(sim, f).stem
        result = _result(folder)
        assert result["capture"]["focal_length_mm"] == pytest.approx(f)
        used = result["calibration_setting"]
        assert used["focal_length_mm"] == f
        assert used["chosen_by"] == "metadata"
        assert used["settings_mm"] == list(FOCAL_MM)
        assert used["z_c_m"] == settings[f].z_c
        err = _depth_error(sim, folder, settings[f])
        assert err <= MAX_DEPTH_ERROR[f], f"{f:g} mm: median depth error {err:.4f}"


def test_zoom_overrides_wrong_metadata_and_the_wrong_setting_shows(zoomcam, tmp_path) -> None:
    sim, cal_path = zoomcam
    zoom = lfcam.ZoomCalibration.load(cal_path)
    settings = {c.focal_length: c for c in zoom.settings}
    src = _capture(sim, 75.0)
    # The 75 mm capture, its EXIF saying 60 mm (a lens reporting the wrong value).
    inputs = tmp_path / "in"
    inputs.mkdir()
    wrong = _rewrite(src, inputs / "wrong_exif.dng", 60.0)
    out = tmp_path / "out"
    args = ["process", str(wrong), "-c", str(cal_path), "-o", str(out), "--frame", "full"]
    assert main([*args, "--zoom", "75"]) == 0
    result = _result(out / "wrong_exif")
    assert result["capture"]["focal_length_mm"] == pytest.approx(60.0)
    assert result["calibration_setting"]["chosen_by"] == "focal_length"
    assert result["calibration_setting"]["focal_length_mm"] == 75.0
    right = _depth_error(sim, out / "wrong_exif", settings[75.0])
    assert right <= MAX_DEPTH_ERROR[75.0]
    # The same capture with the 100 mm setting: the depth check sees the wrong setting.
    res = lfcam.process_capture(src, zoom, focal_length=100.0)
    assert res.setting is not None
    assert res.setting.calibration is settings[100.0]
    assert res.setting.chosen_by == "focal_length"
    truth = _truth_in_frame(sim, 75.0, settings[100.0].report["zoom"]["warps_from_mm"])
    assert res.depth.depth is not None
    c100 = settings[100.0]
    rel = np.abs(res.depth.depth - truth) / truth
    wrong_setting = float(np.nanmedian(rel[c100.masks[c100.reference]]))
    assert wrong_setting > 10 * MAX_DEPTH_ERROR[75.0], wrong_setting


def test_captures_matching_no_setting_fail_alone(zoomcam, tmp_path, capsys) -> None:
    sim, cal_path = zoomcam
    src = _capture(sim, 100.0)
    inputs = tmp_path / "in"
    inputs.mkdir()
    (inputs / src.name).write_bytes(src.read_bytes())
    _rewrite(src, inputs / "at_60mm.dng", 60.0)
    _rewrite(src, inputs / "no_exif.dng", None)
    out = tmp_path / "out"
    code = main(["process", str(inputs), "-c", str(cal_path), "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 3, err
    # Each failure names the capture, its focal length (if any) and the file's settings.
    lines = [line for line in err.splitlines() if "failed:" in line]
    assert len(lines) == 2, err
    at60 = next(line for line in lines if "at_60mm.dng" in line)
    assert "focal length 60 mm matches none of" in at60
    assert "zoom settings 75, 100 mm (within 2%)" in at60
    no_exif = next(line for line in lines if "no_exif.dng" in line)
    assert "has zoom settings 75, 100 mm" in no_exif
    assert "has no focal length" in no_exif
    # The good capture is done; the failed ones left nothing.
    assert _result(out / src.stem)["calibration_setting"]["focal_length_mm"] == 100.0
    assert sorted(p.name for p in out.iterdir()) == [src.stem]


_FILES = ("depth.tiff", "confidence.tiff", "points.ply")


def _same_pixels(a: Path, b: Path) -> None:
    """Two batch outputs hold the same products and the same settings."""
    for f in FOCAL_MM:
        name = f"{SCENE}_{f:g}mm"
        assert _result(a / name)["calibration_setting"] == _result(b / name)["calibration_setting"]
        for file in _FILES[:2]:
            got, want = read_image(a / name / file), read_image(b / name / file)
            assert got.tobytes() == want.tobytes(), f"{name}/{file}"
        assert (a / name / _FILES[2]).read_bytes() == (b / name / _FILES[2]).read_bytes()


@pytest.fixture(scope="module")
def mixed_reference(zoomcam, tmp_path_factory):
    """The mixed folder processed in the calling process (``jobs=1``)."""
    sim, cal_path = zoomcam
    out = tmp_path_factory.mktemp("mixed") / "jobs1"
    summary = lfcam.process_folder(sim.root / "captures", cal_path, out)
    assert len(summary.done) == len(FOCAL_MM), summary.failed
    return out


def test_mixed_folder_the_same_with_two_worker_processes(zoomcam, mixed_reference, tmp_path):
    sim, cal_path = zoomcam
    summary = lfcam.process_folder(sim.root / "captures", cal_path, tmp_path / "out", jobs=2)
    assert summary.workers == 2
    assert len(summary.done) == len(FOCAL_MM), summary.failed
    _same_pixels(tmp_path / "out", mixed_reference)


def test_mixed_folder_on_a_cluster_loads_the_file_once(zoomcam, mixed_reference, tmp_path):
    distributed = pytest.importorskip("distributed")
    from lfcam.batch.cluster import calibration_loads

    sim, cal_path = zoomcam
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        out = tmp_path / "by_path"
        summary = lfcam.process_folder(sim.root / "captures", cal_path, out, client=client)
        assert len(summary.done) == len(FOCAL_MM), summary.failed
        _same_pixels(out, mixed_reference)
        # Every setting came from one load of the file per worker that ran a capture.
        sha = lfcam.io.file_hash(cal_path)
        loads = [d for d in client.run(calibration_loads).values() if d]
        assert loads
        assert all(d == {sha: 1} for d in loads), loads
        # A ZoomCalibration without a file is scattered, and each capture still gets
        # its own setting.
        zoom = lfcam.ZoomCalibration.load(cal_path)
        out = tmp_path / "scattered"
        summary = lfcam.process_folder(sim.root / "captures", zoom, out, client=client)
        assert len(summary.done) == len(FOCAL_MM), summary.failed
        _same_pixels(out, mixed_reference)
