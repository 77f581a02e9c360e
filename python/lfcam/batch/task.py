"""One capture of a batch: its options, its outcome, and the task a worker runs.

A worker (a local process, a Dask worker or the calling process) gets the calibration
once (:func:`load_calibration` checks its sha256) and then runs :func:`run_capture` per
capture, which never raises: whatever goes wrong is the capture's outcome.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..calibration import Calibration, ZoomCalibration
from ..calibration.settings import check_focal_length
from ..errors import InputError, LfcamError
from ..io.lock import LockBusy, path_lock
from ..kernels import INTERPOLATIONS
from ..outputs import FRAMES, NovelViewOptions, write_capture
from ..pipeline import process_capture

__all__ = [
    "CaptureOutcome",
    "CaptureTask",
    "ProcessOptions",
    "as_tuple",
    "failure_reason",
    "is_complete",
    "load_calibration",
    "run_capture",
]


@dataclass(frozen=True)
class ProcessOptions:
    """What to make of each capture of a batch (:func:`lfcam.process_folder`).

    Attributes
    ----------
    save_views : bool
        Also write the rectified views (``views/``).
    superres : int or None
        Also write ``superres.png``, the reference view super-resolved by this factor
        (1 to 4).
    refocus : tuple of float
        Also write ``refocus_<Z>m.png`` at these distances, metres (beyond ``Z_c``).
    novel : NovelViewOptions or None
        The mesh and novel views to write.
    overwrite : bool
        Redo captures whose output folder is complete (else they are skipped).
    interp : str
        Rectification resampling.
    frame : {'valid', 'full'}
        The image outputs' frame (:func:`lfcam.outputs.output_frame`): cut to the
        reference view's valid box, or the calibration's whole rectified frame.
    focal_length : float or None
        The front lens's focal length (mm) of every capture: picks the calibration's
        zoom setting, overriding each capture's metadata (``--zoom``); None: each
        capture's own (:meth:`lfcam.ZoomCalibration.choose`).
    """

    save_views: bool = False
    superres: int | None = None
    refocus: tuple[float, ...] = ()
    novel: NovelViewOptions | None = None
    overwrite: bool = False
    interp: str = "bilinear"
    frame: str = "valid"
    focal_length: float | None = None

    def check_values(self) -> None:
        """Raise :class:`~lfcam.InputError` naming a malformed option (no calibration
        needed: checked before one is loaded)."""
        if self.frame not in FRAMES:
            raise InputError(f"frame: expected one of {', '.join(FRAMES)}, got {self.frame!r}")
        if self.superres is not None and not (
            isinstance(self.superres, int)
            and not isinstance(self.superres, bool)
            and 1 <= self.superres <= 4
        ):
            raise InputError(f"superres: expected a factor from 1 to 4, got {self.superres!r}")
        if not isinstance(self.interp, str) or self.interp not in INTERPOLATIONS:
            choices = ", ".join(repr(i) for i in INTERPOLATIONS)
            raise InputError(f"interp: expected one of {choices}, got {self.interp!r}")
        if not isinstance(self.refocus, tuple):
            raise InputError(f"refocus: expected a tuple of distances, got {self.refocus!r}")
        if self.focal_length is not None:
            check_focal_length(self.focal_length, "focal_length")

    def settings(self, cal: Calibration | ZoomCalibration) -> tuple[Calibration, ...]:
        """The settings of ``cal`` that captures may use: the one ``focal_length``
        picks, else all (an :class:`~lfcam.InputError` if it picks none)."""
        zoom = ZoomCalibration.of(cal)
        if self.focal_length is None:
            return zoom.settings
        return (zoom.select(self.focal_length, "focal_length"),)

    def check(self, cal: Calibration | ZoomCalibration) -> None:
        """Raise :class:`~lfcam.InputError` naming the option that is malformed or that
        ``cal`` (each setting captures may use) cannot serve."""
        self.check_values()
        for c in self.settings(cal):
            where = f" ({c.focal_length:g} mm setting)" if math.isfinite(c.focal_length) else ""
            if self.refocus and not c.metric:
                raise InputError(
                    f"refocus: the calibration{where} is relative (no Z_c): no metric focus"
                )
            bad = [z for z in self.refocus if not (math.isfinite(z) and z > c.z_c)]
            if bad:
                raise InputError(
                    f"refocus: distances must be beyond Z_c = {c.z_c:.3f} m{where}: {bad}"
                )
            n = self.novel
            if (
                n is not None
                and (n.pose is not None or n.orbit)
                and not (c.metric and math.isfinite(c.pattern_pitch))
            ):
                raise InputError(
                    f"novel: views need a metric calibration{where} with a known pattern pitch"
                )


@dataclass(frozen=True)
class CaptureTask:
    """One capture to process: its raw file and its output folder."""

    source: str
    out: str


@dataclass(frozen=True)
class CaptureOutcome:
    """What became of one capture.

    Attributes
    ----------
    source, out : str
        The raw file and its output folder.
    status : str
        ``"done"``, ``"skipped"`` (complete already), ``"failed"`` or ``"busy"``
        (another run holds its lock).
    reason : str or None
        Why it failed.
    seconds : float
        Time spent on it, wall clock.
    timings : dict
        The pipeline's timings of its stages, seconds.
    """

    source: str
    out: str
    status: str
    reason: str | None = None
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)


def is_complete(out: str | os.PathLike[str]) -> bool:
    """Whether an output folder is complete (it has ``result.json``)."""
    return (Path(out) / "result.json").is_file()


def load_calibration(path: str | os.PathLike[str], sha256: str | None) -> ZoomCalibration:
    """Load a calibration (every zoom setting, each once), refusing it if its sha256 is
    not ``sha256`` (when given).

    A worker loads the batch's calibration once; the check catches a file replaced
    since the batch started, or a shared path that shows another file on this host.
    The file hashed is the file parsed (:meth:`Calibration.load`).
    """
    return ZoomCalibration.load(path, sha256=sha256)


def failure_reason(exc: BaseException) -> str:
    """Why a capture failed, in words: an lfcam error's message, else the exception's
    type and message."""
    if isinstance(exc, LfcamError):
        return str(exc)
    if isinstance(exc, MemoryError):
        return f"out of memory ({exc or 'MemoryError'})"
    return f"{type(exc).__name__}: {exc}"


def run_capture(
    task: CaptureTask,
    cal: Calibration | ZoomCalibration,
    options: ProcessOptions,
    extra: dict[str, Any],
    *,
    threads: int,
    wait: bool = False,
) -> CaptureOutcome:
    """Process one capture into its output folder, holding the folder's lock.

    Never raises for the capture's sake: an exception of any type is a ``"failed"``
    outcome with its reason. Without ``wait``, a folder locked by another run is a
    ``"busy"`` outcome at once; a folder found complete under the lock is ``"skipped"``
    (unless ``options.overwrite``). The capture's zoom setting is chosen by
    :func:`lfcam.process_capture` (``options.focal_length``, else its metadata).
    """
    t0 = time.perf_counter()

    def outcome(status: str, reason: str | None = None, **kw: Any) -> CaptureOutcome:
        return CaptureOutcome(task.source, task.out, status, reason, time.perf_counter() - t0, **kw)

    try:
        Path(task.out).parent.mkdir(parents=True, exist_ok=True)
        with path_lock(task.out, wait=wait):
            if not options.overwrite and is_complete(task.out):
                return outcome("skipped")
            res = process_capture(
                task.source,
                cal,
                focal_length=options.focal_length,
                interp=options.interp,
                threads=threads,
                superres=options.superres,
                refocus=options.refocus,
            )
            assert res.setting is not None
            write_capture(
                task.out,
                res,
                res.setting.calibration,
                extra=extra,
                save_views=options.save_views,
                novel=options.novel,
                frame=options.frame,
            )
        return outcome("done", timings=dict(res.timings))
    except LockBusy:
        return outcome("busy")
    except Exception as exc:  # any failure is this capture's, reported with its reason
        return outcome("failed", failure_reason(exc))


def result_extra(
    cal_path: str | None,
    cal_sha256: str | None,
    options: ProcessOptions,
    parameters: dict[str, Any],
) -> dict[str, Any]:
    """What ``result.json`` records about the batch (calibration, parameters, products)."""
    extra: dict[str, Any] = {
        "calibration": cal_path,
        "calibration_sha256": cal_sha256,
        "parameters": {"interp": options.interp, **parameters},
    }
    if options.superres is not None or options.refocus:
        extra["products"] = {"superres": options.superres, "refocus": list(options.refocus)}
    return extra


def as_tuple(values: Sequence[float] | None, name: str = "refocus") -> tuple[float, ...]:
    """A sequence of distances as a tuple of floats (``None``: empty), or an
    :class:`~lfcam.InputError` naming argument ``name``."""
    if values is None:
        return ()
    try:
        if isinstance(values, (str, bytes)):
            raise TypeError
        return tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a sequence of distances, got {values!r}") from None
