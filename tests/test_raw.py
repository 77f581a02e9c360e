"""Camera raw files: DNGs written from Bayer mosaics read back through rawpy (LibRaw),
their metadata through exifread, and the simulator's DNG captures calibrated and
processed end to end."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

import lfcam
from lfcam.cli import main
from lfcam.errors import LfcamWarning
from lfcam.io import (
    CaptureMetadata,
    demosaic,
    files,
    read_image,
    read_metadata,
    read_raw,
    to_float,
    write_dng,
)
from lfcam.io.raw import read_camera_raw
from lfcam.sim import SimConfig

rawpy = pytest.importorskip("rawpy")

META = CaptureMetadata(
    focal_length_mm=75.0, exposure_s=0.004, iso=400.0, f_number=2.8, make="Acme", model="LF-1"
)


def _mosaic(rgb: np.ndarray, cfa: str) -> np.ndarray:
    """The Bayer mosaic of an RGB image: each pixel keeps the colour ``cfa`` gives it."""
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        out[dy::2, dx::2] = rgb[dy::2, dx::2, "RGB".index(cfa[k])]
    return out


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_dng_cfa_values_and_metadata_survive(tmp_path, cfa) -> None:
    rng = np.random.default_rng(1)
    v = rng.integers(0, 256, (48, 70), dtype=np.uint16)  # an 8-bit sensor
    black = 64
    path = tmp_path / "a.dng"
    write_dng(path, v + black, cfa, black_level=black, white_level=black + 255, metadata=META)
    # LibRaw itself sees the stored values, levels and mosaic.
    with rawpy.imread(str(path)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, v + black)
        assert list(raw.black_level_per_channel) == [black] * 4
        assert raw.white_level == black + 255
        desc = raw.color_desc.decode()
        assert "".join(desc[c] for c in raw.raw_colors_visible[:2, :2].ravel()) == cfa
    # lfcam's mosaic: black subtracted, white at 65535, exactly v * 257.
    mosaic, got_cfa = read_camera_raw(path, mosaic=True)
    assert got_cfa == cfa
    assert mosaic.dtype == np.uint16
    np.testing.assert_array_equal(mosaic, v * 257)
    # With the calibration's Bayer pattern: the same demosaic as any Bayer frame.
    np.testing.assert_array_equal(read_raw(path, cfa), demosaic(v.astype(np.uint16) * 257, cfa))
    assert read_metadata(path) == META


def test_dng_demosaiced_by_libraw_is_linear_without_white_balance(tmp_path) -> None:
    # A smooth image of distinct colours, mosaicked: LibRaw's demosaic must give the
    # same linear camera RGB (no gamma, no auto-brightness, no white balance).
    H, W = 64, 96
    yy, xx = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    rgb = np.stack([0.2 + 0.5 * xx, 0.6 - 0.3 * yy, 0.1 + 0.2 * xx * yy], -1)
    v = np.round(_mosaic(rgb, "RGGB") * 4095).astype(np.uint16)  # a 12-bit sensor
    path = tmp_path / "smooth.dng"
    write_dng(path, v + 256, "RGGB", black_level=256, white_level=256 + 4095)
    img = read_image(path)
    assert img.shape == (H, W, 3)
    assert img.dtype == np.uint16
    got = to_float(img)[4:-4, 4:-4]
    err = np.abs(got - rgb[4:-4, 4:-4])
    assert err.max() < 2e-3, err.max()
    assert read_raw(path).shape == (H, W, 3)  # read_raw without bayer: the same image
    assert read_metadata(path) == CaptureMetadata(make="lfcam", model="lfcam simulated camera")


def test_raw_errors_name_the_file(tmp_path, monkeypatch) -> None:
    path = tmp_path / "a.dng"
    write_dng(path, np.zeros((32, 48), np.uint16), "RGGB", white_level=4095)
    with pytest.raises(lfcam.InputError, match=r"a\.dng.*mosaic is RGGB.*--bayer GBRG"):
        read_raw(path, "GBRG")
    bad = tmp_path / "broken.nef"
    bad.write_bytes(b"not a raw file at all" * 10)
    with pytest.raises(lfcam.InputError, match=r"broken\.nef: not a readable camera raw"):
        read_raw(bad)
    with pytest.raises(lfcam.InputError, match=r"missing\.cr2: no such file"):
        read_raw(tmp_path / "missing.cr2")
    # Without the extra: a clear message naming it.
    monkeypatch.setitem(sys.modules, "rawpy", None)
    monkeypatch.setitem(sys.modules, "exifread", None)
    with pytest.raises(lfcam.InputError, match=r'a\.dng: .*pip install "lfcam\[raw\]"'):
        read_raw(path)
    with pytest.raises(lfcam.InputError, match=r'a\.dng: .*pip install "lfcam\[raw\]"'):
        read_metadata(path)


def test_simulated_dng_equals_png_capture(tmp_path) -> None:
    cfg = SimConfig(
        view_size=(96, 72),
        bayer="RGGB",
        captures_per_distance=1,
        white_captures=1,
        distances=(1.0,),
        scenes=("layered",),
        seed=5,
    )
    png = lfcam.simulate(tmp_path / "png", cfg, truth=False)
    dng = lfcam.simulate(tmp_path / "dng", cfg.replace(raw_format="dng"), truth=False)
    a, b = png.captures["layered"], dng.captures["layered"]
    assert b.suffix == ".dng"
    mosaic, cfa = read_camera_raw(b, mosaic=True)
    np.testing.assert_array_equal(mosaic, read_image(a).astype(np.uint16) * 257)
    assert cfa == "RGGB"
    # Demosaiced from 8 or 16 bits: the same within the 8-bit rounding.
    np.testing.assert_allclose(
        to_float(read_raw(b, "RGGB")), to_float(read_raw(a, "RGGB")), atol=1 / 255
    )
    meta = read_metadata(b)
    assert meta.focal_length_mm == pytest.approx(100.0)
    assert meta.exposure_s == pytest.approx(0.01)
    assert meta.iso == 100
    assert meta.f_number is not None
    assert meta.model == "simulated 3x4 light-field camera"
    with pytest.raises(lfcam.InputError, match="bayer"):
        cfg.replace(raw_format="dng", bayer=None)


def test_dng_camera_calibrates_and_processes(tmp_path, capsys) -> None:
    sim = tmp_path / "sim"
    code = main(
        [
            "simulate",
            str(sim),
            "--view-size",
            "200x150",
            "--bayer",
            "RGGB",
            "--format",
            "dng",
            "--captures",
            "2",
            "--scenes",
            "planes",
        ]
    )
    assert code == 0, capsys.readouterr().err
    assert sorted(p.suffix for p in (sim / "calibration" / "white").iterdir()) == [".dng"] * 3
    cal_path = tmp_path / "cam.lfcal"
    assert main(["calibrate", str(sim / "calibration"), "-o", str(cal_path)]) == 0
    cal = lfcam.Calibration.load(cal_path)
    assert cal.bayer == "RGGB"
    truth = lfcam.sim.load_truth(sim / "truth" / "camera.npz")
    # The tolerance of tests/test_calibrate.py (1% of Z_b), on a smaller camera.
    assert abs(cal.z_c - float(truth["z_c"])) <= 0.01 * float(truth["z_b"])
    out = tmp_path / "out"
    assert main(["process", str(sim / "captures"), "-c", str(cal_path), "-o", str(out)]) == 0
    result = json.loads((out / "planes" / "result.json").read_text())
    assert result["capture"]["focal_length_mm"] == pytest.approx(100.0)
    assert result["capture"]["iso"] == 100
    depth = read_image(out / "planes" / "depth.tiff")
    # The outputs are cut to the reference view's box (result.json's frame).
    (x0, y0), (h, w) = result["frame"]["offset_xy"], result["frame"]["shape"]
    z_true = read_image(sim / "truth" / "planes" / "depth.tiff")[y0 : y0 + h, x0 : x0 + w]
    rel = np.abs(depth - z_true) / z_true
    assert np.nanmedian(rel[cal.masks[cal.reference][y0 : y0 + h, x0 : x0 + w]]) <= 0.01


def test_raw_size_checked_before_decoding(tmp_path, monkeypatch) -> None:
    """The sensor's declared size is refused before LibRaw unpacks it."""
    path = tmp_path / "a.dng"
    write_dng(path, np.zeros((32, 48), np.uint16), "RGGB", white_level=4095)
    assert read_camera_raw(path, mosaic=True)[0].shape == (32, 48)
    monkeypatch.setattr(files, "MAX_IMAGE_PIXELS", 32 * 48 - 1)
    for read in (
        lambda: read_camera_raw(path, mosaic=True),
        lambda: read_image(path),
        lambda: read_raw(path, "RGGB"),
    ):
        with pytest.raises(lfcam.InputError) as e:
            read()
        assert str(e.value) == (
            f"{path}: the header declares a 48 x 32 image, larger than lfcam reads"
            f" (65535 px a side, {32 * 48 - 1} px in all)"
        )
    monkeypatch.setattr(files, "MAX_IMAGE_PIXELS", 1 << 28)
    monkeypatch.setattr(files, "MAX_IMAGE_SIDE", 47)
    with pytest.raises(lfcam.InputError, match=r"a 48 x 32 image, larger than lfcam reads"):
        read_image(path)


