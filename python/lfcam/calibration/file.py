"""The :class:`Calibration` type and its file, ``.lfcal`` (HDF5).

A calibration holds everything processing needs from the once-per-camera calibration
(docs/design.md, "Calibration file"). It is validated when it is built, before it is saved
and when it is loaded, by one function, so an invalid calibration cannot exist in
memory or on disk. Loading never runs code from the file: only numbers, plain strings
and a JSON document are read.

File layout, format 1.2
-----------------------
One HDF5 file, readable with any HDF5 library (h5py, MATLAB ``h5read``, Julia HDF5.jl,
the C API). Shapes below are in C (row-major) order, as h5py and C see them; MATLAB and
Julia show the dimensions reversed. ``N = R * C`` views, ``K`` board distances, and
``C_g`` gain channels (1 or 3). Strings are variable-length UTF-8. Every dataset has a
``description`` attribute saying what it holds.

Root attributes (strings):

====================  ===================================================================
``format``            ``"lfcam-calibration"``
``format_version``    ``"MAJOR.MINOR"``, ``"1.2"`` here. A reader refuses a newer MAJOR;
                      a newer MINOR only adds datasets, which older readers ignore.
``software_version``  the lfcam version that wrote the file
``created``           ISO-8601 UTC time of writing, e.g. ``2026-05-01T12:00:00+00:00``
``sha256``            checksum of the other root attributes (see Checksums)
====================  ===================================================================

Datasets at the root, one per field of :class:`Calibration` (no others; one group,
``zoom``, see Zoom settings):

=================  =======  ======================  =======================================
name               dtype    shape                   meaning
=================  =======  ======================  =======================================
``grid``           int64    (2,)                    R, C: lenslet rows, columns
``reference``      int64    ()                      reference view index ``i = r * C + c``
``raw_shape``      int64    (2,)                    H_raw, W_raw of the raw frames
``rect_shape``     int64    (2,)                    H_rect, W_rect of the rectified frame
``pattern_shape``  int64    (2,)                    H_pat, W_pat of the digital pattern
``scale``          float64  ()                      rectified px per pattern px (> 0)
``crops``          int64    (N, 4)                  x0, y0, w, h of each view, raw px
``centres``        float64  (N, 2)                  x, y image-circle centres, raw px
``warps``          float32  (N, H_rect, W_rect, 2)  x, y position in view i's crop of each
                                                    rectified pixel; NaN only where masked
``masks``          uint8    (N, H_rect, W_rect)     1 where view i sees the rectified pixel
``offsets``        float64  (N, 2)                  o_i, rectified px (metric mode), or
                                                    ``d_i = o_i Z_b / Z_c`` (relative mode)
``z_b``            float64  ()                      reference board distance, m (> 0)
``z_c``            float64  ()                      lenslet-centre depth, m; NaN if relative
``metric``         uint8    ()                      1: metric depth; 0: relative depth
``distances``      float64  (K,)                    board distances used, m (Z_b among them)
``pattern_pitch``  float64  ()                      metres per pattern px; NaN if unknown
``gains``          float32  (H_raw, W_raw, C_g)     multiplier of the raw frame (scaled to
                                                    [0, 1]); 0 where masked
``bayer``          string   ()                      ``RGGB``, ``BGGR``, ``GRBG``, ``GBRG``,
                                                    or ``""`` for none
``report``         string   ()                      the calibration report, a JSON object
``focal_length``   float64  ()                      the front lens's focal length of this
                                                    optical setting, mm; NaN: one setting
                                                    (absent before format 1.2: NaN)
=================  =======  ======================  =======================================

``warps``, ``masks`` and ``gains`` are chunked (at most 256 x 256 pixels, one view per
chunk) and stored with the shuffle, gzip (level 4) and Fletcher-32 checksum filters,
all built into HDF5. A reader also accepts any integer dtype for the int64 datasets,
any float or integer dtype for the float ones, and 0/1 integers or booleans for
``masks`` and ``metric``; lfcam converts them to the dtypes above.

Zoom settings (format 1.2)
--------------------------
A camera calibrated at several focal lengths of its zoom lens keeps the first setting
at the root and each other one in a group ``zoom/<j>`` (``j`` = 1, 2, ...), holding only
the datasets that differ from the root's (at least ``focal_length``; ``offsets``,
``z_c``, ``z_b``, ``distances``, ``report``; ``warps`` and ``masks`` only when that
setting does not share the root's), checked like the root's. A setting is the root's
datasets overridden by its group's. ``grid``, ``raw_shape`` and ``bayer`` are the
root's for every setting.

Checksums (format 1.1)
----------------------
The file starts with a 512-byte HDF5 user block holding
``lfcam-calibration sha256 <64 hex digits>\n`` and zero bytes: the SHA-256 of every
byte after the block. It is checked before the HDF5 library reads anything, so a
changed or damaged file is refused before a parser sees it. Every dataset also has an
attribute ``sha256`` over its name, values and other attributes, and the root one over
the root attributes, checked as each is read. Declared sizes are bounded (at most
:data:`MAX_VIEWS` views, frames within ``lfcam.io.MAX_IMAGE_SIDE`` and
``MAX_IMAGE_PIXELS``, at most :data:`MAX_DISTANCES` distances) before any array is read.

A format 1.0 file (no user block, no checksums) still loads, with an
:class:`~lfcam.LfcamWarning`; it is first read in a child process, so that a crash or
hang of the HDF5 library on a damaged file becomes a :class:`~lfcam.CalibrationError`.
Saving it again upgrades it.

Writing datasets goes through ``_write_dataset`` and reading through
``_read_dataset``, both for any HDF5 group, so a later format that adds groups (one
per camera setting, say) gets the same checksums by using them.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import subprocess
import sys
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO, NoReturn

import h5py  # type: ignore[import-untyped]
import numpy as np
from numpy.typing import NDArray

from .._lfcam import __version__
from ..errors import CalibrationError, InputError, LfcamWarning
from ..io import BAYER_PATTERNS, MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE, atomic_output, file_hash

__all__ = [
    "BAYER_PATTERNS",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MAX_DISTANCES",
    "MAX_VIEWS",
    "ZOOM_TOLERANCE",
    "Calibration",
    "file_hash",
    "info",
    "load_settings",
    "save_settings",
    "select_setting",
]

FORMAT_NAME = "lfcam-calibration"
"""The root ``format`` attribute of every ``.lfcal`` file."""

FORMAT_VERSION = (1, 2)
"""(MAJOR, MINOR) of the file format this module writes and reads (and older MINORs)."""

MAX_VIEWS = 4096
"""Most views (``R * C``) a calibration may declare; checked before anything is read."""

MAX_DISTANCES = 1000
"""Most board distances (``K``) a calibration may declare."""

# The HDF5 user block: "lfcam-calibration sha256 <64 hex digits>\n", then zero bytes.
# The digest is SHA-256 of every byte after the block; it is checked before h5py
# (and the HDF5 library) reads anything of the file.
_USERBLOCK_SIZE = 512
_SEAL_PREFIX = b"lfcam-calibration sha256 "
_SEAL_LENGTH = len(_SEAL_PREFIX) + 64 + 1
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
# Attribute holding the SHA-256 of a dataset's values and other attributes (and, at
# the root, of the root attributes).
_DIGEST_ATTR = "sha256"
# A format-1.0 file (no checksums) is first read in a child process: if the HDF5
# library crashes or hangs on it, that is an error naming the file, not a dead process.
_PROBE_TIMEOUT_S = 120.0


# Datasets stored chunked + compressed + checksummed.
_COMPRESSED = ("warps", "masks", "gains")
_GZIP_LEVEL = 4
_CHUNK_PX = 256

_DESCRIPTIONS = {
    "grid": "R, C: lenslet rows, columns",
    "reference": "reference view index i = r*C + c",
    "raw_shape": "H_raw, W_raw of the raw frames, px",
    "rect_shape": "H_rect, W_rect of the rectified frame, px",
    "pattern_shape": "H_pat, W_pat of the digital calibration pattern, px",
    "scale": "rectified px per pattern px",
    "crops": "(N, 4) x0, y0, w, h of each view's crop, raw px",
    "centres": "(N, 2) x, y image-circle centre of each view, raw px",
    "warps": "(N, H_rect, W_rect, 2) x, y in view i's crop of each rectified pixel; "
    "NaN only where masks is 0",
    "masks": "(N, H_rect, W_rect) 1 where view i sees the rectified pixel, else 0",
    "offsets": "(N, 2) parallax vector o_i in rectified px (metric mode) or "
    "d_i = o_i*Z_b/Z_c (relative mode); zero for the reference view",
    "z_b": "reference board distance Z_b, m",
    "z_c": "object-space lenslet-centre depth Z_c, m; NaN in relative mode",
    "metric": "1: depth in metres; 0: relative depth t = s*Z_c/Z_b",
    "distances": "(K,) board distances used in calibration, m",
    "pattern_pitch": "metres per pattern pixel on the board; NaN if unknown",
    "gains": "(H_raw, W_raw, C) multiplier of the raw frame scaled to [0, 1]; 0 where masked",
    "bayer": "Bayer pattern of the raw frames (RGGB, BGGR, GRBG, GBRG) or empty for none",
    "report": "calibration report, a JSON object",
    "focal_length": "front lens focal length of this optical setting, mm; NaN: one setting",
}
# Datasets a zoom setting's group may not hold: every setting shares the root's.
_SHARED_BY_SETTINGS = ("grid", "raw_shape", "bayer")
_ZOOM_GROUP = "zoom"
#: A focal length picks the zoom setting whose focal length is within this share of it.
ZOOM_TOLERANCE = 0.02

# The datasets of a format-1.x file: every field but software_version (a root attribute).
_DATASETS = tuple(_DESCRIPTIONS)
_STRING_DATASETS = ("bayer", "report")
_SCALAR_DATASETS = (
    "reference",
    "scale",
    "z_b",
    "z_c",
    "metric",
    "pattern_pitch",
    "focal_length",
)
# dtype kinds a numeric dataset or field may have (b: bool, i/u: integers, f: floats).
_INT_KINDS = "iu"
_FLOAT_KINDS = "fiu"
_BOOL_KINDS = "biu"
_KINDS = {
    "grid": _INT_KINDS,
    "reference": _INT_KINDS,
    "raw_shape": _INT_KINDS,
    "rect_shape": _INT_KINDS,
    "pattern_shape": _INT_KINDS,
    "crops": _INT_KINDS,
    "masks": _BOOL_KINDS,
    "metric": _BOOL_KINDS,
}  # every other numeric dataset: _FLOAT_KINDS

_VERSION_RE = re.compile(r"^\s*(\d+)\.(\d+)\s*$")


# --------------------------------------------------------------------------- validation


def _expected_shapes(
    grid: tuple[int, int], raw_shape: tuple[int, int], rect_shape: tuple[int, int]
) -> dict[str, tuple[tuple[int | None, ...], str]]:
    """Expected shape (``None``: any length) and its symbolic form, for every array."""
    n = grid[0] * grid[1]
    hr, wr = rect_shape
    h, w = raw_shape
    return {
        "grid": ((2,), "(2,)"),
        "raw_shape": ((2,), "(2,)"),
        "rect_shape": ((2,), "(2,)"),
        "pattern_shape": ((2,), "(2,)"),
        "crops": ((n, 4), "(N, 4)"),
        "centres": ((n, 2), "(N, 2)"),
        "warps": ((n, hr, wr, 2), "(N, H_rect, W_rect, 2)"),
        "masks": ((n, hr, wr), "(N, H_rect, W_rect)"),
        "offsets": ((n, 2), "(N, 2)"),
        "distances": ((None,), "(K,)"),
        "gains": ((h, w, None), "(H_raw, W_raw, C) with C = 1 or 3"),
        **dict.fromkeys(_SCALAR_DATASETS, ((), "() (a scalar)")),
    }


def _check_shape(
    name: str,
    shape: tuple[int, ...],
    expected: tuple[tuple[int | None, ...], str],
    where: str,
) -> None:
    want, symbolic = expected
    ok = len(shape) == len(want) and all(e is None or e == s for e, s in zip(want, shape))
    if name == "gains" and ok:
        ok = shape[2] in (1, 3)
    if name == "distances" and ok:
        ok = 1 <= shape[0] <= MAX_DISTANCES
    if not ok:
        letter = {"distances": "K", "gains": "C"}.get(name, "?")
        if name == "distances":
            symbolic += f" with 1 <= K <= {MAX_DISTANCES}"
        shown = tuple(letter if e is None else e for e in want)
        raise CalibrationError(
            f"{where}: {name}: expected shape {symbolic} = {_fmt_shape(shown)}, "
            f"got {_fmt_shape(shape)}"
        )


def _fmt_shape(shape: tuple[Any, ...]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _check_kind(name: str, dtype: np.dtype[Any], where: str) -> None:
    kinds = _KINDS.get(name, _FLOAT_KINDS)
    if dtype.kind not in kinds or dtype.fields is not None:
        what = {
            _INT_KINDS: "integers",
            _FLOAT_KINDS: "numbers",
            _BOOL_KINDS: "booleans or 0/1 integers",
        }[kinds]
        raise CalibrationError(f"{where}: {name}: expected {what}, got dtype {dtype}")


def _as_array(value: Any, name: str, where: str) -> NDArray[Any]:
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"{where}: {name}: not an array ({e})") from None
    _check_kind(name, arr.dtype, where)
    return arr


def _int_pair(value: Any, name: str, where: str) -> tuple[int, int]:
    arr = _as_array(value, name, where)
    _check_shape(name, arr.shape, ((2,), "(2,)"), where)
    a, b = (int(v) for v in arr.tolist())
    if a < 1 or b < 1:
        raise CalibrationError(f"{where}: {name}: expected two integers >= 1, got ({a}, {b})")
    return a, b


def _check_sizes(
    grid: tuple[int, int],
    raw_shape: tuple[int, int],
    rect_shape: tuple[int, int],
    where: str,
) -> None:
    """Bounds on the declared sizes, so that no array they imply is absurdly large."""
    n = grid[0] * grid[1]
    if n > MAX_VIEWS:
        raise CalibrationError(
            f"{where}: grid: {grid[0]} x {grid[1]} = {n} views, more than lfcam reads ({MAX_VIEWS})"
        )
    for name, (h, w) in (("raw_shape", raw_shape), ("rect_shape", rect_shape)):
        if max(h, w) > MAX_IMAGE_SIDE or h * w > MAX_IMAGE_PIXELS:
            raise CalibrationError(
                f"{where}: {name}: a {h} x {w} (H x W) frame is larger than lfcam reads "
                f"({MAX_IMAGE_SIDE} px a side, {MAX_IMAGE_PIXELS} px in all)"
            )
    if n * rect_shape[0] * rect_shape[1] > MAX_IMAGE_PIXELS:
        raise CalibrationError(
            f"{where}: rect_shape: {n} views of {rect_shape[0]} x {rect_shape[1]} px are "
            f"more rectified pixels than lfcam reads ({MAX_IMAGE_PIXELS} in all)"
        )


def _scalar(value: Any, name: str, where: str) -> Any:
    if isinstance(value, (bool, np.bool_)) and _KINDS.get(name) != _BOOL_KINDS:
        raise CalibrationError(f"{where}: {name}: expected a number, got {value!r}")
    arr = _as_array(value, name, where)
    if arr.ndim != 0:
        raise CalibrationError(f"{where}: {name}: expected a scalar, got shape {arr.shape}")
    return arr[()].item()


def _float(value: Any, name: str, where: str) -> float:
    return float(_scalar(value, name, where))


def _first_bad(bad: NDArray[np.bool_]) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(bad)[0])


def _validate(values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """Check every field of a calibration and return them in their canonical types.

    The one validator, used by :meth:`Calibration.__post_init__`, :meth:`Calibration.save`
    and :meth:`Calibration.load`. Arrays come back C-contiguous in their documented
    dtypes (the same object if it already is), scalars as Python numbers, ``report``
    as a fresh JSON round trip.

    Raises
    ------
    CalibrationError
        ``"{where}: {field}: {problem}"`` for the first problem found.
    """
    out: dict[str, Any] = {}

    def fail(msg: str) -> NoReturn:
        raise CalibrationError(f"{where}: {msg}")

    # Sizes first: every expected shape follows from them.
    grid = _int_pair(values["grid"], "grid", where)
    raw_shape = _int_pair(values["raw_shape"], "raw_shape", where)
    rect_shape = _int_pair(values["rect_shape"], "rect_shape", where)
    pattern_shape = _int_pair(values["pattern_shape"], "pattern_shape", where)
    _check_sizes(grid, raw_shape, rect_shape, where)
    out.update(grid=grid, raw_shape=raw_shape, rect_shape=rect_shape, pattern_shape=pattern_shape)
    n = grid[0] * grid[1]
    shapes = _expected_shapes(grid, raw_shape, rect_shape)

    def array(name: str, dtype: type[np.generic]) -> NDArray[Any]:
        arr = _as_array(values[name], name, where)
        _check_shape(name, arr.shape, shapes[name], where)
        with np.errstate(over="ignore", invalid="ignore"):
            return np.ascontiguousarray(arr, dtype=dtype)

    reference = _scalar(values["reference"], "reference", where)
    if not 0 <= reference < n:
        fail(f"reference: view index {reference} is out of range for a {grid[0]} x {grid[1]} grid")
    out["reference"] = int(reference)

    scale = _float(values["scale"], "scale", where)
    if not (math.isfinite(scale) and scale > 0):
        fail(f"scale: expected a finite number > 0, got {scale}")
    out["scale"] = scale

    crops = array("crops", np.int64)
    sizes = {(int(w), int(h)) for w, h in crops[:, 2:].tolist()}
    if len(sizes) != 1:
        fail(f"crops: every view must have the same w, h; got {sorted(sizes)}")
    h_raw, w_raw = raw_shape
    for i, (x0, y0, w, h) in enumerate(crops.tolist()):
        if w < 1 or h < 1:
            fail(f"crops: view {i}: empty crop w={w}, h={h}")
        if x0 < 0 or y0 < 0 or x0 > w_raw - w or y0 > h_raw - h:
            fail(
                f"crops: view {i} (x0={x0}, y0={y0}, w={w}, h={h}) lies outside the "
                f"{w_raw} x {h_raw} (W x H) raw frame"
            )
    out["crops"] = crops

    for name in ("centres", "offsets"):
        arr = array(name, np.float64)
        bad = ~np.isfinite(arr)
        if bad.any():
            i, j = _first_bad(bad)
            fail(f"{name}: view {i} has a non-finite value {arr[i, j]} (NaN or inf)")
        out[name] = arr
    ref_offset = out["offsets"][out["reference"]]
    if np.any(ref_offset != 0):
        fail(
            f"offsets: the reference view's offset must be (0, 0), got "
            f"({ref_offset[0]}, {ref_offset[1]}) for view {out['reference']}"
        )

    raw_masks = _as_array(values["masks"], "masks", where)
    _check_shape("masks", raw_masks.shape, shapes["masks"], where)
    if raw_masks.dtype.kind != "b" and not np.all((raw_masks == 0) | (raw_masks == 1)):
        fail("masks: expected only 0 and 1 (or False and True)")
    masks = np.ascontiguousarray(raw_masks, dtype=np.bool_)
    out["masks"] = masks

    # A float64 value too large for float32 becomes inf here and is refused below.
    warps = array("warps", np.float32)
    bad = masks & ~np.isfinite(warps).all(axis=-1)
    if bad.any():
        i, v, u = _first_bad(bad)
        fail(
            f"warps: view {i} has NaN or inf at rectified pixel (u={u}, v={v}) where masks is "
            f"True; NaN is allowed only where masks is False"
        )
    out["warps"] = warps

    z_b = _float(values["z_b"], "z_b", where)
    if not (math.isfinite(z_b) and z_b > 0):
        fail(f"z_b: expected a finite distance > 0 m, got {z_b}")
    out["z_b"] = z_b

    metric = _scalar(values["metric"], "metric", where)
    if metric not in (0, 1):
        fail(f"metric: expected True/False (1/0), got {metric!r}")
    out["metric"] = bool(metric)

    z_c = _float(values["z_c"], "z_c", where)
    if out["metric"]:
        if not (math.isfinite(z_c) and 0 <= z_c < z_b):
            fail(f"z_c: metric mode needs a finite 0 <= z_c < z_b = {z_b} m, got {z_c}")
    elif not math.isnan(z_c):
        fail(f"z_c: must be NaN in relative mode (metric is False), got {z_c}")
    out["z_c"] = z_c

    distances = array("distances", np.float64)
    if not (np.isfinite(distances).all() and (distances > 0).all()):
        fail(f"distances: expected finite distances > 0 m, got {distances.tolist()}")
    if not np.isclose(distances, z_b, rtol=1e-9, atol=0.0).any():
        fail(f"distances: z_b = {z_b} m is not among the board distances {distances.tolist()}")
    out["distances"] = distances

    pitch = _float(values["pattern_pitch"], "pattern_pitch", where)
    if not (math.isnan(pitch) or (math.isfinite(pitch) and pitch > 0)):
        fail(f"pattern_pitch: expected a finite number > 0 m, or NaN if unknown, got {pitch}")
    out["pattern_pitch"] = pitch

    gains = array("gains", np.float32)
    finite = np.isfinite(gains)
    if not finite.all():
        y, x, c = _first_bad(~finite)
        fail(f"gains: non-finite value {gains[y, x, c]} at raw pixel (x={x}, y={y}), channel {c}")
    if (gains < 0).any():
        y, x, c = _first_bad(gains < 0)
        fail(f"gains: negative value {gains[y, x, c]} at raw pixel (x={x}, y={y}), channel {c}")
    out["gains"] = gains

    bayer = values["bayer"]
    if bayer is not None and (not isinstance(bayer, str) or bayer not in BAYER_PATTERNS):
        fail(f"bayer: expected None or one of {', '.join(BAYER_PATTERNS)}, got {bayer!r}")
    out["bayer"] = bayer

    report = values["report"]
    if not isinstance(report, dict):
        fail(f"report: expected a dict (a JSON object), got {type(report).__name__}")
    try:
        text = json.dumps(report, allow_nan=False, ensure_ascii=False)
    except (TypeError, ValueError, RecursionError) as e:
        fail(f"report: not JSON-serialisable ({e}); use None, not NaN, for missing numbers")
    out["report"] = json.loads(text)

    focal = _float(values.get("focal_length", math.nan), "focal_length", where)
    if not (math.isnan(focal) or (math.isfinite(focal) and focal > 0)):
        fail(f"focal_length: expected a finite number > 0 mm, or NaN, got {focal}")
    out["focal_length"] = focal

    version = values["software_version"]
    if not isinstance(version, str) or not version.strip():
        fail(f"software_version: expected a non-empty string, got {version!r}")
    out["software_version"] = version
    return out


# --------------------------------------------------------------------------- the type


@dataclass(eq=False)
class Calibration:
    """Everything processing needs from a camera's calibration (docs/design.md, "Calibration file").

    Built by the calibration steps, saved with :meth:`save` and read back with
    :meth:`load`. Every field is validated on construction (and again by :meth:`save`,
    in case a field was changed since); arrays are converted to the dtypes below.
    ``N = R * C`` views, view ``i = r * C + c``.

    Attributes
    ----------
    grid : tuple of int
        ``(R, C)`` lenslet rows and columns.
    reference : int
        Reference view index; depth and products are in its rectified frame.
    raw_shape, rect_shape, pattern_shape : tuple of int
        ``(H, W)`` of the raw frames, the rectified frame and the digital pattern.
    scale : float
        Rectified pixels per pattern pixel, > 0.
    crops : numpy.ndarray of int64, shape (N, 4)
        ``x0, y0, w, h`` of each view's crop in raw pixels; all of the same size and
        inside the raw frame.
    centres : numpy.ndarray of float64, shape (N, 2)
        ``x, y`` image-circle centres in raw pixels.
    warps : numpy.ndarray of float32, shape (N, H_rect, W_rect, 2)
        For each rectified pixel, the ``x, y`` position in view i's crop to sample
        (OpenCV ``remap`` convention). NaN only where ``masks`` is False.
    masks : numpy.ndarray of bool, shape (N, H_rect, W_rect)
        Where view i sees the rectified pixel.
    offsets : numpy.ndarray of float64, shape (N, 2)
        ``o_i`` in rectified pixels (metric mode) or ``d_i = o_i * Z_b / Z_c``
        (relative mode); ``offsets[reference]`` is exactly 0.
    z_b : float
        Reference board distance ``Z_b``, metres, > 0.
    z_c : float
        Object-space lenslet-centre depth ``Z_c``, metres, ``0 <= z_c < z_b``; NaN in
        relative mode.
    metric : bool
        True: depth in metres; False: relative depth ``t = s * Z_c / Z_b``.
    distances : numpy.ndarray of float64, shape (K,)
        Board distances used, metres; ``z_b`` is one of them.
    pattern_pitch : float
        Metres per pattern pixel on the board; NaN if unknown (then X, Y are not
        metric).
    gains : numpy.ndarray of float32, shape (H_raw, W_raw, C)
        ``C`` is 1 or 3. Multiplier of the raw frame scaled to [0, 1]; finite, >= 0,
        0 where masked.
    bayer : str or None
        None, or the raw frames' Bayer pattern: ``RGGB``, ``BGGR``, ``GRBG``, ``GBRG``.
    focal_length : float
        The front lens's focal length (mm) of this optical setting, for a zoom lens
        calibrated at several settings; NaN for a camera with one.
    report : dict
        The calibration report, a JSON object (strict JSON: no NaN; use None). Stored
        as its JSON round trip, so tuples become lists and keys strings. Headline
        numbers under ``report["summary"]`` are shown by :meth:`summary`.
    software_version : str
        The lfcam version that made the calibration.

    Raises
    ------
    CalibrationError
        If any field breaks a rule above; the message names the field.
    """

    grid: tuple[int, int]
    reference: int
    raw_shape: tuple[int, int]
    rect_shape: tuple[int, int]
    pattern_shape: tuple[int, int]
    scale: float
    crops: NDArray[np.int64]
    centres: NDArray[np.float64]
    warps: NDArray[np.float32]
    masks: NDArray[np.bool_]
    offsets: NDArray[np.float64]
    z_b: float
    z_c: float
    metric: bool
    distances: NDArray[np.float64]
    pattern_pitch: float
    gains: NDArray[np.float32]
    bayer: str | None
    report: dict[str, Any]
    focal_length: float = math.nan
    software_version: str = __version__

    def __post_init__(self) -> None:
        self._set(_validate(self._values(), "invalid calibration"))

    def _values(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def _set(self, values: Mapping[str, Any]) -> None:
        for name, value in values.items():
            setattr(self, name, value)

    def __repr__(self) -> str:
        r, c = self.grid
        return (
            f"Calibration(grid=({r}, {c}), reference={self.reference}, "
            f"raw_shape={self.raw_shape}, rect_shape={self.rect_shape}, "
            f"metric={self.metric}, z_b={self.z_b}, z_c={self.z_c}, bayer={self.bayer!r})"
        )

    @property
    def n_views(self) -> int:
        """Number of views ``N = R * C``."""
        return self.grid[0] * self.grid[1]

    @property
    def reference_rc(self) -> tuple[int, int]:
        """``(row, col)`` of the reference view in the lenslet grid."""
        r, c = divmod(self.reference, self.grid[1])
        return r, c

    # ----------------------------------------------------------------------- writing

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the calibration to an ``.lfcal`` (HDF5) file, atomically.

        The file is written under a temporary name in the same folder and renamed to
        ``path`` only once complete, so ``path`` is either the old file or the whole
        new one; on any error the temporary file is removed.

        Parameters
        ----------
        path : path-like
            Destination, conventionally ending in ``.lfcal``. Replaced if it exists.

        Returns
        -------
        pathlib.Path
            ``path``.

        Raises
        ------
        CalibrationError
            If a field was changed since construction and is now invalid.
        InputError
            If the destination folder does not exist or ``path`` is a folder.
        OSError
            If writing fails (disk full, permissions).
        """
        p = Path(path)
        values = _validate(self._values(), "cannot save calibration")
        self._set(values)
        if not p.parent.is_dir():
            raise InputError(f"{p}: folder {p.parent} does not exist")
        if p.is_dir():
            raise InputError(f"{p}: is a folder")
        with atomic_output(p) as tmp:
            with h5py.File(tmp, "w", userblock_size=_USERBLOCK_SIZE) as f:
                _write(f, values)
            _seal_file(tmp)
        return p

    # ----------------------------------------------------------------------- reading

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str],
        focal_length: float | None = None,
        *,
        sha256: str | None = None,
    ) -> Calibration:
        """Read and validate an ``.lfcal`` file.

        Parameters
        ----------
        path : path-like
            A file written by :meth:`save` (or by any program following the layout in
            this module's docstring).
        sha256 : str, optional
            Refuse the file unless its SHA-256 (:func:`lfcam.io.file_hash`) is this:
            the bytes hashed are the bytes parsed.
        focal_length : float, optional
            For a file of several zoom settings: the focal length (mm) whose setting
            to load (within ZOOM_TOLERANCE; :func:`select_setting`).

        Returns
        -------
        Calibration

        Raises
        ------
        InputError
            If ``path`` does not exist or is a folder.
        CalibrationError
            If the file is not HDF5, is corrupt or truncated (including a failed
            checksum), is not an lfcam calibration, was written by a newer major
            format version, lacks a dataset or has an unexpected one, or holds
            inconsistent data, or its SHA-256 is not ``sha256``. The message starts
            with the path and names the dataset or attribute at fault.
        """
        settings = load_settings(path, sha256=sha256)
        return select_setting(settings, focal_length, str(path), "focal_length")

    # ----------------------------------------------------------------------- display

    def summary(self) -> str:
        """A readable multi-line description: sizes, depth model, per-view table, report.

        Returns
        -------
        str
            Aligned text, no trailing newline; what ``lfcam info CAMERA.lfcal`` prints.
        """
        r, c = self.grid
        rr, rc = self.reference_rc
        h, w = self.raw_shape
        hr, wr = self.rect_shape
        hp, wp = self.pattern_shape
        n_ch = self.gains.shape[2]
        masked = float(np.mean(np.all(self.gains == 0, axis=2))) * 100
        if self.metric:
            mode = "metric (depth Z in metres)"
            z_c = f"{self.z_c:.6g} m (object-space lenslet-centre depth)"
        else:
            mode = "relative (t = s * Z_c / Z_b; Z_c unknown)"
            z_c = "unknown (relative mode)"
        pitch = (
            "unknown (X, Y not metric)"
            if math.isnan(self.pattern_pitch)
            else f"{self.pattern_pitch * 1e3:.6g} mm per pattern px"
        )
        header = [
            ("format", f"{FORMAT_NAME} {FORMAT_VERSION[0]}.{FORMAT_VERSION[1]}"),
            ("software version", self.software_version),
            ("grid", f"{r} x {c} lenslets ({self.n_views} views)"),
            ("reference view", f"{self.reference} (row {rr}, col {rc})"),
            ("raw frame", f"{h} x {w} px (H x W)"),
            ("rectified frame", f"{hr} x {wr} px (H x W)"),
            ("pattern", f"{hp} x {wp} px (H x W)"),
            ("scale", f"{self.scale:.6g} rectified px per pattern px"),
            ("depth mode", mode),
            ("Z_b", f"{self.z_b:.6g} m (reference board distance)"),
            ("Z_c", z_c),
            ("board distances", ", ".join(f"{d:.6g}" for d in self.distances.tolist()) + " m"),
            ("pattern pitch", pitch),
            ("Bayer", self.bayer or "none"),
            (
                "focal length",
                "one setting" if math.isnan(self.focal_length) else f"{self.focal_length:g} mm",
            ),
            ("gains", f"{n_ch} channel{'s' if n_ch > 1 else ''}, {masked:.1f}% of raw px masked"),
            ("report", ", ".join(str(k) for k in self.report) or "empty"),
        ]
        lines = ["lfcam calibration"]
        width = max(len(k) for k, _ in header)
        lines += [f"  {k:<{width}}  {v}" for k, v in header]

        o = "o" if self.metric else "d"
        coverage = self.masks.reshape(self.n_views, -1).mean(axis=1) * 100
        rows = []
        for i in range(self.n_views):
            x0, y0, cw, ch = self.crops[i].tolist()
            cx, cy = self.centres[i].tolist()
            ox, oy = self.offsets[i].tolist()
            rows.append(
                [
                    f"{i}{'*' if i == self.reference else ''}",
                    str(i // c),
                    str(i % c),
                    str(x0),
                    str(y0),
                    str(cw),
                    str(ch),
                    f"{cx:.2f}",
                    f"{cy:.2f}",
                    f"{ox:.3f}",
                    f"{oy:.3f}",
                    f"{math.hypot(ox, oy):.3f}",
                    f"{coverage[i]:.1f}",
                ]
            )
        heads = ["view", "row", "col", "x0", "y0", "w", "h", "centre x", "centre y"]
        heads += [f"{o}_x", f"{o}_y", f"|{o}|", "coverage %"]
        unit = "o_i in rectified px" if self.metric else "d_i = o_i Z_b / Z_c in rectified px"
        lines += ["", f"views (* reference; crops and centres in raw px; {unit})"]
        lines += _table(heads, rows)

        headline = self.report.get("summary")
        if isinstance(headline, dict) and headline:
            lines += ["", "report summary"]
            kw = max(len(str(k)) for k in headline)
            lines += [f"  {k!s:<{kw}}  {_fmt_value(v)}" for k, v in headline.items()]
        return "\n".join(lines)


def _fmt_value(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return json.dumps(v)
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (dict, list)):
        return json.dumps(v, ensure_ascii=False)
    return str(v)


def _table(heads: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(h), *(len(r[j]) for r in rows)) for j, h in enumerate(heads)]
    out = ["  " + "  ".join(h.rjust(w) for h, w in zip(heads, widths))]
    out += ["  " + "  ".join(v.rjust(w) for v, w in zip(r, widths)) for r in rows]
    return out


