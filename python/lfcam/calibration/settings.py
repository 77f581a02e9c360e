"""A calibration file's zoom settings together, and the choice of one per capture
(docs/design.md, "Zoom settings in processing").

A capture names the setting it needs through the focal length of the front lens: given
by the caller (``lfcam process --zoom F``, ``focal_length=F``) or read from its EXIF
metadata. A focal length within :data:`~lfcam.calibration.file.ZOOM_TOLERANCE` of a
setting's picks it; any other is an :class:`~lfcam.InputError` naming the focal length
and every setting, never the nearest setting.
"""

from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass
from typing import Any

from ..errors import InputError
from .file import Calibration, load_settings, select_setting

__all__ = ["SettingChoice", "ZoomCalibration", "check_focal_length"]


def check_focal_length(value: Any, name: str) -> None:
    """Raise :class:`~lfcam.InputError` naming ``name`` unless ``value`` is a focal
    length: a finite number > 0 (mm)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if not (ok and math.isfinite(value) and value > 0):
        raise InputError(f"{name}: expected a focal length > 0 mm, got {value!r}")


@dataclass(frozen=True)
class SettingChoice:
    """Which setting of a :class:`ZoomCalibration` served a capture, and why.

    Attributes
    ----------
    calibration : Calibration
        The setting used.
    chosen_by : str
        ``"focal_length"`` (given by the caller: ``--zoom``, ``focal_length=``),
        ``"metadata"`` (the capture's EXIF focal length) or ``"only setting"`` (a
        calibration of one setting and no focal length to check against it).
    focal_length_mm : float or None
        The focal length that chose it: the one given, else the capture's; None if
        neither is known.
    settings_mm : tuple of float
        Every setting's focal length, mm (empty for a calibration without zoom
        settings).
    """

    calibration: Calibration
    chosen_by: str
    focal_length_mm: float | None
    settings_mm: tuple[float, ...]

    def to_dict(self) -> dict[str, Any]:
        """What ``result.json`` records (``calibration_setting``), JSON-ready."""
        cal = self.calibration
        f = cal.focal_length
        return {
            "focal_length_mm": None if math.isnan(f) else f,
            "chosen_by": self.chosen_by,
            "requested_focal_length_mm": self.focal_length_mm,
            "settings_mm": list(self.settings_mm),
            "z_c_m": cal.z_c if cal.metric else None,
            "z_b_m": cal.z_b,
        }


@dataclass(frozen=True, eq=False)
class ZoomCalibration:
    """Every optical setting of one calibration file: a zoom lens calibrated at
    several focal lengths, or a camera with one setting.

    Parameters
    ----------
    settings : tuple of Calibration
        The settings; several must each have a distinct, finite ``focal_length``.
    source : str
        What to call the calibration in messages (its file's path).

    Examples
    --------
    >>> zoom = lfcam.ZoomCalibration.load("zoom.lfcal")  # doctest: +SKIP
    >>> zoom.focal_lengths  # doctest: +SKIP
    (50.0, 75.0, 100.0)
    >>> cal = zoom.select(75.0)  # the 75 mm setting (within 2%)  # doctest: +SKIP
    """

    settings: tuple[Calibration, ...]
    source: str = "the calibration"

    def __post_init__(self) -> None:
        settings = tuple(self.settings)
        if not settings or not all(isinstance(c, Calibration) for c in settings):
            raise InputError(f"{self.source}: expected one or more Calibration settings")
        if len(settings) > 1:
            focal = [c.focal_length for c in settings]
            if not all(math.isfinite(f) for f in focal) or len(set(focal)) != len(focal):
                raise InputError(
                    f"{self.source}: several settings need distinct focal lengths, got"
                    f" {', '.join(f'{f:g}' for f in focal)} mm"
                )
        object.__setattr__(self, "settings", settings)

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, sha256: str | None = None) -> ZoomCalibration:
        """Every setting of an ``.lfcal`` file, each read and validated once.

        Parameters
        ----------
        path : path-like
            The calibration file.
        sha256 : str, optional
            Refuse the file unless its SHA-256 is this (:meth:`Calibration.load`).

        Raises
        ------
        InputError, CalibrationError
            As :meth:`Calibration.load`.
        """
        return cls(tuple(load_settings(path, sha256=sha256)), str(path))

    @classmethod
    def of(cls, cal: Calibration | ZoomCalibration) -> ZoomCalibration:
        """``cal`` itself, or a single :class:`Calibration` as a one-setting one."""
        if isinstance(cal, ZoomCalibration):
            return cal
        if not isinstance(cal, Calibration):
            raise InputError(
                f"cal: expected a Calibration or ZoomCalibration, got {type(cal).__name__}"
            )
        return cls((cal,))

    @property
    def focal_lengths(self) -> tuple[float, ...]:
        """Each setting's focal length, mm; empty for a calibration without zoom
        settings (one setting, focal length NaN)."""
        return tuple(c.focal_length for c in self.settings if math.isfinite(c.focal_length))

    def __len__(self) -> int:
        return len(self.settings)

    def select(self, focal_length: float | None, what: str = "focal_length") -> Calibration:
        """The setting for ``focal_length`` (mm), within ``ZOOM_TOLERANCE`` (2%).

        A calibration without zoom settings serves every focal length; one setting
        with a focal length serves only that one.

        Raises
        ------
        InputError
            No setting within the tolerance, or several settings and no focal length;
            the message names ``what``, the focal length and every setting.
        """
        if focal_length is not None:
            check_focal_length(focal_length, what)
        return select_setting(list(self.settings), focal_length, self.source, what)

    def choose(
        self,
        focal_length: float | None = None,
        *,
        capture_focal_length: float | None = None,
        capture: str = "the capture",
    ) -> SettingChoice:
        """The setting for one capture: by ``focal_length`` when given (it overrides
        the capture's metadata), else by the capture's own focal length.

        Parameters
        ----------
        focal_length : float, optional
            The focal length the caller gives (``--zoom``), mm.
        capture_focal_length : float, optional
            The capture's focal length from its metadata, mm.
        capture : str
            The capture's name in messages.

        Raises
        ------
        InputError
            As :meth:`select`, naming the capture.
        """
        zoomed = self.focal_lengths
        if focal_length is not None:
            cal = self.select(focal_length, "focal_length")
            how = "focal_length" if zoomed else "only setting"
            return SettingChoice(cal, how, float(focal_length), zoomed)
        if capture_focal_length is not None:
            try:
                cal = self.select(capture_focal_length, f"{capture} (its metadata)")
            except InputError as exc:
                raise InputError(
                    f"{exc}; --zoom F (focal_length=F) overrides the capture's metadata"
                ) from None
            how = "metadata" if zoomed else "only setting"
            return SettingChoice(cal, how, float(capture_focal_length), zoomed)
        return SettingChoice(self.select(None, capture), "only setting", None, zoomed)
