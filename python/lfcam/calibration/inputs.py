"""The calibration folder: its layout, its settings file, and its captures read alike.

Folder layout::

    CAL_DIR/pattern.png            the digital pattern shown on the board
    CAL_DIR/white/*                captures of a uniform white target
    CAL_DIR/board_<distance>m/*    pattern captures at that distance (metres)
    CAL_DIR/camera.toml            optional: grid, reference, z_c, pattern_pitch, bayer,
                                   reference_distance, scale
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

__all__ = ["CalibrationInputs", "CaptureReader", "find_inputs", "mean_capture"]

_BOARD_RE = re.compile(r"^board_(.+)m$")


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


def find_inputs(cal_dir: str | os.PathLike[str]) -> CalibrationInputs:
    """Check a calibration folder's layout and list its files.

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
    pattern = root / "pattern.png"
    if not pattern.is_file():
        raise InputError(
            f"{pattern}: the calibration pattern is missing (make it with `lfcam pattern`)"
        )
    wdir = root / "white"
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
    toml = root / "camera.toml"
    if toml.is_file():
        try:
            with toml.open("rb") as fh:
                settings = tomllib.load(fh)
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
        unknown = sorted(set(settings) - known)
        if unknown:
            raise InputError(
                f"{toml}: unknown setting(s) {', '.join(unknown)};"
                f" known: {', '.join(sorted(known))}"
            )
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
