"""Outputs that explain themselves: frames and crop offsets, TIFF descriptions, sRGB
PNGs, PLY headers, and the depth arguments of super_resolve / all_in_focus."""

from __future__ import annotations

import dataclasses
import json
import struct
import zlib
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import tifffile

import lfcam
from lfcam.io import (
    encode_u8,
    encode_u16,
    read_tiff_description,
    srgb_decode,
    srgb_encode,
    write_image,
)
from lfcam.outputs import NovelViewOptions, output_frame, reference_box, write_capture
from lfcam.pipeline import process_capture
from lfcam.processing.depth import depth_from_parallax
from lfcam.products.geometry import parse_pose
from lfcam.products.mesh import mesh_from_depth
from lfcam.products.render import render_mesh
from lfcam.products.superres import resolve_parallax


# ------------------------------------------------------------------ file encodings
def test_tiff_description_round_trips_and_is_deflated(tmp_path) -> None:
    img = np.linspace(0, 1, 64 * 48, dtype=np.float32).reshape(48, 64)
    img[3, 4] = np.nan
    meta = {"quantity": "depth", "unit": "m", "frame": {"offset_xy": [7, 9]}, "n": 1.5}
    write_image(tmp_path / "d.tiff", img, description=meta)
    assert read_tiff_description(tmp_path / "d.tiff") == meta
    back = tifffile.imread(tmp_path / "d.tiff")
    np.testing.assert_array_equal(back, img)  # NaN in the same place, bit for bit
    with tifffile.TiffFile(tmp_path / "d.tiff") as tif:
        assert tif.pages.first.compression == tifffile.COMPRESSION.ADOBE_DEFLATE
    # No description: an empty dict, not an error.
    write_image(tmp_path / "plain.tiff", img)
    assert read_tiff_description(tmp_path / "plain.tiff") == {}
    with pytest.raises(lfcam.InputError, match="TIFF"):
        write_image(tmp_path / "p.png", encode_u8(img), description=meta)


def test_srgb_curve_known_values_and_inverse() -> None:
    # IEC 61966-2-1: the linear segment ends at 0.0031308 -> 0.04045; 0.5 -> 0.7354.
    enc = srgb_encode(np.array([0.0, 0.0031308, 0.18, 0.5, 1.0]))
    np.testing.assert_allclose(enc, [0.0, 0.04045, 0.461356, 0.735357, 1.0], atol=1e-6)
    assert encode_u8(np.array([0.5]))[0] == 188  # round(0.735357 * 255)
    x = np.linspace(0, 1, 10001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)


