"""Camera raw files (DNG, CR2, CR3, NEF, ARW, RAF, ...): reading through rawpy (LibRaw),
capture metadata through exifread, and DNG writing (the simulator's Bayer captures).

Both readers are the optional extra ``lfcam[raw]``. Raw values come back linear: the
black level subtracted, no gamma, no automatic brightness and no camera white balance
(the white captures' gains do the colour), scaled so the sensor's white level is 65535.
"""

from __future__ import annotations

import io
import math
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, LfcamWarning
from .atomic import atomic_output
from .files import MAX_IMAGE_FILE_BYTES, check_image_size, read_file_bytes

__all__ = [
    "RAW_EXTENSIONS",
    "CaptureMetadata",
    "is_camera_raw",
    "read_camera_raw",
    "read_metadata",
    "write_dng",
]

#: Camera raw extensions (lower case) read through rawpy.
RAW_EXTENSIONS = (
    ".dng",
    ".cr2",
    ".cr3",
    ".crw",
    ".nef",
    ".nrw",
    ".arw",
    ".srf",
    ".sr2",
    ".raf",
    ".orf",
    ".rw2",
    ".pef",
    ".srw",
    ".3fr",
    ".iiq",
    ".erf",
    ".kdc",
    ".mos",
    ".mrw",
    ".x3f",
)
_EXTRA_HINT = 'pip install "lfcam[raw]"'
# A DNG's CFAPattern codes of the colours.
_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def is_camera_raw(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` has a camera raw extension."""
    return Path(path).suffix.lower() in RAW_EXTENSIONS


def _rawpy(path: Path) -> Any:
    try:
        import rawpy  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        raise InputError(f"{path}: reading camera raw files needs rawpy: {_EXTRA_HINT}") from None
    return rawpy


def _open(path: Path, data: bytes | None) -> Any:
    rawpy = _rawpy(path)
    # LibRaw decodes the bytes read by Python: any byte in the name works.
    if data is None:
        data = read_file_bytes(path, MAX_IMAGE_FILE_BYTES)
    try:
        raw = rawpy.imread(io.BytesIO(data))
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable camera raw file ({exc})") from None
    try:
        # The sensor's size and the visible area's, as the header declares them,
        # before LibRaw unpacks or demosaics anything.
        sizes = raw.sizes
        check_image_size(int(sizes.raw_width), int(sizes.raw_height), 1, str(path))
        check_image_size(int(sizes.width), int(sizes.height), 3, str(path))
    except BaseException:
        raw.close()
        raise
    return raw


def _cfa_name(raw: Any, path: Path) -> str:
    """The mosaic of the visible area's top-left 2 x 2 block, e.g. ``RGGB``."""
    desc = raw.color_desc.decode("ascii", "replace")
    colors = np.asarray(raw.raw_colors_visible[:2, :2])
    if raw.num_colors != 3 or colors.shape != (2, 2):
        raise InputError(f"{path}: not a Bayer (R, G, B) sensor (colours {desc!r})")
    name = "".join(desc[int(c)] for c in colors.ravel())
    if sorted(name) != ["B", "G", "G", "R"]:
        raise InputError(f"{path}: not a 2 x 2 Bayer mosaic (top-left block {name!r})")
    return name


def read_camera_raw(
    path: str | os.PathLike[str], *, mosaic: bool = False, data: bytes | None = None
) -> tuple[np.ndarray, str | None]:
    """Read a camera raw file as linear values.

    Parameters
    ----------
    path : path-like
        A camera raw file (:data:`RAW_EXTENSIONS`).
    mosaic : bool
        Keep the sensor's colour filter array mosaic ``(H, W)`` (the visible area)
        instead of demosaicing it (LibRaw's AHD) to ``(H, W, 3)`` RGB.
    data : bytes, optional
        The file's bytes, already read: decoded instead of reading ``path``.

    Returns
    -------
    image : numpy.ndarray
        uint16, black level subtracted, the white level scaled to 65535; camera RGB
        (no colour matrix, no white balance, no gamma, no automatic brightness).
    cfa : str or None
        The mosaic's top-left 2 x 2 block (``RGGB``, ...) with ``mosaic=True``, else None.

    Raises
    ------
    lfcam.InputError
        rawpy is not installed (the message says ``pip install "lfcam[raw]"``), the
        file is missing or not a raw file LibRaw decodes, its sensor or visible area
        is larger than :data:`~lfcam.io.files.MAX_IMAGE_SIDE` /
        :data:`~lfcam.io.files.MAX_IMAGE_PIXELS`, or (``mosaic=True``) the sensor is
        not a 2 x 2 Bayer mosaic.
    """
    p = Path(path)
    rawpy = _rawpy(p)
    with _open(p, data) as raw:
        try:
            white = float(raw.white_level)
            if mosaic:
                cfa = _cfa_name(raw, p)
                data = np.asarray(raw.raw_image_visible, np.float32)
                black = np.asarray(raw.black_level_per_channel, np.float32)
                blk = black[np.asarray(raw.raw_colors_visible)]
                span = white - blk
                if not (span > 0).all():
                    raise InputError(f"{p}: white level {white:g} is not above the black level")
                with np.errstate(invalid="ignore"):
                    lin = np.clip((data - blk) / span, 0.0, 1.0)
                return np.round(lin * 65535.0).astype(np.uint16), cfa
            rgb = raw.postprocess(
                output_color=rawpy.ColorSpace.raw,
                gamma=(1.0, 1.0),
                no_auto_bright=True,
                use_camera_wb=False,
                use_auto_wb=False,
                user_wb=[1.0, 1.0, 1.0, 1.0],
                output_bps=16,
                user_flip=0,
                adjust_maximum_thr=0.0,
            )
        except rawpy.LibRawError as exc:
            raise InputError(f"{p}: cannot decode the raw data ({exc})") from None
    return np.ascontiguousarray(rgb, dtype=np.uint16), None


@dataclass(frozen=True)
class CaptureMetadata:
    """What a capture's file says about how it was taken (EXIF); None where it is silent."""

    #: Focal length of the (front) lens, mm: picks the zoom setting.
    focal_length_mm: float | None = None
    #: Exposure time, seconds.
    exposure_s: float | None = None
    #: ISO speed.
    iso: float | None = None
    #: Aperture, f-number.
    f_number: float | None = None
    #: Camera maker and model.
    make: str | None = None
    model: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dict."""
        return asdict(self)


def _number(tags: dict[str, Any], *names: str) -> float | None:
    for name in names:
        tag = tags.get(name)
        if tag is None:
            continue
        values = getattr(tag, "values", None)
        v = values[0] if isinstance(values, (list, tuple)) and values else values
        try:
            x = float(v.num) / float(v.den) if hasattr(v, "den") else float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            continue
        if math.isfinite(x) and x > 0:
            return x
    return None


def _text(tags: dict[str, Any], name: str) -> str | None:
    tag = tags.get(name)
    if tag is None:
        return None
    s = str(tag.printable if hasattr(tag, "printable") else tag).strip().strip("\x00").strip()
    return s or None


def read_metadata(path: str | os.PathLike[str], *, data: bytes | None = None) -> CaptureMetadata:
    """A capture's EXIF metadata: focal length, exposure, ISO, aperture, camera.

    Read with exifread (the extra ``lfcam[raw]``), for camera raw files, TIFF and
    JPEG (tags in the EXIF directory or, as TIFF/EP and DNG allow, in the first
    image directory). PNG files carry none, and neither do TIFF and JPEG files
    without the extra installed: every field is then None. Metadata that cannot be
    parsed is an :class:`~lfcam.LfcamWarning` naming the file, and every field None:
    the pixels may still be fine.

    Parameters
    ----------
    path : path-like
        The capture.
    data : bytes, optional
        Its bytes, already read (the ones its pixels were decoded from): parsed
        instead of reading ``path`` again.

    Raises
    ------
    lfcam.InputError
        The file is missing, or it is a camera raw file and exifread is not
        installed (the message says ``pip install "lfcam[raw]"``).
    """
    p = Path(path)
    if data is None and not p.is_file():
        raise InputError(f"{p}: no such file")
    if p.suffix.lower() not in (*RAW_EXTENSIONS, ".tif", ".tiff", ".jpg", ".jpeg"):
        return CaptureMetadata()
    try:
        import exifread  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        if not is_camera_raw(p):
            return CaptureMetadata()
        raise InputError(
            f"{p}: reading a capture's metadata needs exifread: {_EXTRA_HINT}"
        ) from None
    if data is None:
        data = read_file_bytes(p, MAX_IMAGE_FILE_BYTES)
    try:
        tags = exifread.process_file(io.BytesIO(data), details=False)
    except Exception as exc:  # exifread raises many kinds on damaged files
        warnings.warn(
            f"{p}: unreadable EXIF metadata ({type(exc).__name__}: {exc}); recorded as unknown",
            LfcamWarning,
            stacklevel=2,
        )
        return CaptureMetadata()
    return CaptureMetadata(
        focal_length_mm=_number(tags, "EXIF FocalLength", "Image FocalLength"),
        exposure_s=_number(tags, "EXIF ExposureTime", "Image ExposureTime"),
        iso=_number(tags, "EXIF ISOSpeedRatings", "Image ISOSpeedRatings"),
        f_number=_number(tags, "EXIF FNumber", "Image FNumber"),
        make=_text(tags, "Image Make"),
        model=_text(tags, "Image Model"),
    )


def _rational(name: str, x: float, den: int, unit: str) -> tuple[int, int]:
    """``x`` as the TIFF RATIONAL ``(num, den)`` (32-bit unsigned parts), or an
    :class:`~lfcam.InputError` naming the metadata field."""
    lo, hi = 1 / den, 0xFFFFFFFF / den
    ok = isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
    if not (ok and 1 <= round(x * den) <= 0xFFFFFFFF):
        raise InputError(f"metadata.{name}: expected {lo:g} to {hi:g}{unit}, got {x!r}")
    return round(x * den), den


def write_dng(
    path: str | os.PathLike[str],
    mosaic: np.ndarray,
    cfa: str,
    *,
    black_level: int = 0,
    white_level: int | None = None,
    metadata: CaptureMetadata | None = None,
) -> None:
    """Write a Bayer mosaic as an uncompressed DNG (tifffile with the DNG tags).

    Parameters
    ----------
    path : path-like
        The ``.dng`` file to write.
    mosaic : (H, W) uint8 or uint16
        Sensor values as stored (black level included).
    cfa : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}
        The top-left 2 x 2 block of the mosaic.
    black_level, white_level : int
        The sensor's black and white levels (default white: the dtype's maximum).
    metadata : CaptureMetadata, optional
        Written as the TIFF/EP EXIF tags of the image directory (focal length,
        exposure time, ISO, f-number) and Make / Model.

    Raises
    ------
    lfcam.InputError
        If the mosaic, ``cfa`` or the levels are malformed, or a metadata field does
        not fit its tag (ISO 1 to 65535, the others positive and within a 32-bit
        rational), naming it. The file is written atomically
        (:func:`lfcam.io.atomic.atomic_output`): on any error nothing is left.
    """
    import tifffile

    p = Path(path)
    if len(cfa) != 4 or sorted(cfa) != ["B", "G", "G", "R"]:
        raise InputError(f"cfa: expected RGGB, BGGR, GRBG or GBRG, got {cfa!r}")
    arr = np.asarray(mosaic)
    if arr.ndim != 2 or arr.dtype not in (np.uint8, np.uint16):
        raise InputError(
            f"{p}: a DNG mosaic is (H, W) uint8 or uint16, got {arr.dtype} {arr.shape}"
        )
    if white_level is None:
        white_level = int(np.iinfo(arr.dtype).max)
    if not 0 <= black_level < white_level <= 65535:
        raise InputError(f"{p}: need 0 <= black level < white level <= 65535")
    meta = metadata or CaptureMetadata()
    make = meta.make or "lfcam"
    model = meta.model or "lfcam simulated camera"
    identity = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)
    tags: list[tuple[int, str, int, Any, bool]] = [
        (271, "s", 0, make, True),  # Make
        (272, "s", 0, model, True),  # Model
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in cfa), True),  # CFAPattern
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, f"{make} {model}", True),  # UniqueCameraModel
        (50714, "H", 1, (int(black_level),), True),  # BlackLevel
        (50717, "H", 1, (int(white_level),), True),  # WhiteLevel
        (50721, "2i", 9, identity, True),  # ColorMatrix1 (camera = XYZ: unknown colour)
        (50778, "H", 1, (21,), True),  # CalibrationIlluminant1: D65
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1), True),  # AsShotNeutral
    ]
    if meta.exposure_s is not None:
        tags.append(
            (33434, "2I", 1, _rational("exposure_s", meta.exposure_s, 1_000_000, " s"), True)
        )
    if meta.f_number is not None:
        tags.append((33437, "2I", 1, _rational("f_number", meta.f_number, 100, ""), True))
    if meta.iso is not None:
        iso = meta.iso
        if not (
            isinstance(iso, (int, float))
            and not isinstance(iso, bool)
            and math.isfinite(iso)
            and 1 <= round(iso) <= 65535
        ):
            raise InputError(f"metadata.iso: expected 1 to 65535, got {iso!r}")
        tags.append((34855, "H", 1, (round(iso),), True))
    if meta.focal_length_mm is not None:
        focal = _rational("focal_length_mm", meta.focal_length_mm, 1000, " mm")
        tags.append((37386, "2I", 1, focal, True))
    with atomic_output(p) as tmp:
        tifffile.imwrite(
            tmp,
            np.ascontiguousarray(arr.astype(np.uint16, copy=False)),
            photometric=32803,  # CFA
            subfiletype=0,
            software="lfcam",
            extratags=tags,
            metadata=None,
        )