# --------------------------------------------------------------------------- checksums


def _encode(value: Any) -> bytes:
    """A value's bytes for a checksum: kind, dtype and shape, then the data."""
    if isinstance(value, str):
        return b"s" + value.encode("utf-8", "surrogatepass")
    if isinstance(value, bytes):
        return b"b" + value
    arr = np.asarray(value)
    if arr.dtype.kind in "OSU":  # strings in an array: each one's bytes
        parts = [
            _encode(v.decode("utf-8", "surrogateescape") if isinstance(v, bytes) else v)
            for v in arr.reshape(-1).tolist()
        ]
        return (
            b"a"
            + repr(arr.shape).encode()
            + b"".join(len(x).to_bytes(8, "little") + x for x in parts)
        )
    le = arr.dtype.newbyteorder("<")
    data = np.ascontiguousarray(arr, dtype=le)
    return b"n" + le.str.encode() + repr(arr.shape).encode() + data.tobytes()


def _digest(items: list[tuple[str, Any]]) -> str:
    """SHA-256 of (name, value) pairs, as 64 hex digits."""
    h = hashlib.sha256()
    for name, value in items:
        for part in (name.encode("utf-8", "surrogatepass"), _encode(value)):
            h.update(len(part).to_bytes(8, "little"))
            h.update(part)
    return h.hexdigest()


