"""The calibration folder: its layout, its settings file, and its captures read alike.

Folder layout::

    CAL_DIR/pattern.png            the digital pattern shown on the board
    CAL_DIR/white/*                captures of a uniform white target
    CAL_DIR/board_<distance>m/*    pattern captures at that distance (metres)
    CAL_DIR/camera.toml            optional: grid, reference, z_c, pattern_pitch, bayer,
                                   reference_distance, scale

A zoom lens calibrated at several settings has one folder per setting, named by the
front lens's focal length, each laid out as above; ``pattern.png``, ``white/`` and
``camera.toml`` may instead be shared at the top (a setting's own ``camera.toml``
overrides the shared one key by key)::

    CAL_DIR/zoom_<f>mm/board_<distance>m/*   e.g. zoom_50mm/board_1.0m/
    CAL_DIR/zoom_<f>mm/white/*               optional: this setting's white captures
"""

from __future__ import annotations

import math
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io import is_image_file, read_raw, to_float

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["CalibrationInputs", "CaptureReader", "find_inputs", "find_settings", "mean_capture"]

_BOARD_RE = re.compile(r"^board_(.+)m$")
_ZOOM_RE = re.compile(r"^zoom_(.+)mm$")


@dataclass
class CalibrationInputs:
    """The files of a calibration folder, checked and sorted."""

    root: Path
    pattern: Path
    white: list[Path]
    boards: dict[float, list[Path]]  # distance (m) -> captures
    settings: dict[str, Any]  # from camera.toml


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if is_image_file(p))


def find_settings(cal_dir: str | os.PathLike[str]) -> dict[float | None, CalibrationInputs]:
    """The optical settings of a calibration folder: focal length (mm) -> its inputs,
    sorted; ``{None: ...}`` for a folder without ``zoom_<f>mm/`` settings.

    Raises
    ------
    lfcam.InputError
        Naming the missing or malformed file or folder.
    """
    root = Path(cal_dir)
    if not root.is_dir():
        return {None: find_inputs(root)}
    found: dict[float, Path] = {}
    for d in sorted(root.iterdir()):
        if not d.is_dir() or not d.name.startswith("zoom"):
            continue
        m = _ZOOM_RE.match(d.name)
        try:
            if m is None:
                raise ValueError
            f = float(m.group(1))
            if not (math.isfinite(f) and f > 0):
                raise ValueError
        except ValueError:
            raise InputError(
                f"{d}: cannot read a focal length from the folder name;"
                " use zoom_<millimetres>mm, e.g. zoom_50mm"
            ) from None
        if f in found:
            raise InputError(f"{d}: a second folder for focal length {f:g} mm (and {found[f]})")
        found[f] = d
    if not found:
        return {None: find_inputs(root)}
    boards = [d for d in root.iterdir() if d.is_dir() and d.name.startswith("board")]
    if boards:
        raise InputError(
            f"{boards[0]}: board folders go inside a zoom_<f>mm/ setting folder when"
            " there are settings"
        )
    return {f: find_inputs(found[f], shared=root) for f in sorted(found)}


def find_inputs(
    cal_dir: str | os.PathLike[str], *, shared: str | os.PathLike[str] | None = None
) -> CalibrationInputs:
    """Check a calibration folder's layout and list its files.

    ``shared``: the folder above a zoom setting's, where ``pattern.png``, ``white/`` and
    ``camera.toml`` are found when the setting has none of its own.

    Raises
    ------
    lfcam.InputError
        Naming the missing or malformed file or folder.
    """
    root = Path(cal_dir)
    if not root.exists():
        raise InputError(f"{root}: no such calibration folder")
    if not root.is_dir():
        raise InputError(f"{root}: not a folder")
    top = Path(shared) if shared is not None else None
    pattern = root / "pattern.png"
    if not pattern.is_file() and top is not None and (top / "pattern.png").is_file():
        pattern = top / "pattern.png"
    if not pattern.is_file():
        raise InputError(
            f"{pattern}: the calibration pattern is missing (make it with `lfcam pattern`)"
        )
    wdir = root / "white"
    if not wdir.is_dir() and top is not None and (top / "white").is_dir():
        wdir = top / "white"
    if not wdir.is_dir():
        raise InputError(f"{wdir}: no white-target folder")
    white = _images(wdir)
    if not white:
        raise InputError(f"{wdir}: no images (PNG, TIFF, JPEG or camera raw) of the white target")
    boards: dict[float, list[Path]] = {}
    for d in sorted(root.iterdir()):
        if not d.is_dir() or not d.name.startswith("board"):
            continue
        m = _BOARD_RE.match(d.name)
        try:
            if m is None:
                raise ValueError
            z = float(m.group(1))
            if not (math.isfinite(z) and z > 0):
                raise ValueError
        except ValueError:
            raise InputError(
                f"{d}: cannot read a distance from the folder name;"
                " use board_<metres>m, e.g. board_1.0m"
            ) from None
        if z in boards:
            raise InputError(f"{d}: a second folder for distance {z:g} m")
        imgs = _images(d)
        if not imgs:
            raise InputError(f"{d}: no images of the board")
        boards[z] = imgs
    if not boards:
        raise InputError(f"{root}: no board folder (board_<distance>m/, e.g. board_1.0m/)")
    settings: dict[str, Any] = {}
    tomls = [t for t in ((top / "camera.toml") if top else None, root / "camera.toml") if t]
    for toml in tomls:
        if not toml.is_file():
            continue
        try:
            with toml.open("rb") as fh:
                table = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"{toml}: not valid TOML: {exc}") from None
        known = {
            "grid",
            "reference",
            "z_c",
            "pattern_pitch",
            "bayer",
            "reference_distance",
            "scale",
        }
        unknown = sorted(set(table) - known)
        if unknown:
            raise InputError(
                f"{toml}: unknown setting(s) {', '.join(unknown)};"
                f" known: {', '.join(sorted(known))}"
            )
        settings.update(table)
    return CalibrationInputs(root, pattern, white, boards, settings)


class CaptureReader:
    """Reads raw captures as float RGB in [0, 1], all of one size."""

    def __init__(self, bayer: str | None) -> None:
        self.bayer = bayer
        self.shape: tuple[int, ...] | None = None
        self.first: Path | None = None

    def __call__(self, path: Path) -> np.ndarray:
        img = to_float(read_raw(path, self.bayer))
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if self.shape is None:
            self.shape, self.first = img.shape, path
        elif img.shape != self.shape:
            raise InputError(
                f"{path}: image size {img.shape[1]}x{img.shape[0]} differs from"
                f" {self.first} ({self.shape[1]}x{self.shape[0]})"
            )
        return img


def mean_capture(reader: CaptureReader, paths: list[Path]) -> np.ndarray:
    acc = None
    for p in paths:
        img = reader(p)
        acc = img.astype(np.float64) if acc is None else acc + img
    assert acc is not None
    return (acc / len(paths)).astype(np.float32)
