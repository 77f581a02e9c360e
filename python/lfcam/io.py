"""Image files: the one module that reads and writes them.

Images are numpy arrays in (row, col, channel) order with RGB channel order
(OpenCV's BGR is converted at this boundary). PNG and TIFF keep 8 and 16 bits;
float32 goes to TIFF.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError

__all__ = [
    "BAYER_PATTERNS",
    "demosaic",
    "read_flo",
    "read_image",
    "read_pfm",
    "read_raw",
    "to_float",
    "write_image",
    "write_image_atomic",
    "write_pfm",
]

BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
# OpenCV names a Bayer code by the 2x2 block starting at row 1, column 1.
_CV_BAYER = {"RGGB": "BG", "BGGR": "RG", "GRBG": "GB", "GBRG": "GR"}

_WRITABLE = {".png", ".tif", ".tiff"}
_READABLE = {".png", ".tif", ".tiff", ".jpg", ".jpeg"}


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a PNG, TIFF or JPEG image without changing its bit depth.

    Parameters
    ----------
    path : path-like
        The image file.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` for grey or Bayer, ``(H, W, 3)`` RGB otherwise (an alpha
        channel is dropped); uint8, uint16 or float32 as stored.

    Raises
    ------
    lfcam.InputError
        If the file is missing, has an unsupported extension or cannot be decoded.
    """
    p = Path(path)
    if p.suffix.lower() not in _READABLE:
        raise InputError(f"{p}: unsupported image type {p.suffix!r} (use PNG, TIFF or JPEG)")
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    if p.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            img = tifffile.imread(p)
        except Exception as exc:
            raise InputError(f"{p}: not a readable TIFF ({exc})") from None
    else:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"{p}: not a readable image (corrupt or truncated?)")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise InputError(f"{p}: expected a grey or RGB image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        raise InputError(f"{p}: unsupported pixel type {img.dtype} (use 8/16-bit or float32)")
    return np.ascontiguousarray(img)


def write_image(path: str | os.PathLike[str], img: np.ndarray, *, compression: int = 3) -> None:
    """Write ``img`` (grey or RGB; uint8/uint16 to PNG or TIFF, float32 to TIFF)."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in _WRITABLE:
        raise InputError(f"{p}: unsupported output type {p.suffix!r} (use .png, .tif or .tiff)")
    img = np.asarray(img)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
        raise InputError(f"{p}: cannot write an image of shape {img.shape}")
    if ext == ".png":
        if img.dtype not in (np.uint8, np.uint16):
            raise InputError(f"{p}: PNG holds 8 or 16-bit integers, not {img.dtype}")
        arr = img if img.ndim == 2 else img[..., ::-1]
        ok = cv2.imwrite(
            str(p), np.ascontiguousarray(arr), [cv2.IMWRITE_PNG_COMPRESSION, compression]
        )
        if not ok:
            raise OSError(f"{p}: could not write PNG")
    else:
        import tifffile

        tifffile.imwrite(
            p, img, photometric="rgb" if img.ndim == 3 and img.shape[2] == 3 else "minisblack"
        )


def _file_mode() -> int:
    """Permissions a new file gets under the current umask (mkstemp makes 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``.

    On any error the temporary file is removed and ``path`` is left untouched,
    so a failed write never leaves a half-written file behind.
    """
    p = Path(path)
    if not p.parent.is_dir():
        raise InputError(f"{p}: folder {p.parent} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}.", suffix=p.suffix, dir=p.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, _file_mode())
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_image_atomic(path: str | os.PathLike[str], img: np.ndarray, **kw: int) -> None:
    """:func:`write_image` to a temporary name beside ``path``, then rename."""
    p = Path(path)
    if p.suffix.lower() not in _WRITABLE:
        raise InputError(f"{p}: unsupported output type {p.suffix!r} (use .png, .tif or .tiff)")
    with atomic_output(p) as tmp:
        write_image(tmp, img, **kw)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write a text file atomically (see :func:`atomic_output`)."""
    with atomic_output(path) as tmp:
        tmp.write_text(text)


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


def read_raw(path: str | os.PathLike[str], bayer: str | None = None) -> np.ndarray:
    """Read a raw capture: grey, RGB, or a Bayer mosaic demosaiced to RGB.

    Parameters
    ----------
    path : path-like
        PNG, TIFF (8/16-bit or float32) or JPEG.
    bayer : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}, optional
        The sensor's mosaic, for single-channel Bayer frames.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` or ``(H, W, 3)``, the file's dtype (uint8, uint16 or float32).

    Examples
    --------
    >>> raw = lfcam.read_raw("capture.png")                 # doctest: +SKIP
    >>> raw = lfcam.read_raw("capture.tiff", bayer="RGGB")  # doctest: +SKIP
    """
    img = read_image(path)
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


# PFM (portable float map): a text header "PF" (RGB) or "Pf" (grey), "W H", and a
# scale whose sign gives the byte order (negative: little-endian), then W*H*C float32
# samples, rows stored bottom to top. The HCI 4D light-field benchmark's format.
_PFM_HEADER = re.compile(rb"\A(P[Ff])\s+(\d+)\s+(\d+)\s+(\S+)\s")


def read_pfm(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a PFM (portable float map) file, top row first.

    Parameters
    ----------
    path : path-like
        The ``.pfm`` file: ``Pf`` (one channel) or ``PF`` (RGB), either byte order.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` or ``(H, W, 3)`` float32 (native byte order, C-contiguous). PFM
        stores rows bottom to top; they are flipped here, so row 0 is the top of the
        image. Samples are multiplied by the magnitude of the header's scale when it
        is not 1 (HCI files use -1: little-endian, unscaled).

    Raises
    ------
    lfcam.InputError
        If the file is missing, its header is malformed, or its data are truncated
        or too long for the size the header gives.

    Examples
    --------
    >>> gt = lfcam.read_pfm("hci4d_antinous/gt_disp_lowres.pfm")  # doctest: +SKIP
    >>> gt.shape, gt.dtype                                         # doctest: +SKIP
    ((512, 512), dtype('float32'))
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    data = p.read_bytes()
    m = _PFM_HEADER.match(data[:256])
    if m is None:
        head = data[:24].split(b"\n")[0][:16]
        raise InputError(
            f"{p}: not a PFM file (expected a header 'PF' or 'Pf', width height, scale;"
            f" the file starts with {head!r})"
        )
    magic, w, h = m.group(1), int(m.group(2)), int(m.group(3))
    try:
        scale = float(m.group(4))
    except ValueError:
        scale = math.nan
    if not math.isfinite(scale) or scale == 0:
        raise InputError(
            f"{p}: PFM scale must be a non-zero number (its sign gives the byte order),"
            f" got {m.group(4).decode('latin-1')!r}"
        )
    if w == 0 or h == 0:
        raise InputError(f"{p}: PFM header gives an empty image ({w} x {h})")
    channels = 3 if magic == b"PF" else 1
    expected = w * h * channels * 4
    body = memoryview(data)[m.end() :]
    if len(body) != expected:
        what = "truncated" if len(body) < expected else "longer than its header says"
        raise InputError(
            f"{p}: PFM data {what}: {w} x {h} x {channels} float32 need {expected} bytes,"
            f" found {len(body)}"
        )
    arr = np.frombuffer(body, dtype="<f4" if scale < 0 else ">f4")
    shape = (h, w) if channels == 1 else (h, w, 3)
    out = np.flipud(arr.reshape(shape)).astype(np.float32)  # native order, a copy
    if abs(scale) != 1.0:
        out *= np.float32(abs(scale))
    return np.ascontiguousarray(out)


def read_flo(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a Middlebury ``.flo`` optical-flow file.

    Parameters
    ----------
    path : path-like
        Tag ``202021.25`` (float32), width and height (int32), then ``(u, v)``
        float32 pairs, row-major, top row first, little-endian.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 2)`` float32, ``[..., 0]`` = u (x); NaN where the file marks the
        flow unknown (``|value| > 1e9``).

    Raises
    ------
    lfcam.InputError
        If the file is missing, has the wrong tag, or its size does not match.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    data = p.read_bytes()
    if len(data) < 12 or np.frombuffer(data[:4], "<f4")[0] != 202021.25:
        raise InputError(f"{p}: not a Middlebury .flo file (tag 202021.25 missing)")
    w, h = (int(x) for x in np.frombuffer(data[4:12], "<i4"))
    if w <= 0 or h <= 0 or len(data) != 12 + 8 * w * h:
        raise InputError(f"{p}: .flo size {w} x {h} does not match its {len(data)} bytes")
    flow = np.frombuffer(data[12:], "<f4").reshape(h, w, 2).astype(np.float32)
    return np.where(np.abs(flow).max(-1, keepdims=True) < 1e9, flow, np.nan).astype(np.float32)


def write_pfm(path: str | os.PathLike[str], array: np.ndarray, *, scale: float = -1.0) -> None:
    """Write a PFM file atomically (a temporary file beside ``path``, then a rename).

    Parameters
    ----------
    path : path-like
        The file to write (``.pfm`` by convention; any name is accepted).
    array : (H, W), (H, W, 1) or (H, W, 3) array
        Real numbers, stored as float32 (NaN and infinities are kept). Row 0 is the
        top of the image; PFM's bottom-to-top row order is applied here.
    scale : float, optional
        The header's scale: its sign picks the byte order (negative, the default:
        little-endian; positive: big-endian). A magnitude other than 1 divides the
        stored samples so that :func:`read_pfm` gives ``array`` back.

    Raises
    ------
    lfcam.InputError
        If ``array`` is not an image of real numbers, ``scale`` is zero or not
        finite, or the folder of ``path`` does not exist.

    Examples
    --------
    >>> lfcam.write_pfm("disparity.pfm", disparity)  # doctest: +SKIP
    """
    p = Path(path)
    arr = np.asarray(array)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3) or arr.size == 0:
        raise InputError(
            f"array: PFM holds a non-empty (H, W) or (H, W, 3) image, got shape {arr.shape}"
        )
    if arr.dtype.kind not in "fiu":
        raise InputError(f"array: PFM holds real numbers, not {arr.dtype}")
    scale = float(scale)
    if not math.isfinite(scale) or scale == 0:
        raise InputError(f"scale: must be a finite non-zero number, got {scale!r}")
    data = arr.astype(np.float32)
    if abs(scale) != 1.0:
        data = data / np.float32(abs(scale))
    h, w = arr.shape[:2]
    header = f"{'PF' if arr.ndim == 3 else 'Pf'}\n{w} {h}\n{scale:g}\n".encode("ascii")
    body = np.ascontiguousarray(np.flipud(data), dtype="<f4" if scale < 0 else ">f4")
    with atomic_output(p) as tmp:
        tmp.write_bytes(header + body.tobytes())