def _attrs_items(node: h5py.HLObject) -> list[tuple[str, Any]]:
    return [(k, node.attrs[k]) for k in sorted(node.attrs) if k != _DIGEST_ATTR]


def _dataset_digest(ds: h5py.Dataset, value: Any) -> str:
    """Checksum of a dataset: its name, its values and its other attributes."""
    return _digest([("", ds.name), ("value", value), *_attrs_items(ds)])


def _dataset_value(ds: h5py.Dataset) -> Any:
    """A dataset's values as read for its checksum: strings as str, numbers as arrays."""
    if h5py.check_string_dtype(ds.dtype) is not None:
        return ds.asstr()[()] if ds.shape == () else [str(v) for v in ds.asstr()[()].tolist()]
    return ds[()]


def _seal_file(path: Path) -> None:
    """Write the file's SHA-256 (of everything after the user block) into its user block."""
    with open(path, "rb+") as fh:
        seal = _SEAL_PREFIX + file_hash(fh, offset=_USERBLOCK_SIZE).encode() + b"\n"
        fh.seek(0)
        fh.write(seal + bytes(_USERBLOCK_SIZE - len(seal)))


def _seal(path: str | os.PathLike[str]) -> None:
    """Recompute every checksum of an lfcam file that has a user block.

    For files changed with another HDF5 tool on purpose (and for the tests, which damage
    files in known ways): the dataset checksums from their current values, the root's,
    then the whole-file checksum in the user block.
    """
    p = Path(path)
    with h5py.File(p, "r+") as f:
        if f.userblock_size != _USERBLOCK_SIZE:
            raise CalibrationError(f"{p}: no {_USERBLOCK_SIZE}-byte user block to seal")
        datasets: list[h5py.Dataset] = []
        f.visititems(lambda _, obj: datasets.append(obj) if isinstance(obj, h5py.Dataset) else None)
        for ds in datasets:
            ds.attrs[_DIGEST_ATTR] = _dataset_digest(ds, _dataset_value(ds))
        f.attrs[_DIGEST_ATTR] = _digest(_attrs_items(f))
    _seal_file(p)


