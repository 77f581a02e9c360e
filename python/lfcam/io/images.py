"""Image files: reading and writing images and raw captures.

Images are numpy arrays in (row, col, channel) order with RGB channel order
(OpenCV's BGR is converted at this boundary). PNG and TIFF keep 8 and 16 bits;
float32 goes to TIFF.
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .._validate import check_path
from ..errors import InputError
from .atomic import atomic_output
from .files import (
    MAX_IMAGE_FILE_BYTES,
    MAX_IMAGE_PIXELS,
    MAX_IMAGE_SIDE,
    check_image_size,
    read_file_bytes,
)
from .raw import RAW_EXTENSIONS, is_camera_raw, read_camera_raw

__all__ = [
    "BAYER_PATTERNS",
    "IMAGE_EXTENSIONS",
    "MAX_IMAGE_FILE_BYTES",
    "MAX_IMAGE_PIXELS",
    "MAX_IMAGE_SIDE",
    "WRITABLE_EXTENSIONS",
    "demosaic",
    "is_image_file",
    "read_image",
    "read_raw",
    "read_tiff_description",
    "to_float",
    "write_image",
    "write_image_atomic",
]

#: Bayer mosaics, named by the colours of the top-left 2 x 2 block, row by row.
BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
# OpenCV names a Bayer code by the 2x2 block starting at row 1, column 1.
_CV_BAYER = {"RGGB": "BG", "BGGR": "RG", "GRBG": "GB", "GBRG": "GR"}

#: File extensions (lower case) lfcam reads as images: every folder scan uses this list.
#: Camera raw files (:data:`lfcam.io.raw.RAW_EXTENSIONS`) need the extra ``lfcam[raw]``.
IMAGE_EXTENSIONS = (".png", ".tif", ".tiff", ".jpg", ".jpeg", *RAW_EXTENSIONS)
#: File extensions lfcam writes images to.
WRITABLE_EXTENSIONS = (".png", ".tif", ".tiff")

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> channels (0 grey, 2 RGB, 3 palette, 4 grey + alpha, 6 RGBA).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
# JPEG start-of-frame markers: SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _png_header(data: bytes, where: str) -> tuple[int, int, int]:
    """(width, height, channels) from a PNG's IHDR chunk."""
    if len(data) < 33 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise InputError(f"{where}: not a readable PNG (no PNG header)")
    width, height = struct.unpack(">II", data[16:24])
    channels = _PNG_CHANNELS.get(data[25])
    if channels is None or data[24] not in (1, 2, 4, 8, 16):
        raise InputError(
            f"{where}: not a readable PNG (bad IHDR: bit depth {data[24]}, colour type {data[25]})"
        )
    return width, height, channels


def _jpeg_header(data: bytes, where: str) -> tuple[int, int, int]:
    """(width, height, channels) from a JPEG's start-of-frame segment."""
    if data[:2] != b"\xff\xd8":
        raise InputError(f"{where}: not a readable JPEG (no JPEG header)")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            break
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if length < 2:
            break
        if marker in _JPEG_SOF:
            if i + 10 > len(data):
                break
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return width, height, data[i + 9]
        if marker == 0xDA:  # start of scan before any frame header
            break
        i += 2 + length
    raise InputError(f"{where}: not a readable JPEG (no frame header)")


def _decode_tiff(data: bytes, where: str) -> np.ndarray:
    import tifffile

    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            # The first page only: building tifffile's series walks every page (a crafted
            # file with endless page links takes minutes).
            series = tif.pages.first
            if series is None or not series.shape:
                raise InputError(f"{where}: not a readable TIFF (no image in it)")
            shape = tuple(int(s) for s in series.shape)
            if len(shape) == 2:
                shape = (*shape, 1)
            if len(shape) != 3 or shape[2] > 4:
                raise InputError(
                    f"{where}: expected a grey or RGB image, the TIFF holds shape {series.shape}"
                )
            if series.dtype not in (np.uint8, np.uint16, np.float32):
                raise InputError(
                    f"{where}: unsupported pixel type {series.dtype} (use 8/16-bit or float32)"
                )
            check_image_size(shape[1], shape[0], shape[2], where)
            img = series.asarray()
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{where}: not enough memory to decode this TIFF") from None
    except Exception as exc:  # tifffile and its codecs raise many types on bad data
        raise InputError(f"{where}: not a readable TIFF ({type(exc).__name__}: {exc})") from None
    return np.asarray(img)


def _decode_cv2(data: bytes, ext: str, where: str) -> np.ndarray:
    kind = "PNG" if ext == ".png" else "JPEG"
    width, height, channels = (_png_header if ext == ".png" else _jpeg_header)(data, where)
    check_image_size(width, height, channels, where)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise InputError(f"{where}: not a readable {kind} ({str(exc).strip()})") from None
    if img is None:
        raise InputError(f"{where}: not a readable {kind} (corrupt or truncated?)")
    if img.shape[:2] != (height, width):
        raise InputError(
            f"{where}: decoded {img.shape[1]} x {img.shape[0]} px, but the header says "
            f"{width} x {height}"
        )
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return img


