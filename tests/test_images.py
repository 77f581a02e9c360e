"""Reading images from untrusted files: round trips, names with any bytes, and headers
or contents that must be refused with an InputError naming the file."""

from __future__ import annotations

import base64
import os
import struct
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

import lfcam
from lfcam.errors import InputError
from lfcam.io import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE, read_image, write_image

RNG = np.random.default_rng(7)
U8_RGB = RNG.integers(0, 256, (13, 17, 3), dtype=np.uint8)
U16_GREY = RNG.integers(0, 65536, (9, 11), dtype=np.uint16)
F32_RGB = RNG.random((5, 6, 3)).astype(np.float32)


@pytest.mark.parametrize(
    ("ext", "img"),
    [
        (".png", U8_RGB),
        (".png", U16_GREY),
        (".tif", U16_GREY),
        (".tiff", U8_RGB),
        (".tif", F32_RGB),
    ],
)
def test_round_trip_exact(tmp_path: Path, ext: str, img: np.ndarray) -> None:
    path = tmp_path / f"a{ext}"
    write_image(path, img)
    back = read_image(path)
    assert back.dtype == img.dtype
    assert back.shape == img.shape
    assert back.tobytes() == img.tobytes()


def test_jpeg_and_rgba_png(tmp_path: Path) -> None:
    # JPEG is lossy: a smooth image comes back within a few levels.
    smooth = np.repeat(
        np.repeat(np.linspace(0, 255, 8, dtype=np.uint8)[None, :, None], 16, 0), 3, 2
    )
    smooth = np.repeat(smooth, 4, 1)
    ok, buf = cv2.imencode(".jpg", smooth[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 98])
    assert ok
    (tmp_path / "a.jpg").write_bytes(buf.tobytes())
    back = read_image(tmp_path / "a.jpg")
    assert back.shape == (16, 32, 3)
    assert np.abs(back.astype(int) - smooth).max() <= 6
    # RGBA PNG: alpha dropped, RGB order kept.
    rgba = np.dstack([U8_RGB, np.full(U8_RGB.shape[:2], 200, np.uint8)])
    ok, buf = cv2.imencode(".png", rgba[..., [2, 1, 0, 3]])
    (tmp_path / "rgba.png").write_bytes(buf.tobytes())
    np.testing.assert_array_equal(read_image(tmp_path / "rgba.png"), U8_RGB)


def test_any_bytes_in_the_name(tmp_path: Path) -> None:
    """A file name that is not valid UTF-8 (0xff) reads and writes; errors name it."""
    for ext in (".png", ".tif"):
        path = tmp_path / os.fsdecode(b"cap\xff\xfe" + ext.encode())
        write_image(path, U8_RGB)
        np.testing.assert_array_equal(lfcam.read_image(path), U8_RGB)
        path.write_bytes(b"\x89PNG junk" if ext == ".png" else b"II*\x00junk")
        with pytest.raises(InputError) as e:
            lfcam.read_raw(path)
        assert str(e.value).startswith(f"{path}: not a readable")