def test_png_says_srgb_and_decodes_to_the_linear_values(tmp_path) -> None:
    lin = np.linspace(0, 1, 3 * 256, dtype=np.float32).reshape(16, 16, 3)
    write_image(tmp_path / "x.png", encode_u16(lin), srgb=True)
    data = (tmp_path / "x.png").read_bytes()
    # sRGB (perceptual intent) and gAMA 1/2.2 right after IHDR, before the pixel data.
    crc = struct.pack(">I", zlib.crc32(b"sRGB\x00"))
    assert data[33:46] == struct.pack(">I", 1) + b"sRGB\x00" + crc
    i = data.index(b"gAMA")
    assert struct.unpack(">I", data[i + 4 : i + 8])[0] == 45455
    assert i < data.index(b"IDAT")
    back = cv2.imread(str(tmp_path / "x.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    # 16-bit sRGB: decoding error below half a code times the curve's steepest slope.
    np.testing.assert_allclose(srgb_decode(back), lin, atol=2.5 / 65535)
    # Without srgb: no chunk.
    write_image(tmp_path / "y.png", encode_u16(lin))
    assert b"sRGB" not in (tmp_path / "y.png").read_bytes()


# ------------------------------------------------------------------ output frames
def test_reference_box_is_the_mask_bounding_box() -> None:
    masks = np.zeros((2, 10, 12), bool)
    masks[1, 3:7, 2:9] = True
    masks[1, 5, 10] = True  # one stray pixel widens the box
    cal = SimpleNamespace(masks=masks, reference=1, rect_shape=(10, 12))
    assert reference_box(cal) == (2, 3, 9, 4)
    fr = output_frame(cal)
    assert fr["offset_xy"] == [2, 3]
    assert fr["shape"] == [4, 9]
    assert output_frame(cal, "full")["offset_xy"] == [0, 0]
    assert output_frame(cal, "full")["shape"] == [10, 12]
    with pytest.raises(lfcam.InputError, match=r"^frame:"):
        output_frame(cal, "box")


@pytest.fixture(scope="module")
def planes(reference_camera):
    cam = reference_camera
    res = process_capture(cam.sim.captures["planes"], cam.cal)
    # A known super-resolved image and refocus: the crop must cut the same window.
    H, W = cam.cal.rect_shape
    rng = np.random.default_rng(0)
    sr = rng.random((2 * H, 2 * W, 3), dtype=np.float32)
    refocused = {1.5: rng.random((H, W, 3), dtype=np.float32)}
    return dataclasses.replace(res, superres=sr, refocused=refocused)


def test_capture_outputs_crop_exactly_and_describe_themselves(
    reference_camera, planes, tmp_path
) -> None:
    cal = reference_camera.cal
    extra = {"calibration_sha256": "ab" * 32}
    valid = write_capture(tmp_path / "valid", planes, cal, extra=extra)
    full = write_capture(tmp_path / "full", planes, cal, extra=extra, frame="full")
    info = json.loads((valid / "result.json").read_text())
    x0, y0 = info["frame"]["offset_xy"]
    h, w = info["frame"]["shape"]
    assert (x0, y0, w, h) == reference_box(cal)
    # The simulated camera's rectified frame is much larger than the reference's data.
    assert h * w < 0.5 * cal.rect_shape[0] * cal.rect_shape[1]
    z_full = tifffile.imread(full / "depth.tiff")
    z_valid = tifffile.imread(valid / "depth.tiff")
    assert z_full.shape == tuple(cal.rect_shape)
    # Output pixel (x, y) is rectified pixel (x + x0, y + y0), exactly.
    np.testing.assert_array_equal(z_valid, z_full[y0 : y0 + h, x0 : x0 + w])
    np.testing.assert_array_equal(z_full, planes.depth.depth)
    # Nothing known is cut away.
    assert np.isfinite(z_valid).sum() == np.isfinite(z_full).sum() > 0
    np.testing.assert_array_equal(
        tifffile.imread(valid / "confidence.tiff"),
        planes.depth.confidence[y0 : y0 + h, x0 : x0 + w],
    )
    sr = tifffile.imread(valid / "superres.tiff")
    np.testing.assert_array_equal(sr, planes.superres[2 * y0 : 2 * (y0 + h), 2 * x0 : 2 * (x0 + w)])
    rf = tifffile.imread(valid / "refocus_1.5m.tiff")
    np.testing.assert_array_equal(rf, planes.refocused[1.5][y0 : y0 + h, x0 : x0 + w])
    # Each TIFF says what it holds, in which frame, from which calibration.
    meta = read_tiff_description(valid / "depth.tiff")
    assert meta["unit"] == "m"
    assert meta["quantity"].startswith("depth")
    assert meta["frame"]["offset_xy"] == [x0, y0]
    assert meta["calibration_sha256"] == "ab" * 32
    assert read_tiff_description(full / "depth.tiff")["frame"]["offset_xy"] == [0, 0]
    assert read_tiff_description(valid / "superres.tiff")["frame"]["scale"] == 2
    # The previews are sRGB and say so.
    for name in ("depth.png", "superres.png", "refocus_1.5m.png"):
        assert b"sRGB" in (valid / name).read_bytes()[:64], name
    # points.ply: units and frame in its header; the same points in both frames.
    head = (valid / "points.ply").read_bytes().split(b"end_header")[0].decode()
    assert "comment units X, Y m; Z m" in head
    assert "comment frame front lens: X right, Y down, Z forward" in head
    assert (valid / "points.ply").read_bytes() == (full / "points.ply").read_bytes()


def test_novel_views_crop_exactly(reference_camera, planes, tmp_path) -> None:
    """Novel views follow the output frame: pixel (x, y) is (x + x0, y + y0) of the
    --frame full render, the mesh does not change."""
    cal = reference_camera.cal
    novel = NovelViewOptions(mesh=True, pose=parse_pose("0.002,0,0,0,1,0"), orbit=2)
    valid = write_capture(tmp_path / "valid", planes, cal, novel=novel)
    full = write_capture(tmp_path / "full", planes, cal, novel=novel, frame="full")
    x0, y0, w, h = reference_box(cal)
    info = json.loads((valid / "result.json").read_text())["novel_views"]
    assert info["frame"] == {"name": "valid", "offset_xy": [x0, y0], "shape": [h, w]}
    z_full = tifffile.imread(full / "novel_view_depth.tiff")
    z_valid = tifffile.imread(valid / "novel_view_depth.tiff")
    # --frame full is the render itself, in the rectified frame's size.
    mesh = mesh_from_depth(planes.depth.depth, cal, planes.views[cal.reference])
    np.testing.assert_array_equal(z_full, render_mesh(mesh, cal, novel.pose).depth)
    assert z_valid.shape == (h, w)
    np.testing.assert_array_equal(z_valid, z_full[y0 : y0 + h, x0 : x0 + w])
    assert np.isfinite(z_valid).mean() == pytest.approx(info["novel_view_coverage"])
    assert np.isfinite(z_valid).sum() > 0.5 * h * w  # the planes fill the view
    meta = read_tiff_description(valid / "novel_view_depth.tiff")
    assert meta["frame"]["offset_xy"] == [x0, y0]
    assert meta["unit"] == "m"
    names = ["novel_view.png", *(f"orbit/frame_{k:03d}.png" for k in range(2))]
    for name in names:
        img_full = cv2.imread(str(full / name))
        img_valid = cv2.imread(str(valid / name))
        assert img_full.shape[:2] == tuple(cal.rect_shape), name
        np.testing.assert_array_equal(img_valid, img_full[y0 : y0 + h, x0 : x0 + w], err_msg=name)
    # The video holds the same frames, padded to even sizes (MPEG-4).
    video = cv2.VideoCapture(str(valid / "orbit.mp4"))
    assert video.get(cv2.CAP_PROP_FRAME_COUNT) == 2
    assert video.get(cv2.CAP_PROP_FRAME_WIDTH) == w + w % 2
    assert video.get(cv2.CAP_PROP_FRAME_HEIGHT) == h + h % 2
    video.release()
    assert (valid / "mesh.ply").read_bytes() == (full / "mesh.ply").read_bytes()
    # From the reference pose, everything drawn lies in the box: nothing is cut away.
    ref = render_mesh(mesh, cal, np.eye(4)).depth
    assert np.isfinite(ref[y0 : y0 + h, x0 : x0 + w]).sum() == np.isfinite(ref).sum() > 0


# ------------------------------------------------------------------ depth arguments
def test_super_resolve_refuses_a_positional_array(reference_camera) -> None:
    cal = reference_camera.cal
    raw = np.zeros((*cal.raw_shape, 3), np.uint8)
    z = np.full(tuple(cal.rect_shape), 1.2, np.float32)
    with pytest.raises(lfcam.InputError, match=r"^depth: expected a DepthResult.*depth_m="):
        lfcam.super_resolve(raw, cal, z)
    with pytest.raises(lfcam.InputError, match=r"^depth: expected a DepthResult"):
        lfcam.all_in_focus(raw, cal, z)
    with pytest.raises(lfcam.InputError, match=r"^depth: give exactly one"):
        lfcam.super_resolve(raw, cal, parallax=z, depth_m=z)
    with pytest.raises(lfcam.InputError, match=r"^depth: give exactly one"):
        lfcam.all_in_focus(raw, cal)


def test_depth_in_metres_is_converted_to_parallax(reference_camera, planes) -> None:
    cal = reference_camera.cal
    s = planes.depth.parallax
    z = depth_from_parallax(s, cal.z_b, cal.z_c)
    back = resolve_parallax(cal, depth_m=z)
    ok = np.isfinite(s)
    np.testing.assert_array_equal(np.isfinite(back), ok)
    np.testing.assert_allclose(back[ok], s[ok], atol=2e-5)
    np.testing.assert_array_equal(resolve_parallax(cal, planes.depth), s)
    np.testing.assert_array_equal(resolve_parallax(cal, parallax=s), s)
    # Z_b is parallax 0; at or before Z_c there is none.
    flat = resolve_parallax(cal, depth_m=np.full(tuple(cal.rect_shape), cal.z_b))
    np.testing.assert_allclose(flat, 0, atol=1e-6)
    assert np.isnan(resolve_parallax(cal, depth_m=np.full(tuple(cal.rect_shape), cal.z_c))).all()