def _check_seal(fh: BinaryIO, where: str) -> bool:
    """Verify the whole-file checksum of an open file, before anything parses it.

    Returns True for a sealed (format 1.1 or later) file, False for an HDF5 file
    without a seal (format 1.0, or written by another program).
    """
    try:
        fh.seek(0)
        head = fh.read(_USERBLOCK_SIZE + len(_HDF5_SIGNATURE))
        if not head.startswith(_SEAL_PREFIX):
            if not any(head[o : o + len(_HDF5_SIGNATURE)] == _HDF5_SIGNATURE for o in (0, 512)):
                raise CalibrationError(
                    f"{where}: not an HDF5 file, so not an lfcam calibration (.lfcal)"
                )
            return False
        seal = head[:_SEAL_LENGTH]
        stored = seal[len(_SEAL_PREFIX) : -1].decode("ascii", "replace")
        if (
            len(head) < _USERBLOCK_SIZE
            or seal[-1:] != b"\n"
            or re.fullmatch(r"[0-9a-f]{64}", stored) is None
            or any(head[_SEAL_LENGTH:_USERBLOCK_SIZE])
        ):
            raise CalibrationError(
                f"{where}: corrupt or truncated: its checksum block (the HDF5 user block) "
                "is damaged"
            )
        digest = file_hash(fh, offset=_USERBLOCK_SIZE)
    except OSError as e:
        raise CalibrationError(f"{where}: cannot read file ({e.strerror or e})") from None
    if digest != stored:
        raise CalibrationError(
            f"{where}: corrupt or truncated: the file's SHA-256 checksum does not match the "
            "one stored in it (the file was changed or damaged after it was written)"
        )
    return True