def _png(width: int, height: int, colour: int = 2, depth: int = 8, idat: bytes = b"") -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _jpeg(width: int, height: int) -> bytes:
    _, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    data = bytearray(buf.tobytes())
    at = data.index(b"\xff\xc0")
    data[at + 5 : at + 9] = struct.pack(">HH", height, width)
    return bytes(data)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        (
            "huge.png",
            _png(65535, 65535, idat=zlib.compress(b"\0" * 100)),
            "larger than lfcam reads",
        ),
        ("wide.png", _png(MAX_IMAGE_SIDE + 1, 1), "larger than lfcam reads"),
        ("empty.png", _png(0, 10), "declares an empty 0 x 10 image"),
        ("badtype.png", _png(4, 4, colour=5), "bad IHDR"),
        ("short.png", _png(4, 4)[:20], "no PNG header"),
        ("trunc.png", _png(4, 4, idat=zlib.compress(b"\0" * 5)), "not a readable PNG"),
        ("text.png", b"hello", "no PNG header"),
        ("zero.png", b"", "no PNG header"),
        ("huge.jpg", _jpeg(65500, 65500), "larger than lfcam reads"),
        ("nosof.jpg", b"\xff\xd8\xff\xd9", "no frame header"),
        ("png.jpg", _png(4, 4), "no JPEG header"),
        ("junk.tif", b"II*\x00" + bytes(range(256)) * 4, "not a readable TIFF"),
        ("text.tiff", b"not a tiff", "not a readable TIFF"),
    ],
)
def test_bad_files_name_the_file(tmp_path: Path, name: str, content: bytes, message: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(InputError) as e:
        read_image(path)
    assert str(e.value).startswith(f"{path}: "), str(e.value)
    assert message in str(e.value)


def test_tiff_shapes_and_types_checked_before_decoding(tmp_path: Path) -> None:
    path = tmp_path / "a.tif"
    tifffile.imwrite(
        path, np.zeros((4, 5, 6), np.uint8), photometric="minisblack", planarconfig="contig"
    )
    with pytest.raises(InputError, match=r"expected a grey or RGB image, the TIFF holds shape"):
        read_image(path)
    tifffile.imwrite(path, np.zeros((4, 5), np.float64))
    with pytest.raises(InputError, match="unsupported pixel type float64"):
        read_image(path)
    # A header declaring more pixels than the limit, no data behind it: a 4 x 5 TIFF whose
    # width and length tags are rewritten in place (writing a real one takes half a minute).
    tifffile.imwrite(path, np.zeros((4, 5), np.uint8))
    with tifffile.TiffFile(path) as tif:
        assert tif.byteorder == "<"
        tags = tif.pages.first.tags
        offsets = [tags[name].valueoffset for name in ("ImageWidth", "ImageLength")]
    with open(path, "r+b") as f:
        for offset in offsets:
            f.seek(offset)
            f.write((40_000).to_bytes(4, "little"))
    with tifffile.TiffFile(path) as tif:
        assert tif.pages.first.shape == (40_000, 40_000)
    assert MAX_IMAGE_PIXELS < 40_000 * 40_000
    with pytest.raises(InputError, match="larger than lfcam reads"):
        read_image(path)


def test_missing_folder_and_special_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        read_image(tmp_path / "none.png")
    (tmp_path / "d.png").mkdir()
    with pytest.raises(InputError, match="is a folder"):
        read_image(tmp_path / "d.png")
    os.mkfifo(tmp_path / "fifo.png")
    with pytest.raises(InputError, match="not a regular file"):
        read_image(tmp_path / "fifo.png")
    with pytest.raises(InputError, match=r"unsupported image type .\.bmp."):
        read_image(tmp_path / "a.bmp")


# A 333-byte TIFF (found by fuzz/fuzz_inputs.py) whose page links loop: building tifffile's
# series over every page took minutes; only the first page is read.
_LOOPING_TIFF = base64.b64decode(
    "SUkqAAgAAAAPAAABBAABAAAAAAAAAAEBBAABAAAABhYBBAABAAAABgAAwgAAAAMBAwABAAAAAQAAAAYB"
    "AwABAAAAAgAAAA4BAgABAAAAAAMAAAAWAQQAAQAAAAYAAAAXAQQAAQAAAPwAAAAaAQUAAQAAAOwHAgAA"
    "AAAAAAAAABsBBQABAAAA9AAAABwBAwABAAAAPwEAAAAoAQNQiVBORw0KGgoAAAANSUhEUgDyAAcBBAAB"
    "AAAABgAAABcBBAABAAAA/AAAABoBBQABAAAA7AcCAAAAAAAAAAAAGwEFAAEAAAD0AAAAHAEDAAEAAAAB"
    "AAAbAQUAAQAAAPQAAAAcAQMAAQAAAAEAAAAoAQNQiVBORw0KGgoAAAANSUhEUgDyAAcAAAAGCAAAAAgN"
    "Df8SRF1iYmdnbAAAAAYIAAAACA0N/xJEXWJiZ2dsbHFx"
)


def test_tiff_with_looping_pages_is_refused_quickly(tmp_path) -> None:
    p = tmp_path / "loop.tif"
    p.write_bytes(_LOOPING_TIFF)
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=r"loop\.tif"):
        lfcam.read_image(p)
    assert time.perf_counter() - t0 < 5.0