def is_image_file(path: Path) -> bool:
    """Whether ``path`` is a visible file with an image extension (folder scans)."""
    return (
        path.is_file()
        and not path.name.startswith(".")
        and (path.suffix.lower() in IMAGE_EXTENSIONS)
    )


def read_image(path: str | os.PathLike[str], *, data: bytes | None = None) -> np.ndarray:
    """Read a PNG, TIFF, JPEG or camera raw image without changing its bit depth.

    Parameters
    ----------
    path : path-like
        The image file.
    data : bytes, optional
        Its bytes, already read (:func:`lfcam.io.files.read_file_bytes`): decoded
        instead of reading ``path`` again, which then only names the file and its type.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` for grey or Bayer, ``(H, W, 3)`` RGB otherwise (an alpha
        channel is dropped); uint8, uint16 or float32 as stored. A camera raw file
        comes back demosaiced, linear uint16 RGB (:func:`lfcam.io.raw.read_camera_raw`).

    Raises
    ------
    lfcam.InputError
        If the file is missing, has an unsupported extension, declares a size beyond
        :data:`MAX_IMAGE_SIDE` / :data:`MAX_IMAGE_PIXELS`, or cannot be decoded.

    Notes
    -----
    The file is read by Python and decoded from memory (``cv2.imdecode``, tifffile),
    never opened by a decoder by name, and the size its header declares is checked
    before decoding: no file name or content can crash the process (docs/design.md,
    "Processing pipeline").
    """
    check_path(path, "path")
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in IMAGE_EXTENSIONS:
        raise InputError(
            f"{p}: unsupported image type {p.suffix!r} (use PNG, TIFF, JPEG or camera raw)"
        )
    if is_camera_raw(p):
        img = read_camera_raw(p, data=data)[0]
    else:
        if data is None:
            data = read_file_bytes(p, MAX_IMAGE_FILE_BYTES)
        if ext in (".tif", ".tiff"):
            img = _decode_tiff(data, str(p))
            if img.ndim == 3 and img.shape[2] == 1:
                img = img[..., 0]
        else:
            img = _decode_cv2(data, ext, str(p))
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise InputError(f"{p}: expected a grey or RGB image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        raise InputError(f"{p}: unsupported pixel type {img.dtype} (use 8/16-bit or float32)")
    return np.ascontiguousarray(img)


def write_image(
    path: str | os.PathLike[str],
    img: np.ndarray,
    *,
    compression: int = 3,
    srgb: bool = False,
    description: Mapping[str, Any] | None = None,
) -> None:
    """Write ``img`` (grey or RGB; uint8/uint16 to PNG or TIFF, float32 to TIFF).

    Parameters
    ----------
    path : path-like
        ``.png``, ``.tif`` or ``.tiff``.
    img : (H, W) or (H, W, 3) array
        The pixels, RGB order.
    compression : int
        Deflate level, 0 (none) to 9: PNG, and TIFF (zlib compression).
    srgb : bool
        PNG only: the values are sRGB-encoded (:func:`lfcam.io.encode_u8`); the file
        says so with an ``sRGB`` chunk (perceptual intent) and the matching ``gAMA``
        (1/2.2) for readers that only know gamma.
    description : mapping, optional
        TIFF only: stored as JSON in the ImageDescription tag (what the values are:
        quantity, unit, frame); read it back with :func:`read_tiff_description`.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in WRITABLE_EXTENSIONS:
        raise InputError(f"{p}: unsupported output type {p.suffix!r} (use .png, .tif or .tiff)")
    img = np.asarray(img)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)) or img.size == 0:
        raise InputError(f"{p}: cannot write an image of shape {img.shape}")
    if ext == ".png":
        if img.dtype not in (np.uint8, np.uint16):
            raise InputError(f"{p}: PNG holds 8 or 16-bit integers, not {img.dtype}")
        if description is not None:
            raise InputError(f"{p}: a description is written to TIFFs only")
        arr = img if img.ndim == 2 else img[..., ::-1]
        ok, buf = cv2.imencode(
            ".png", np.ascontiguousarray(arr), [cv2.IMWRITE_PNG_COMPRESSION, compression]
        )
        if not ok:
            raise OSError(f"{p}: could not encode PNG")
        data = buf.tobytes()
        if srgb:
            data = _png_with_srgb(data)
        p.write_bytes(data)
    else:
        import tifffile

        if srgb:
            raise InputError(f"{p}: TIFFs hold linear values; srgb is for PNG previews")
        text = None if description is None else json.dumps(dict(description), allow_nan=False)
        tifffile.imwrite(
            p,
            img,
            photometric="rgb" if img.ndim == 3 and img.shape[2] == 3 else "minisblack",
            compression="zlib" if compression > 0 else None,
            compressionargs={"level": compression} if compression > 0 else None,
            description=text,
            metadata=None,
        )


def read_tiff_description(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The JSON description :func:`write_image` stored in a TIFF (empty if none).

    Examples
    --------
    >>> import numpy as np, tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "z.tiff"
    >>> write_image(p, np.ones((2, 3), np.float32), description={"quantity": "depth"})
    >>> read_tiff_description(p)
    {'quantity': 'depth'}
    """
    import tifffile

    p = Path(path)
    try:
        with tifffile.TiffFile(p) as tif:
            text = tif.pages.first.description
    except Exception as exc:
        raise InputError(f"{p}: not a readable TIFF ({exc})") from None
    if not text:
        return {}
    try:
        value = json.loads(text)
    except ValueError:
        return {}
    return value if isinstance(value, dict) else {}


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def _png_with_srgb(data: bytes) -> bytes:
    """A PNG with ``sRGB`` (rendering intent 0, perceptual) and ``gAMA`` (45455, the
    PNG specification's value to accompany sRGB) chunks after IHDR."""
    # Signature (8 bytes), then IHDR: length (4), type (4), 13 bytes of data, CRC (4).
    end = 8 + 4 + 4 + 13 + 4
    if data[12:16] != b"IHDR":
        raise OSError("PNG encoder wrote no IHDR first")
    extra = _png_chunk(b"sRGB", b"\x00") + _png_chunk(b"gAMA", struct.pack(">I", 45455))
    return data[:end] + extra + data[end:]


def write_image_atomic(path: str | os.PathLike[str], img: np.ndarray, **kw: Any) -> None:
    """:func:`write_image` to a temporary name beside ``path``, then rename
    (:func:`lfcam.io.atomic.atomic_output`)."""
    p = Path(path)
    if p.suffix.lower() not in WRITABLE_EXTENSIONS:
        raise InputError(f"{p}: unsupported output type {p.suffix!r} (use .png, .tif or .tiff)")
    with atomic_output(p) as tmp:
        write_image(tmp, img, **kw)


def demosaic(raw: np.ndarray, pattern: str, *, name: str = "raw") -> np.ndarray:
    """Demosaic a Bayer frame (OpenCV, bilinear) -> ``(H, W, 3)`` RGB, same dtype.

    ``pattern`` names the colours of the top-left 2x2 block, row by row
    (``RGGB``: red at (0, 0)).
    """
    if pattern not in _CV_BAYER:
        raise InputError(f"bayer: expected one of {', '.join(BAYER_PATTERNS)}, got {pattern!r}")
    if raw.ndim != 2:
        raise InputError(f"{name}: a Bayer frame has one channel, got shape {raw.shape}")
    if raw.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{name}: a Bayer frame is 8 or 16-bit, not {raw.dtype}")
    code = getattr(cv2, f"COLOR_Bayer{_CV_BAYER[pattern]}2RGB")
    return cv2.cvtColor(np.ascontiguousarray(raw), code)


def read_raw(
    path: str | os.PathLike[str], bayer: str | None = None, *, data: bytes | None = None
) -> np.ndarray:
    """Read a raw capture: grey, RGB, or a Bayer mosaic demosaiced to RGB.

    Parameters
    ----------
    path : path-like
        PNG, TIFF (8/16-bit or float32), JPEG, or a camera raw file (DNG, CR2, NEF,
        ARW, ...; needs ``pip install "lfcam[raw]"``).
    bayer : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}, optional
        The sensor's mosaic, for single-channel Bayer frames. A camera raw file is
        then read as its mosaic (which must be ``bayer``) and demosaiced here like any
        Bayer frame; without ``bayer`` LibRaw demosaics it.
    data : bytes, optional
        The file's bytes, already read (as :func:`read_image`).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` or ``(H, W, 3)``, the file's dtype (uint8, uint16 or float32).

    Examples
    --------
    >>> raw = lfcam.read_raw("capture.png")                 # doctest: +SKIP
    >>> raw = lfcam.read_raw("capture.tiff", bayer="RGGB")  # doctest: +SKIP
    >>> raw = lfcam.read_raw("capture.dng")                 # doctest: +SKIP
    """
    if bayer is not None and is_camera_raw(path) and (data is not None or Path(path).is_file()):
        mosaic, cfa = read_camera_raw(path, mosaic=True, data=data)
        if cfa != bayer:
            raise InputError(
                f"{path}: the file's colour filter mosaic is {cfa}, but the calibration"
                f" says --bayer {bayer}"
            )
        return demosaic(mosaic, bayer, name=str(path))
    img = read_image(path, data=data)
    if bayer is not None:
        if img.ndim != 2:
            raise InputError(f"{path}: --bayer {bayer} given, but the image has 3 channels")
        img = demosaic(img, bayer, name=str(path))
    return img


def to_float(raw: np.ndarray) -> np.ndarray:
    """Raw values -> float32 in [0, 1] (uint8 / 255, uint16 / 65535, float32 as is)."""
    if raw.dtype == np.uint8:
        return raw.astype(np.float32) * np.float32(1 / 255)
    if raw.dtype == np.uint16:
        return raw.astype(np.float32) * np.float32(1 / 65535)
    return raw.astype(np.float32, copy=False)