def test_metadata_from_the_bytes_read_and_damage_only_warns(tmp_path, monkeypatch) -> None:
    path = tmp_path / "a.dng"
    write_dng(path, np.zeros((32, 48), np.uint16), "RGGB", white_level=4095, metadata=META)
    data = path.read_bytes()
    path.unlink()  # parsed from the bytes given, not read again
    assert read_metadata(path, data=data) == META
    assert read_raw(path, "RGGB", data=data).shape == (32, 48, 3)
    exifread = pytest.importorskip("exifread")

    def broken(*args, **kw):  # type: ignore[no-untyped-def]
        raise IndexError("list index out of range")

    monkeypatch.setattr(exifread, "process_file", broken)
    with pytest.warns(LfcamWarning) as w:
        assert read_metadata(path, data=data) == CaptureMetadata()
    assert [str(x.message) for x in w] == [
        f"{path}: unreadable EXIF metadata (IndexError: list index out of range);"
        " recorded as unknown"
    ]


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("iso", 70_000.0, "metadata.iso: expected 1 to 65535, got 70000.0"),
        ("iso", float("nan"), "metadata.iso: expected 1 to 65535, got nan"),
        ("exposure_s", float("inf"), "metadata.exposure_s: expected 1e-06 to 4294.97 s, got inf"),
        ("exposure_s", 1e-9, "metadata.exposure_s: expected 1e-06 to 4294.97 s, got 1e-09"),
        ("f_number", -2.0, "metadata.f_number: expected 0.01 to 4.29497e+07, got -2.0"),
        ("focal_length_mm", 5e6, "metadata.focal_length_mm: expected 0.001 to 4.29497e+06 mm"),
    ],
)
def test_write_dng_refuses_metadata_out_of_range(tmp_path, field, value, message) -> None:
    path = tmp_path / "a.dng"
    meta = CaptureMetadata(**{field: value})
    with pytest.raises(lfcam.InputError) as e:
        write_dng(path, np.zeros((32, 48), np.uint16), "RGGB", metadata=meta)
    assert str(e.value).startswith(message)
    assert list(tmp_path.iterdir()) == []


def test_write_dng_is_atomic(tmp_path, monkeypatch) -> None:
    import tifffile

    path = tmp_path / "a.dng"
    write_dng(path, np.zeros((32, 48), np.uint16), "RGGB", white_level=4095)
    before = path.read_bytes()
    real = tifffile.imwrite

    def half(file, *args, **kw):  # type: ignore[no-untyped-def]
        real(file, *args, **kw)
        with open(file, "r+b") as fh:
            fh.truncate(100)
        raise OSError("disk full")

    monkeypatch.setattr(tifffile, "imwrite", half)
    with pytest.raises(OSError, match="disk full"):
        write_dng(path, np.ones((32, 48), np.uint16), "RGGB", white_level=4095)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["a.dng"]
