"""Image files: reading and writing images and raw captures.

Images are numpy arrays in (row, col, channel) order with RGB channel order
(OpenCV's BGR is converted at this boundary). PNG and TIFF keep 8 and 16 bits;
float32 goes to TIFF.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from .raw import RAW_EXTENSIONS, is_camera_raw, read_camera_raw

__all__ = [
    "BAYER_PATTERNS",
    "IMAGE_EXTENSIONS",
    "WRITABLE_EXTENSIONS",
    "demosaic",
    "is_image_file",
    "read_image",
    "read_raw",
    "to_float",
    "write_image",
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


def is_image_file(path: Path) -> bool:
    """Whether ``path`` is a visible file with an image extension (folder scans)."""
    return (
        path.is_file()
        and not path.name.startswith(".")
        and (path.suffix.lower() in IMAGE_EXTENSIONS)
    )


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a PNG, TIFF, JPEG or camera raw image without changing its bit depth.

    Parameters
    ----------
    path : path-like
        The image file.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` for grey or Bayer, ``(H, W, 3)`` RGB otherwise (an alpha
        channel is dropped); uint8, uint16 or float32 as stored. A camera raw file
        comes back demosaiced, linear uint16 RGB (:func:`lfcam.io.raw.read_camera_raw`).

    Raises
    ------
    lfcam.InputError
        If the file is missing, has an unsupported extension or cannot be decoded.
    """
    p = Path(path)
    if p.suffix.lower() not in IMAGE_EXTENSIONS:
        raise InputError(
            f"{p}: unsupported image type {p.suffix!r} (use PNG, TIFF, JPEG or camera raw)"
        )
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    if is_camera_raw(p):
        img = read_camera_raw(p)[0]
    elif p.suffix.lower() in (".tif", ".tiff"):
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
    if ext not in WRITABLE_EXTENSIONS:
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
        PNG, TIFF (8/16-bit or float32), JPEG, or a camera raw file (DNG, CR2, NEF,
        ARW, ...; needs ``pip install "lfcam[raw]"``).
    bayer : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}, optional
        The sensor's mosaic, for single-channel Bayer frames. A camera raw file is
        then read as its mosaic (which must be ``bayer``) and demosaiced here like any
        Bayer frame; without ``bayer`` LibRaw demosaics it.

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
    if bayer is not None and is_camera_raw(path) and Path(path).is_file():
        mosaic, cfa = read_camera_raw(path, mosaic=True)
        if cfa != bayer:
            raise InputError(
                f"{path}: the file's colour filter mosaic is {cfa}, but the calibration"
                f" says --bayer {bayer}"
            )
        return demosaic(mosaic, bayer, name=str(path))
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
