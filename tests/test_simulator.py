"""The camera simulator against docs/design.md: explicit ray geometry vs plane + parallax."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

import lfcam
from lfcam.io import read_image
from lfcam.sim import SimConfig, SimulatedCamera, load_truth
from lfcam.sim.scenes import add_noise, make_scene, trace

# Several cameras as users have them: other grids, optics, distortions, references.
CAMERAS = {
    "reference-3x4": SimConfig(),
    "3x3": SimConfig(grid=(3, 3), seed=5),
    "4x4-short-f-strong-distortion": SimConfig(
        grid=(4, 4), focal_length=0.08, lens_to_lenslet=0.2, distortion=2.0, seed=7
    ),
    "2x5-off-reference-1mpx": SimConfig(
        grid=(2, 5),
        reference=(0, 3),
        view_size=(1200, 900),
        lens_to_lenslet=0.3,
        distances=(0.7, 1.3, 2.0),
        seed=11,
    ),
    # A parfocal zoom's setting: its principal plane moved with the focal length.
    "3x4-zoom-50mm-setting": SimConfig(zoom=(50.0, 100.0), seed=4).zoom_setting(50.0),
}


def _plane_parallax_error(cam: SimulatedCamera, rng: np.random.Generator, n: int = 3000):
    """Largest |p_i - (p + o_i s)| in rectified px over random points seen by both views."""
    worst = 0.0
    seen = 0
    for i in range(cam.N):
        z = rng.uniform(0.45, 4.0, n)
        xy = rng.uniform(-0.07, 0.07, (n, 2)) * z[:, None]
        P = np.column_stack([xy, z])
        a_ref = cam.project(cam.ref, P)
        a_i = cam.project(i, P)
        # Keep points that land inside both views' crops (the images exist there).
        ok = np.ones(n, bool)
        for j, a in ((cam.ref, a_ref), (i, a_i)):
            x0, y0, w, h = cam.crops()[j]
            xy_raw = cam.raw_from_sensor(a)
            ok &= np.isfinite(xy_raw).all(1)
            with np.errstate(invalid="ignore"):
                ok &= (xy_raw[:, 0] >= x0) & (xy_raw[:, 0] < x0 + w)
                ok &= (xy_raw[:, 1] >= y0) & (xy_raw[:, 1] < y0 + h)
        p = cam.rect_from_sensor(cam.ref, a_ref[ok])
        p_i = cam.rect_from_sensor(i, a_i[ok])
        s = 1.0 - (cam.z_b - cam.z_c) / (z[ok] - cam.z_c)
        pred = p + cam.offsets[i] * s[:, None]
        worst = max(worst, float(np.abs(p_i - pred).max()))
        seen += int(ok.sum())
    return worst, seen


@pytest.mark.parametrize("name", list(CAMERAS))
def test_traced_rays_obey_plane_plus_parallax(name: str) -> None:
    """docs/design.md, "Plane and parallax": p_i = p + o_i s, with Z_c = f D / (D - f),
    b_i = -l_i Z_c / D.

    The simulator traces rays explicitly (thin-lens imaging, pinholes, per-lenslet
    distortion); nothing in it uses the equation. They agree to 1e-3 px.
    """
    cam = SimulatedCamera(CAMERAS[name])
    worst, seen = _plane_parallax_error(cam, np.random.default_rng(1))
    assert seen > 2000 * cam.N / 3  # enough points are visible in both views
    assert worst < 1e-3, f"{name}: plane + parallax off by {worst:.3g} px"


def test_parallax_fails_with_z_c_zero() -> None:
    """The check can fail: assuming Z_c = 0 (a naive camera model) is far off."""
    cam = SimulatedCamera(SimConfig())
    rng = np.random.default_rng(2)
    z = rng.uniform(0.6, 3.0, 500)
    P = np.column_stack([rng.uniform(-0.01, 0.01, (500, 2)) * z[:, None], z])
    i = 3
    p = cam.rect_from_sensor(cam.ref, cam.project(cam.ref, P))
    p_i = cam.rect_from_sensor(i, cam.project(i, P))
    s_wrong = 1.0 - cam.z_b / z
    o_wrong = (cam.b[i] - cam.b[cam.ref]) / cam.rect_pitch
    ok = np.isfinite(p).all(1) & np.isfinite(p_i).all(1)
    err = np.abs(p_i - (p + o_wrong * s_wrong[:, None]))[ok]
    assert err.max() > 1.0


@pytest.mark.parametrize("name", list(CAMERAS))
def test_optical_centres_give_o_times_zb_over_zc(name: str) -> None:
    """docs/design.md, "Parallax fit": image-circle centres mapped to the rectified frame,
    relative to the reference, are d_i = o_i Z_b / Z_c (not o_i)."""
    cam = SimulatedCamera(CAMERAS[name])
    c = np.array([cam.rect_from_sensor(i, cam.optical_centre_sensor(i)) for i in range(cam.N)])
    d = c - c[cam.ref]
    np.testing.assert_allclose(d, cam.offsets * cam.z_b / cam.z_c, atol=1e-6)
    assert cam.z_b / cam.z_c > 3  # the scale the paper leaves open is large


def test_distortion_is_strong_smooth_and_inverted_exactly() -> None:
    cam = SimulatedCamera(SimConfig())
    rng = np.random.default_rng(3)
    for i in range(cam.N):
        x0, y0, w, h = cam.crops()[i]
        xy = np.column_stack([rng.uniform(x0, x0 + w, 2000), rng.uniform(y0, y0 + h, 2000)])
        a = cam.sensor_from_raw(xy)
        q = cam.ideal_from_actual(i, a)
        shift_px = np.abs(q - a).max() / cam.pixel_pitch
        assert 3.0 < shift_px < 60.0  # strong: several pixels, up to tens of pixels
        back = cam.actual_from_ideal(i, q)
        np.testing.assert_allclose(back, a, rtol=0, atol=1e-6 * cam.pixel_pitch)


def test_true_warps_map_back_to_their_rectified_pixel() -> None:
    cam = SimulatedCamera(SimConfig(view_size=(160, 120), seed=3))
    warps, masks = cam.warps()
    crops = cam.crops()
    assert warps.shape == (cam.N, cam.H_rect, cam.W_rect, 2)
    vv, uu = np.mgrid[0 : cam.H_rect, 0 : cam.W_rect]
    for i in range(cam.N):
        m = masks[i]
        assert m.mean() > 0.15
        a = cam.sensor_from_raw(warps[i][m].astype(np.float64) + crops[i, :2])
        uv = cam.rect_from_sensor(i, a)
        # float32 maps: about 1e-5 px of rounding.
        np.testing.assert_allclose(uv, np.column_stack([uu[m], vv[m]]), atol=2e-4)
    # The reference view sees the middle of the frame; every view sees part of it.
    assert masks[cam.ref, cam.H_rect // 2, cam.W_rect // 2]


def test_crops_and_centres_are_consistent() -> None:
    cam = SimulatedCamera(SimConfig())
    crops = cam.crops()
    assert crops.shape == (12, 4)
    assert len({(int(w), int(h)) for w, h in crops[:, 2:]}) == 1
    w, h = crops[0, 2:]
    assert 0.8 * 480 < w <= 480
    assert 0.9 * 360 < h <= 360
    assert (crops[:, 0] >= 0).all()
    assert (crops[:, 1] >= 0).all()
    assert (crops[:, 0] + w <= cam.W_raw).all()
    assert (crops[:, 1] + h <= cam.H_raw).all()
    centres = cam.centres()
    mid = crops[:, :2] + crops[:, 2:] / 2.0
    assert np.abs(centres - mid).max() < 25.0  # the circle is near the crop centre
    # Non-axial distortion moves the visible circle's centre off the optical centre,
    # by a few pixels: a small error of the optical-centre route (docs/design.md, "Parallax fit").
    off = np.linalg.norm(centres - cam.optical_centres(), axis=1)
    assert 0.3 < np.median(off) < 12.0
    # The circle is clipped by the baffle at the top and bottom, not at the sides.
    r_px = cam.circle_radius / cam.pixel_pitch
    assert 360 / 2 < r_px < 480 / 2  # cell of 480 x 360 px


def test_board_depth_truth_is_exact() -> None:
    cfg = SimConfig(view_size=(160, 120), scenes=("board",), board_distance=1.37)
    cam = SimulatedCamera(cfg)
    vv, uu = np.mgrid[0 : cam.H_rect, 0 : cam.W_rect].astype(np.float64)
    from lfcam.sim.scenes import reference_rays

    x0, m = reference_rays(cam, np.stack([uu, vv], -1))
    _, depth, labels = trace(make_scene("board", cam), x0, m)
    np.testing.assert_allclose(depth, 1.37, rtol=1e-12)
    assert (labels == 1).all()


def test_reference_rays_pass_through_the_board_pixel_and_the_optical_centre() -> None:
    from lfcam.sim.scenes import reference_rays

    cam = SimulatedCamera(SimConfig(seed=4))
    uv = np.random.default_rng(0).uniform(0, [cam.W_rect, cam.H_rect], (100, 2))
    x0, m = reference_rays(cam, uv)
    np.testing.assert_allclose(x0 - m * cam.z_b, cam.board_from_rect(uv), atol=1e-12)
    np.testing.assert_allclose(
        x0 - m * cam.z_c, np.broadcast_to(cam.b[cam.ref], x0.shape), atol=1e-12
    )


def test_noise_follows_the_poisson_gaussian_model() -> None:
    cfg = SimConfig(full_well=4000.0, read_noise=5.0, bit_depth=16)
    rng = np.random.default_rng(0)
    levels = np.array([0.05, 0.3, 0.8], np.float32)
    clean = np.broadcast_to(levels[None, None, :], (400, 500, 3)).copy()
    raw = add_noise(clean, cfg, rng).astype(np.float64) / 65535.0
    for k, x in enumerate(levels):
        var = raw[..., k].var()
        expect = (x * cfg.full_well + cfg.read_noise**2) / cfg.full_well**2
        assert abs(var / expect - 1) < 0.03
        assert abs(raw[..., k].mean() - x) < 1e-3


def test_bayer_mosaic_layout() -> None:
    clean = np.zeros((4, 6, 3), np.float32)
    clean[..., 0], clean[..., 1], clean[..., 2] = 0.2, 0.5, 0.8
    cfg = SimConfig(bayer="GRBG", full_well=1e9, read_noise=0.0)
    raw = add_noise(clean, cfg, np.random.default_rng(0))
    assert raw.shape == (4, 6)
    assert raw.dtype == np.uint8
    expect = np.array([[0.5, 0.2], [0.8, 0.5]])  # G R / B G
    np.testing.assert_allclose(raw[:2, :2] / 255.0, expect, atol=1 / 255)
    np.testing.assert_array_equal(raw[2:4, 2:4], raw[:2, :2])


def test_config_errors_name_the_setting(tmp_path) -> None:
    with pytest.raises(lfcam.InputError, match="grid"):
        SimConfig(grid=(1, 1))
    with pytest.raises(lfcam.InputError, match="focal_length"):
        SimConfig(focal_length=0.3, lens_to_lenslet=0.2)
    with pytest.raises(lfcam.InputError, match="reference"):
        SimConfig(grid=(3, 4), reference=(3, 0))
    with pytest.raises(lfcam.InputError, match="scenes"):
        SimConfig(scenes=("nope",))
    with pytest.raises(ValueError, match="bit_depth"):  # InputError is a ValueError
        SimConfig(bit_depth=12)
    bad = tmp_path / "cam.toml"
    bad.write_text("grid = [3, 4]\nfocal_lenght = 0.1\n")
    with pytest.raises(lfcam.InputError, match=r"cam\.toml.*focal_lenght"):
        SimConfig.from_toml(bad)
    bad.write_text("grid = [3, \n")
    with pytest.raises(lfcam.InputError, match="not valid TOML"):
        SimConfig.from_toml(bad)
    good = tmp_path / "good.toml"
    good.write_text("seed = 4\n[camera]\ngrid = [3, 3]\nview_size = [200, 150]\n")
    cfg = SimConfig.from_toml(good, bit_depth=16)
    assert cfg.grid == (3, 3)
    assert cfg.view_size == (200, 150)
    assert cfg.seed == 4
    assert cfg.bit_depth == 16


SMALL = SimConfig(
    view_size=(160, 120),
    captures_per_distance=2,
    white_captures=2,
    scenes=("layered", "board"),
    seed=9,
)


@pytest.fixture(scope="module")
def small_sim(tmp_path_factory):
    return lfcam.simulate(tmp_path_factory.mktemp("sim") / "out", SMALL)


def test_simulate_writes_the_calibration_layout(small_sim) -> None:
    root = small_sim.root
    cal = root / "calibration"
    assert (cal / "pattern.png").is_file()
    assert len(list((cal / "white").glob("*.png"))) == 2
    for z in SMALL.distances:
        assert len(list((cal / f"board_{z:.2f}m").glob("*.png"))) == 2
    toml = (cal / "camera.toml").read_text()
    assert "grid = [3, 4]" in toml
    assert "reference = [1, 1]" in toml
    assert "pattern_pitch" in toml
    raw = read_image(small_sim.captures["layered"])
    assert raw.shape == (360, 640, 3)
    assert raw.dtype == np.uint8
    pattern = read_image(cal / "pattern.png")
    cam = small_sim.camera
    assert pattern.shape == (cam.H_pat, cam.W_pat)
    info = json.loads((root / "simulation.json").read_text())
    assert info["config"]["seed"] == 9
    assert not list(root.parent.glob(".out.tmp-*"))  # no temporary folder left


def test_simulate_truth(small_sim) -> None:
    cam = small_sim.camera
    t = load_truth(small_sim.truth_dir / "camera.npz")
    assert t["warps"].shape == (12, cam.H_rect, cam.W_rect, 2)
    np.testing.assert_allclose(t["offsets"], cam.offsets)
    assert float(t["z_c"]) == pytest.approx(0.1 * 0.22 / 0.12)
    assert float(t["z_b"]) == 1.0
    depth = tifffile.imread(small_sim.truth_dir / "layered" / "depth.tiff")
    assert depth.shape == (cam.H_rect, cam.W_rect)
    assert depth.dtype == np.float32
    assert np.isfinite(depth).all()
    assert 0.7 < depth.min() < 0.8
    assert 1.9 < depth.max() < 2.1
    ref2 = tifffile.imread(small_sim.truth_dir / "layered" / "reference_2x.tiff")
    assert ref2.shape == (2 * cam.H_rect, 2 * cam.W_rect, 3)
    board = tifffile.imread(small_sim.truth_dir / "board" / "depth.tiff")
    np.testing.assert_allclose(board, SMALL.board_distance, rtol=1e-6)


def test_white_capture_is_bright_and_cast(small_sim) -> None:
    cam = small_sim.camera
    white = read_image(small_sim.calibration_dir / "white" / "white_00.png").astype(float) / 255
    x0, y0, w, h = cam.crops()[cam.ref]
    mid = white[y0 + h // 2 - 5 : y0 + h // 2 + 5, x0 + w // 2 - 5 : x0 + w // 2 + 5].mean((0, 1))
    cast = np.array(SMALL.colour_cast) / max(SMALL.colour_cast)
    # Near the centre: exposure x colour cast x (vignetting ~1) x transmission.
    np.testing.assert_allclose(mid / mid.max(), cast, atol=0.03)
    assert 0.7 < mid.max() < 0.95
    left = cam.crops()[cam.ref - 1]
    xm = (left[0] + left[2] + x0) // 2  # the dark gap between two lenslets
    assert white[y0 : y0 + h, xm - 1 : xm + 2].max() < 0.03


def test_deterministic_by_seed(tmp_path) -> None:
    cfg = SimConfig(
        view_size=(96, 72),
        captures_per_distance=1,
        white_captures=1,
        scenes=("spheres",),
        seed=21,
    )
    a = lfcam.simulate(tmp_path / "a", cfg, truth=False)
    b = lfcam.simulate(tmp_path / "b", cfg, truth=False)
    c = lfcam.simulate(tmp_path / "c", cfg.replace(seed=22), truth=False)
    for rel in [
        "captures/spheres.png",
        "calibration/pattern.png",
        "calibration/white/white_00.png",
    ]:
        assert (a.root / rel).read_bytes() == (b.root / rel).read_bytes()
        assert (a.root / rel).read_bytes() != (c.root / rel).read_bytes()


def test_simulate_refuses_non_empty_folder_and_16bit_tiff(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    cfg = SimConfig(view_size=(96, 72), captures_per_distance=1, white_captures=1, scenes=())
    with pytest.raises(lfcam.InputError, match="not empty"):
        lfcam.simulate(out, cfg)
    assert (out / "keep.txt").exists()
    res = lfcam.simulate(
        tmp_path / "t", cfg.replace(bit_depth=16, raw_format="tiff", bayer="RGGB"), truth=False
    )
    raw = tifffile.imread(next((res.calibration_dir / "white").glob("*.tiff")))
    assert raw.dtype == np.uint16
    assert raw.ndim == 2