# What the probe's child prints when it has read the file (or refused it with an lfcam
# error, which the parent then meets and reports itself).
_PROBE_OK = "lfcam-probe: read"
_PROBE_CODE = f"""
import sys
from lfcam.errors import LfcamError
from lfcam.calibration.file import _read_hdf5
try:
    _read_hdf5(sys.argv[1])
except LfcamError:
    pass
print({_PROBE_OK!r})
"""


def _probe(p: Path, where: str) -> None:
    """Read an unsealed file in a child process first: a crash or hang there is an error,
    and so is any end of the child other than its success marker and exit code 0."""
    # The child imports this very lfcam, wherever it was imported from.
    root = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join(x for x in (root, os.environ.get("PYTHONPATH")) if x)
    try:
        run = subprocess.run(
            [sys.executable, "-c", _PROBE_CODE, os.fsencode(p)],
            stdin=subprocess.DEVNULL,
            capture_output=True,
            env={**os.environ, "PYTHONPATH": path},
            timeout=_PROBE_TIMEOUT_S,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise CalibrationError(
            f"{where}: corrupt: reading it did not finish within {_PROBE_TIMEOUT_S:.0f} s"
        ) from None
    if run.returncode < 0:
        raise CalibrationError(
            f"{where}: corrupt: reading it crashed the HDF5 library (signal {-run.returncode})"
        )
    if run.returncode != 0 or run.stdout.splitlines()[-1:] != [_PROBE_OK.encode()]:
        last = run.stderr.decode("utf-8", "replace").strip().splitlines()[-1:]
        why = f": {last[0]}" if last else ""
        raise CalibrationError(
            f"{where}: a format 1.0 file is read in a child process first, and that"
            f" failed (exit code {run.returncode}{why})"
        )


# --------------------------------------------------------------------------- HDF5 I/O


def _write_dataset(
    group: h5py.Group, name: str, data: Any, description: str, *, compressed: bool
) -> h5py.Dataset:
    """One dataset with its description and its checksum (any group: the root or a setting)."""
    if compressed:
        shape = np.shape(data)
        if len(shape) == 3 and name == "gains":  # (H_raw, W_raw, C): tiles of all channels
            chunks: tuple[int, ...] = (
                min(shape[0], _CHUNK_PX),
                min(shape[1], _CHUNK_PX),
                shape[2],
            )
        else:  # (N, H_rect, W_rect[, 2]): tiles of one view
            chunks = (1, min(shape[1], _CHUNK_PX), min(shape[2], _CHUNK_PX), *shape[3:])
        ds = group.create_dataset(
            name,
            data=data,
            chunks=chunks,
            shuffle=True,
            compression="gzip",
            compression_opts=_GZIP_LEVEL,
            fletcher32=True,
        )
    else:
        ds = group.create_dataset(name, data=data)
    ds.attrs["description"] = description
    ds.attrs[_DIGEST_ATTR] = _dataset_digest(ds, data)
    return ds


def _field_data(name: str, value: Any) -> Any:
    """A validated field's value as its dataset stores it."""
    if name == "bayer":
        return value or ""
    if name == "report":
        return json.dumps(value, allow_nan=False, ensure_ascii=False)
    if name in ("masks", "metric"):
        return np.asarray(value, dtype=np.uint8)
    if isinstance(value, tuple) or name == "reference":
        return np.asarray(value, dtype=np.int64)
    if isinstance(value, float):
        return np.float64(value)
    return value


def _same(a: Any, b: Any) -> bool:
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and bool(
            np.array_equal(a, b, equal_nan=a.dtype.kind == "f" and b.dtype.kind == "f")
        )
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def _write(f: h5py.File, values: Mapping[str, Any], settings: list[Mapping[str, Any]] = ()) -> None:
    f.attrs["format"] = FORMAT_NAME
    f.attrs["format_version"] = f"{FORMAT_VERSION[0]}.{FORMAT_VERSION[1]}"
    f.attrs["software_version"] = values["software_version"]
    f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    for name in _DATASETS:
        data = _field_data(name, values[name])
        _write_dataset(f, name, data, _DESCRIPTIONS[name], compressed=name in _COMPRESSED)
    if settings:
        zoom = f.create_group(_ZOOM_GROUP)
        for j, other in enumerate(settings, start=1):
            g = zoom.create_group(str(j))
            for name in _DATASETS:
                if name == "focal_length" or not _same(other[name], values[name]):
                    data = _field_data(name, other[name])
                    compressed = name in _COMPRESSED
                    _write_dataset(g, name, data, _DESCRIPTIONS[name], compressed=compressed)
    f.attrs[_DIGEST_ATTR] = _digest(_attrs_items(f))


def save_settings(path: str | os.PathLike[str], settings: list[Calibration]) -> Path:
    """Write the calibrations of a zoom lens's optical settings to one ``.lfcal`` file,
    atomically (layout: this module's "Zoom settings").

    Parameters
    ----------
    path : path-like
        Destination.
    settings : list of Calibration
        One per focal length (each finite and different); the first is the file's root.
        A setting that shares the first's warp maps stores none of its own.

    Raises
    ------
    CalibrationError
        A setting is invalid, lacks a focal length, repeats one, or differs from the
        first in grid, raw frame or Bayer pattern.
    InputError
        As :meth:`Calibration.save`.
    """
    p = Path(path)
    if not settings:
        raise CalibrationError(f"{p}: no settings to save")
    values = [
        _validate(c._values(), f"cannot save calibration (zoom setting {j})")
        for j, c in enumerate(settings)
    ]
    seen: list[float] = []
    for j, v in enumerate(values):
        f = v["focal_length"]
        if len(values) > 1 and not math.isfinite(f):
            raise CalibrationError(f"{p}: zoom setting {j}: focal_length is NaN")
        if f in seen:
            raise CalibrationError(f"{p}: two zoom settings of focal length {f:g} mm")
        seen.append(f)
        for name in _SHARED_BY_SETTINGS:
            if not _same(v[name], values[0][name]):
                raise CalibrationError(
                    f"{p}: zoom setting {f:g} mm: {name} {v[name]!r} differs from the first"
                    f" setting's {values[0][name]!r} (one camera)"
                )
    if not p.parent.is_dir():
        raise InputError(f"{p}: folder {p.parent} does not exist")
    if p.is_dir():
        raise InputError(f"{p}: is a folder")
    with atomic_output(p) as tmp:
        with h5py.File(tmp, "w", userblock_size=_USERBLOCK_SIZE) as fh:
            _write(fh, values[0], values[1:])
        _seal_file(tmp)
    return p


def _attr_str(f: h5py.File, name: str, where: str) -> str:
    """A root attribute that must be a string (variable- or fixed-length, UTF-8 or ASCII)."""
    if name not in f.attrs:
        raise CalibrationError(f"{where}: missing root attribute {name!r}")
    value: Any = f.attrs[name]
    if isinstance(value, np.ndarray) and value.size == 1 and value.dtype.kind in "OSU":
        value = value.reshape(-1)[0]  # a one-element string array, as some writers make
    if isinstance(value, bytes):
        try:
            value = value.decode("utf-8")
        except UnicodeDecodeError:
            raise CalibrationError(f"{where}: root attribute {name!r} is not UTF-8 text") from None
    if not isinstance(value, str):
        raise CalibrationError(f"{where}: root attribute {name!r} is not a string: {value}")
    return str(value)


def _read_header(f: h5py.File, where: str) -> dict[str, Any]:
    fmt = _attr_str(f, "format", where) if "format" in f.attrs else None
    if fmt is None:
        raise CalibrationError(
            f"{where}: not an lfcam calibration file (HDF5 without a 'format' attribute)"
        )
    if fmt != FORMAT_NAME:
        raise CalibrationError(
            f"{where}: not an lfcam calibration file: format attribute is {fmt!r}, "
            f"expected {FORMAT_NAME!r}"
        )
    version = _attr_str(f, "format_version", where)
    m = _VERSION_RE.match(version)
    if m is None:
        raise CalibrationError(
            f"{where}: unreadable format_version {version!r} (expected MAJOR.MINOR, e.g. '1.0')"
        )
    major, minor = int(m.group(1)), int(m.group(2))
    ours = f"{FORMAT_VERSION[0]}.x"
    if major > FORMAT_VERSION[0]:
        raise CalibrationError(
            f"{where}: written by a newer lfcam (format {major}.{minor}); this lfcam "
            f"reads format {ours}: upgrade lfcam (installed: lfcam {__version__})"
        )
    if major < FORMAT_VERSION[0]:
        raise CalibrationError(
            f"{where}: unsupported format version {major}.{minor}; this lfcam reads format {ours}"
        )
    created = _attr_str(f, "created", where)
    try:
        datetime.fromisoformat(created[:-1] + "+00:00" if created.endswith("Z") else created)
    except ValueError:
        raise CalibrationError(
            f"{where}: root attribute 'created' is not an ISO-8601 time: {created!r}"
        ) from None
    return {
        "format_version": (major, minor),
        "software_version": _attr_str(f, "software_version", where),
        "created": created,
    }


def _read_dataset(group: h5py.Group, name: str, where: str, expected: Any, *, sealed: bool) -> Any:
    """Read one dataset after checking its kind and shape (so nothing huge or odd is read);
    in a sealed file, check its values against its checksum."""
    ds = group[name]
    if not isinstance(ds, h5py.Dataset):
        raise CalibrationError(f"{where}: {name}: expected a dataset, found a group")
    if name in _STRING_DATASETS:
        if h5py.check_string_dtype(ds.dtype) is None:
            raise CalibrationError(f"{where}: {name}: expected a string, got dtype {ds.dtype}")
        if ds.shape != ():
            raise CalibrationError(
                f"{where}: {name}: expected a scalar string, got shape {ds.shape}"
            )
        try:
            value: Any = str(ds.asstr()[()])
        except UnicodeDecodeError:
            raise CalibrationError(f"{where}: {name}: not valid UTF-8 text") from None
    else:
        _check_kind(name, ds.dtype, where)
        if expected is not None:
            _check_shape(name, ds.shape, expected, where)
        try:
            value = ds[()]
        except (OSError, ValueError, RuntimeError) as e:
            hint = ""
            if "filter returned failure" in str(e):  # HDF5's words for a failed checksum
                hint = ": its Fletcher-32 checksum or decompression failed, the file is damaged"
            raise CalibrationError(
                f"{where}: corrupt or truncated: cannot read dataset {name!r} ({e}){hint}"
            ) from None
    if sealed:
        stored = ds.attrs.get(_DIGEST_ATTR)
        if not isinstance(stored, str):
            raise CalibrationError(f"{where}: {name}: no {_DIGEST_ATTR!r} checksum attribute")
        if _dataset_digest(ds, value) != stored:
            raise CalibrationError(
                f"{where}: {name}: its values do not match their checksum "
                "(the dataset was changed or damaged after it was written)"
            )
    return value


def _parse_report(text: str, where: str) -> Any:
    def reject(token: str) -> NoReturn:
        raise ValueError(f"{token} is not valid JSON (use null)")

    try:
        return json.loads(text, parse_constant=reject)
    except (ValueError, RecursionError) as e:
        raise CalibrationError(f"{where}: report: not valid JSON ({e})") from None


def _read_hdf5(
    source: str | os.PathLike[str] | BinaryIO, where: str | None = None, *, sealed: bool = False
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Parse a file (a path, or a file open for reading) with h5py: (raw field values,
    file header). ``sealed``: the user block's checksum was verified, so every dataset
    and the root carry checksums too."""
    if isinstance(source, (str, os.PathLike)):
        source = Path(source)
        where = str(source) if where is None else where
    where = "calibration file" if where is None else where
    raw: dict[str, Any] = {}
    try:
        with h5py.File(source, "r") as f:
            header = _read_header(f, where)
            version = header["format_version"]
            if not sealed and version >= (1, 1):
                raise CalibrationError(
                    f"{where}: corrupt: a format {version[0]}.{version[1]} file carries a "
                    "checksum in its HDF5 user block, and this one has none"
                )
            if sealed and f.attrs.get(_DIGEST_ATTR) != _digest(_attrs_items(f)):
                raise CalibrationError(
                    f"{where}: the root attributes do not match their checksum "
                    "(changed or damaged after the file was written)"
                )
            members = set(f.keys())
            if version >= (1, 2):
                members.discard(_ZOOM_GROUP)
            else:
                members.add("focal_length")  # absent before 1.2: NaN
                raw["focal_length"] = math.nan
            missing = [name for name in _DATASETS if name not in members]
            if missing:
                raise CalibrationError(
                    f"{where}: missing dataset{'s' if len(missing) > 1 else ''} "
                    f"{', '.join(repr(m) for m in missing)} (incomplete file)"
                )
            extra = sorted(members - set(_DATASETS))
            if extra and version[1] <= FORMAT_VERSION[1]:
                raise CalibrationError(
                    f"{where}: unexpected dataset{'s' if len(extra) > 1 else ''} "
                    f"{', '.join(repr(e) for e in extra)} in a format "
                    f"{version[0]}.{version[1]} file"
                )
            # Sizes first, bounded; then every other dataset's shape is checked before
            # it is read.
            for name in ("grid", "raw_shape", "rect_shape"):
                raw[name] = _int_pair(
                    _read_dataset(f, name, where, None, sealed=sealed), name, where
                )
            _check_sizes(raw["grid"], raw["raw_shape"], raw["rect_shape"], where)
            shapes = _expected_shapes(raw["grid"], raw["raw_shape"], raw["rect_shape"])
            for name in _DATASETS:
                if name not in raw:
                    raw[name] = _read_dataset(f, name, where, shapes.get(name), sealed=sealed)
            header["settings"] = (
                _read_settings(f[_ZOOM_GROUP], raw, where, sealed=sealed)
                if version >= (1, 2) and _ZOOM_GROUP in f
                else []
            )
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as e:
        raise CalibrationError(f"{where}: corrupt or truncated: {e}") from None
    header["checksums"] = sealed
    return raw, header


def _read_settings(
    zoom: Any, root: dict[str, Any], where: str, *, sealed: bool
) -> list[dict[str, Any]]:
    """Each zoom setting's raw values: the root's overridden by its group's datasets."""
    if not isinstance(zoom, h5py.Group):
        raise CalibrationError(f"{where}: {_ZOOM_GROUP}: expected a group")
    keys = sorted(zoom.keys(), key=lambda k: (len(k), k))
    if keys != [str(j) for j in range(1, len(keys) + 1)] or len(keys) > MAX_DISTANCES:
        raise CalibrationError(
            f"{where}: {_ZOOM_GROUP}: expected groups 1, 2, ... (at most {MAX_DISTANCES}),"
            f" got {keys[:10]}"
        )
    out = []
    for key in keys:
        g = zoom[key]
        here = f"{where}: {_ZOOM_GROUP}/{key}"
        if not isinstance(g, h5py.Group):
            raise CalibrationError(f"{here}: expected a group")
        names = set(g.keys())
        bad = sorted(names - set(_DATASETS) | (names & set(_SHARED_BY_SETTINGS)))
        if bad or "focal_length" not in names:
            raise CalibrationError(
                f"{here}: a setting holds focal_length and datasets other than"
                f" {', '.join(_SHARED_BY_SETTINGS)}; got {sorted(names)}"
            )
        raw = dict(root)
        if "rect_shape" in names:
            raw["rect_shape"] = _int_pair(
                _read_dataset(g, "rect_shape", here, None, sealed=sealed), "rect_shape", here
            )
            _check_sizes(raw["grid"], raw["raw_shape"], raw["rect_shape"], here)
        shapes = _expected_shapes(raw["grid"], raw["raw_shape"], raw["rect_shape"])
        for name in sorted(names - {"rect_shape"}):
            raw[name] = _read_dataset(g, name, here, shapes.get(name), sealed=sealed)
        for name in ("warps", "masks"):
            if name not in names and raw["rect_shape"] != root["rect_shape"]:
                raise CalibrationError(
                    f"{here}: rect_shape differs from the root's, so {name} must too"
                )
        out.append(raw)
    return out


def _finish(raw: dict[str, Any], header: dict[str, Any], where: str) -> dict[str, Any]:
    raw["bayer"] = raw["bayer"] or None
    if isinstance(raw["report"], str):
        raw["report"] = _parse_report(raw["report"], where)
    raw["software_version"] = header["software_version"]
    return _validate(raw, where)


def _read(
    path: str | os.PathLike[str], sha256: str | None = None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Verify, read and validate a file: (canonical field values, file header).

    One open file is hashed (``sha256``, the seal) and parsed: a file renamed over
    ``path`` meanwhile is not read in its place."""
    if path is None or not isinstance(path, (str, os.PathLike)):
        raise InputError(f"path: expected a calibration file's path, got {path!r}")
    p = Path(path)
    where = str(p)
    if not p.exists():
        raise InputError(f"{p}: no such calibration file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a calibration file")
    if not p.is_file():
        raise InputError(f"{p}: not a regular file")
    with contextlib.ExitStack() as stack:
        try:
            fh = stack.enter_context(open(p, "rb"))
            got = None if sha256 is None else file_hash(fh)
        except OSError as e:
            raise CalibrationError(f"{where}: cannot read file ({e.strerror or e})") from None
        if got != sha256:
            raise CalibrationError(f"{where}: sha256 {got} differs from the expected {sha256}")
        sealed = _check_seal(fh, where)
        if not sealed:
            _probe(p, where)
        fh.seek(0)
        raw, header = _read_hdf5(fh, where, sealed=sealed)
    if not sealed:
        warnings.warn(
            f"{where}: a format 1.0 calibration file, without checksums: damage to it "
            "cannot be detected. Save it again to upgrade it (Calibration.load(path).save(path)).",
            LfcamWarning,
            stacklevel=3,
        )
    header["settings"] = [
        _finish(dict(r), header, f"{where}: {_ZOOM_GROUP}/{j}")
        for j, r in enumerate(header.get("settings", []), start=1)
    ]
    return _finish(raw, header, where), header


def load_settings(path: str | os.PathLike[str], *, sha256: str | None = None) -> list[Calibration]:
    """Every optical setting of an ``.lfcal`` file (one for a camera without zoom
    settings), validated; as :meth:`Calibration.load`."""
    values, header = _read(path, sha256)
    return [Calibration(**values)] + [Calibration(**v) for v in header["settings"]]


def select_setting(
    settings: list[Calibration], focal_length: float | None, where: str, what: str
) -> Calibration:
    """The setting for ``focal_length`` (mm): the one within ZOOM_TOLERANCE of it.

    A file with one setting and no focal length (calibrated without zoom settings)
    serves every focal length; one setting with a focal length serves that one, and
    any setting serves an unknown focal length only when it is the file's only one.
    ``where`` names the calibration and ``what`` the focal length's source in the
    messages.

    Raises
    ------
    InputError
        Several settings and no focal length, or none within the tolerance (naming
        the focal length and every setting).
    """
    if len(settings) == 1 and (focal_length is None or math.isnan(settings[0].focal_length)):
        return settings[0]
    known = ", ".join(f"{c.focal_length:g}" for c in settings) + " mm"
    if focal_length is None:
        raise InputError(
            f"{where}: has zoom settings {known}: {what} has no focal length"
            " (give --zoom F or focal_length=F, or a capture whose metadata has it)"
        )
    near = [
        c for c in settings if abs(c.focal_length - focal_length) <= ZOOM_TOLERANCE * c.focal_length
    ]
    if not near:
        raise InputError(
            f"{what}: focal length {focal_length:g} mm matches none of {where}'s zoom"
            f" settings {known} (within {100 * ZOOM_TOLERANCE:g}%)"
        )
    return min(near, key=lambda c: abs(c.focal_length - focal_length))


def info(path: str | os.PathLike[str]) -> str:
    """Load an ``.lfcal`` file and describe it: what ``lfcam info CAMERA.lfcal`` prints.

    Parameters
    ----------
    path : path-like
        The calibration file.

    Returns
    -------
    str
        The file's path, format version, creation time and SHA-256, then
        :meth:`Calibration.summary`.

    Raises
    ------
    InputError, CalibrationError
        As :meth:`Calibration.load`.
    """
    values, header = _read(path)
    cal = Calibration(**values)
    major, minor = header["format_version"]
    head = [
        ("file", str(path)),
        ("file format", f"{major}.{minor}"),
        ("created", header["created"]),
        ("sha256", file_hash(path)),
        (
            "checksums",
            "verified (the file, every dataset)"
            if header["checksums"]
            else "none (format 1.0 file)",
        ),
    ]
    others = [Calibration(**v) for v in header["settings"]]
    if others:
        listed = []
        for c in [cal, *others]:
            shared = c.warps is cal.warps or _same(c.warps, cal.warps)
            z_c = f"Z_c {c.z_c:.4f} m" if c.metric else "relative depth"
            listed.append(
                f"{c.focal_length:g} mm ({z_c}, Z_b {c.z_b:g} m, warp maps"
                f" {'shared' if shared else 'its own'})"
            )
        head.append(("zoom settings", "; ".join(listed)))
    width = max(len(k) for k, _ in head)
    text = "\n".join(f"{k:<{width}}  {v}" for k, v in head) + "\n\n" + cal.summary()
    for c in others:
        text += f"\n\nzoom setting {c.focal_length:g} mm\n" + c.summary()
    return text
