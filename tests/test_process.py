"""Per-capture processing against the simulator's ground truth."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import tifffile

import lfcam
from accuracy import accuracy
from accuracy import truth as truth_of
from lfcam.cli import main
from lfcam.outputs import reference_box
from lfcam.pipeline import process_capture
from lfcam.products.geometry import points_from_depth


@pytest.fixture(scope="module")
def processed(reference_camera):
    cam = reference_camera
    return {n: process_capture(p, cam.cal) for n, p in cam.sim.captures.items()}


@pytest.mark.parametrize("scene", ["planes", "spheres", "layered"])
def test_depth_accuracy(reference_camera, processed, scene) -> None:
    cam = reference_camera
    z = processed[scene].depth.depth
    truth, labels = truth_of(cam.sim, scene)
    seen = cam.cal.masks[cam.cal.reference]
    med, cover, bad = accuracy(z, truth, labels, seen)
    assert med <= 0.01, f"{scene}: median relative error {med:.4f}"
    assert cover >= 0.95, f"{scene}: coverage {cover:.3f}"
    assert bad <= 0.05, f"{scene}: {100 * bad:.1f}% of pixels off by > 5% (or unknown)"


def test_occlusions_need_robust_view_selection(reference_camera, processed) -> None:
    """Plain least squares over all views fails near occlusions; the robust kernel
    does not (this shows the test above can fail)."""
    cam = reference_camera
    res = processed["layered"]
    from lfcam.processing.depth import compute_flows, depth_from_parallax

    flows, _ = compute_flows(res.views, cam.cal.reference)
    o = cam.cal.offsets[:, None, None, :]
    ok = np.isfinite(flows).all(-1)
    num = np.where(ok, (np.nan_to_num(flows) * o).sum(-1), 0).sum(0)
    den = np.where(ok, (o**2).sum(-1), 0).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        s_plain = num / den
    truth, labels = truth_of(cam.sim, "layered")
    seen = cam.cal.masks[cam.cal.reference]
    z_plain = depth_from_parallax(s_plain, cam.cal.z_b, cam.cal.z_c)
    _, _, bad_plain = accuracy(z_plain, truth, labels, seen)
    _, _, bad_robust = accuracy(res.depth.depth, truth, labels, seen)
    assert bad_robust < bad_plain


def test_board_at_an_unseen_distance_is_flat(reference_camera, processed) -> None:
    cam = reference_camera
    z = processed["board"].depth.depth
    pts, _, units = points_from_depth(z, cam.cal)
    assert units == "m"
    c = pts.mean(0)
    _, _, vt = np.linalg.svd((pts - c).astype(np.float64), full_matrices=False)
    dist = (pts - c) @ vt[2]
    rms = float(np.sqrt(np.mean(dist**2)))
    d0 = cam.sim.camera.cfg.board_distance
    assert rms <= 0.005 * d0, f"plane-fit RMS {rms * 1000:.2f} mm at {d0} m"
    assert abs(float(np.median(z[np.isfinite(z)])) - d0) < 0.01 * d0
    assert abs(abs(vt[2, 2]) - 1) < 0.01  # fronto-parallel


def test_rectify_matches_opencv(reference_camera) -> None:
    cam = reference_camera
    cal = cam.cal
    raw = lfcam.read_raw(cam.sim.captures["planes"])
    views = lfcam.rectify(raw, cal)
    assert views.shape == (12, *cal.rect_shape, 3)
    i = 3
    x0, y0, w, h = cal.crops[i]
    src = (raw.astype(np.float32) / 255 * cal.gains)[y0 : y0 + h, x0 : x0 + w]
    ref = cv2.remap(src, cal.warps[i][..., 0], cal.warps[i][..., 1], cv2.INTER_LINEAR)
    both = np.isfinite(views[i]).all(-1)
    assert both.sum() > 0.9 * cal.masks[i].sum()
    np.testing.assert_allclose(views[i][both], ref[both], atol=1e-5)


def test_depth_from_views_on_bare_arrays(reference_camera, processed) -> None:
    cam = reference_camera
    res = processed["spheres"]
    bare = lfcam.depth_from_views(res.views, cam.cal.offsets, cam.cal.reference)
    same = np.isfinite(bare.parallax) & np.isfinite(res.depth.parallax)
    assert same.mean() > 0.2
    np.testing.assert_allclose(bare.parallax[same], res.depth.parallax[same], atol=1e-6)
    with pytest.raises(lfcam.InputError, match="offsets"):
        lfcam.depth_from_views(res.views, cam.cal.offsets[:5], cam.cal.reference)
    with pytest.raises(lfcam.InputError, match="reference"):
        lfcam.depth_from_views(res.views, cam.cal.offsets, 40)


# --------------------------------------------------------------------------
# lfcam process: outputs, resuming, bad captures, parallel jobs.
# --------------------------------------------------------------------------
def test_process_command(reference_camera, tmp_path, capsys) -> None:
    cam = reference_camera
    calf = tmp_path / "camera.lfcal"
    cam.run.save(calf)
    inp = tmp_path / "in"
    (inp / "day2").mkdir(parents=True)
    shutil.copy(cam.sim.captures["planes"], inp / "a.png")
    shutil.copy(cam.sim.captures["board"], inp / "day2" / "b.png")
    (inp / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    out = tmp_path / "out"
    code = main(["process", str(inp), "-c", str(calf), "-o", str(out), "--jobs", "2"])
    io = capsys.readouterr()
    assert code == 3, io.err  # one capture failed: reported, the others done
    assert "broken.png" in io.err
    assert "processed 2 capture(s)" in io.out
    for sub in ("a", "day2/b"):
        d = out / sub
        assert sorted(p.name for p in d.iterdir()) == [
            "confidence.tiff",
            "depth.png",
            "depth.tiff",
            "points.ply",
            "result.json",
        ]
        info = json.loads((d / "result.json").read_text())
        assert info["calibration_sha256"] == lfcam.io.file_hash(calf)
        z = tifffile.imread(d / "depth.tiff")
        assert z.dtype == np.float32
        # Cropped to the reference view's valid box, which result.json records.
        x0, y0, w, h = reference_box(cam.cal)
        assert info["frame"]["offset_xy"] == [x0, y0]
        assert z.shape == (h, w) == tuple(info["frame"]["shape"])
        assert h < cam.cal.rect_shape[0]
        assert w < cam.cal.rect_shape[1]
        ply = (d / "points.ply").read_bytes()
        assert ply.startswith(b"ply\nformat binary_little_endian 1.0")
        n = int(ply.split(b"element vertex ")[1].split(b"\n")[0])
        assert n == int(np.isfinite(z).sum())
    assert not list(out.rglob(".*tmp-*"))  # nothing half-written
    # Resumable: complete outputs are skipped.
    (inp / "broken.png").unlink()
    assert main(["process", str(inp), "-c", str(calf), "-o", str(out)]) == 0
    assert "skipped 2 complete" in capsys.readouterr().out


def test_process_bad_calibration(tmp_path, capsys) -> None:
    bad = tmp_path / "x.lfcal"
    bad.write_bytes(b"not hdf5")
    raw = tmp_path / "r.png"
    lfcam.io.write_image(raw, np.zeros((10, 10, 3), np.uint8))
    assert main(["process", str(raw), "-c", str(bad), "-o", str(tmp_path / "o")]) == 2
    assert "x.lfcal" in capsys.readouterr().err
