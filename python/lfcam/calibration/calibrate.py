"""Calibration: a folder of captures -> a :class:`~lfcam.Calibration`.

Steps (docs/design.md, "Calibration pipeline"): the layout of the views and the photometric
gains (white captures), one warp map per view (board captures at the reference
distance ``Z_b``), the depth model (``o_i`` and ``Z_c`` from the other distances
and/or the optical centres) and a report. The folder layout is in
:mod:`lfcam.calibration.inputs`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import CalibrationError, InputError, LfcamError
from ..io import BAYER_PATTERNS, read_image, to_float, write_image_atomic, write_text_atomic
from ..kernels.flow import FlowParams
from ..kernels.warp import identity_grid, remap
from .file import Calibration
from .geometric import coarse_homography, register_view
from .inputs import CalibrationInputs, CaptureReader, find_inputs, mean_capture
from .layout import find_layout
from .parallax import (
    MAX_BOARD_RMS_PX,
    MAX_TILT_DEG,
    MAX_TILT_DEPTH_CHANGE,
    ParallaxMeasurement,
    depth_change,
    fit_board_poses,
    fit_depth_model,
    invert_map,
    lattice_check,
    less_reference,
    measure_parallax,
    tilt_degrees,
)
from .photometric import white_gains
from .report import calibration_figure
from .report_page import report_html

__all__ = ["CalibrationParams", "CalibrationRun", "calibrate", "run_calibration"]

#: The lenslet grid when neither the arguments nor ``camera.toml`` give one.
DEFAULT_GRID = (3, 4)
#: A view whose warp map covers less than this share of its frame fails calibration.
MIN_VIEW_COVERAGE = 0.02
#: Rectified px per pattern px is the measured magnification rounded to a multiple of
#: 1 / SCALE_STEPS.
SCALE_STEPS = 8
#: The range of rectified px per pattern px that calibration accepts.
SCALE_RANGE = (0.05, 8.0)


def _pair(value: Any, name: str) -> tuple[int, int] | None:
    if value is None:
        return None
    if (
        isinstance(value, (str, bytes))
        or not hasattr(value, "__len__")
        or len(value) != 2
        or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in value)
    ):
        raise InputError(f"{name}: expected two integers, got {value!r}")
    return int(value[0]), int(value[1])


def _positive(value: Any, name: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise InputError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{name}: expected a finite number > 0, got {value!r}")
    return v


@dataclass(frozen=True)
class CalibrationParams:
    """What calibration is told about the camera; None: ``camera.toml``, else a default.

    Each field may also come from the calibration folder's ``camera.toml`` (same name);
    a value given here wins.
    """

    #: Lenslet rows and columns (R, C); default (3, 4).
    grid: tuple[int, int] | None = None
    #: Reference view (row, col); default the view nearest the array centre,
    #: ``((R - 1) // 2, (C - 1) // 2)``.
    reference: tuple[int, int] | None = None
    #: ``Z_b``, metres: the board distance whose rectified frame products are given in;
    #: default the distance nearest 1 m.
    reference_distance: float | None = None
    #: Rectified px per pattern px; default the measured magnification (a rectified
    #: pixel about one raw pixel), rounded to a multiple of 1/8.
    scale: float | None = None
    #: ``Z_c``, metres, if known from the optics (``f D / (D - f)``): metric depth from
    #: one board distance.
    z_c: float | None = None
    #: Metres per pattern pixel on the board (makes X and Y metric).
    pattern_pitch: float | None = None
    #: Bayer mosaic of the raw captures (RGGB, BGGR, GRBG, GBRG); None: not a mosaic.
    bayer: str | None = None
    #: Optical-flow parameters of the registration and the parallax measurement.
    flow: FlowParams = field(default_factory=FlowParams)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "grid", _pair(self.grid, "grid"))
        set_(self, "reference", _pair(self.reference, "reference"))
        for name in ("reference_distance", "scale", "z_c", "pattern_pitch"):
            set_(self, name, _positive(getattr(self, name), name))
        if self.grid is not None and (min(self.grid) < 1 or self.grid[0] * self.grid[1] < 2):
            raise InputError(f"grid: expected two positive integers (R, C), got {self.grid!r}")
        if self.bayer is not None and self.bayer not in BAYER_PATTERNS:
            raise InputError(
                f"bayer: expected one of {', '.join(BAYER_PATTERNS)}, got {self.bayer!r}"
            )
        if not isinstance(self.flow, FlowParams):
            raise InputError(f"flow: expected a FlowParams, got {type(self.flow).__name__}")
        if self.scale is not None and not (SCALE_RANGE[0] <= self.scale <= SCALE_RANGE[1]):
            raise InputError(
                f"scale: expected {SCALE_RANGE[0]} .. {SCALE_RANGE[1]} rectified px per"
                f" pattern px, got {self.scale!r}"
            )

    @classmethod
    def fields(cls) -> tuple[str, ...]:
        """The names of the fields (the keys ``camera.toml`` may set, but ``flow``)."""
        return tuple(f.name for f in dataclasses.fields(cls))

    def replace(self, **changes: Any) -> CalibrationParams:
        """A copy with ``changes``; an unknown name is an :class:`~lfcam.InputError`."""
        unknown = sorted(set(changes) - set(self.fields()))
        if unknown:
            raise InputError(
                f"{unknown[0]}: not a calibration parameter (known: {', '.join(self.fields())})"
            )
        return dataclasses.replace(self, **changes)

    def merged(self, settings: dict[str, Any], where: str) -> CalibrationParams:
        """These parameters with the fields they leave None taken from ``settings``
        (``camera.toml``'s table); errors name ``where`` and the key."""
        free = {k: v for k, v in settings.items() if getattr(self, k, None) is None}
        try:
            return self.replace(**free)
        except InputError as e:
            raise InputError(f"{where}: {e}") from None


def _crop(img: np.ndarray, rect: np.ndarray) -> np.ndarray:
    x0, y0, w, h = (int(v) for v in rect)
    return img[y0 : y0 + h, x0 : x0 + w]


def _apply_gains(img: np.ndarray, gains: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(gains > 0, img * gains, np.nan).astype(np.float32)


@dataclass
class CalibrationRun:
    """A calibration and the intermediate images its report picture shows."""

    calibration: Calibration
    white: np.ndarray  # mean white capture, float RGB
    residuals: list[np.ndarray]  # per view photometric residual in the rectified frame

    def save(self, path: str | os.PathLike[str]) -> dict[str, Path]:
        """Write ``X.lfcal``, ``X.report.json``, ``X.report.png`` and ``X.report.html``
        (the page a person reads: :func:`lfcam.calibration.report_page.report_html`);
        each atomically.

        The ``.lfcal`` is written last, so its presence means a complete run.
        """
        out = Path(path)
        if out.suffix != ".lfcal":
            out = out.with_name(out.name + ".lfcal")
        if not out.parent.is_dir():
            raise InputError(f"{out}: folder {out.parent} does not exist")
        stem = out.with_suffix("")
        paths = {
            "report_json": stem.with_name(stem.name + ".report.json"),
            "report_png": stem.with_name(stem.name + ".report.png"),
            "report_html": stem.with_name(stem.name + ".report.html"),
            "calibration": out,
        }
        write_text_atomic(paths["report_json"], json.dumps(self.calibration.report, indent=2))
        fig = calibration_figure(self.calibration, self.white, self.residuals)
        write_image_atomic(paths["report_png"], fig)
        write_text_atomic(
            paths["report_html"], report_html(self.calibration, fig, title=f"{out.name}: report")
        )
        self.calibration.save(out)
        return paths


def _finite_json(value: Any) -> Any:
    """A JSON value with NaN and infinities as None (a standard error the fit could not
    give, say)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, list):
        return [_finite_json(v) for v in value]
    if isinstance(value, dict):
        return {k: _finite_json(v) for k, v in value.items()}
    return value


def _fit_with_poses(
    start: dict[str, Any],
    measured: dict[float, ParallaxMeasurement],
    z_b: float,
    ref: int,
    centre: np.ndarray,
    centres_rect: np.ndarray | None,
    rect_pitch: float | None,
    shape: tuple[int, int],
    folders: dict[float, Path],
) -> dict[str, Any]:
    """The depth model with every board's tilt relative to the reference board
    (:func:`fit_board_poses`), starting from the fronto-parallel fit ``start``.

    Raises CalibrationError naming the board's folder for a tilt beyond the model or
    captures that disagree with it.
    """
    try:
        poses = fit_board_poses(
            measured, z_b, ref, centre, start, centres_rect=centres_rect, rect_pitch=rect_pitch
        )
    except LfcamError as e:
        raise CalibrationError(
            f"{folders[z_b].parent}: the depth model with board poses does not fit ({e})"
        ) from None
    z_c = float(poses["z_c"])
    boards: dict[str, Any] = {}
    gradients: dict[float, np.ndarray] = {}
    gradients_se: dict[float, np.ndarray] = {}
    rms: dict[float, float] = {}
    for k, z in enumerate(poses["zs"]):
        gradients[z] = np.asarray(poses["gradients"][k])
        gradients_se[z] = np.asarray(poses["gradients_se"][k])
        rms[z] = float(poses["board_rms_px"][k])
    worst = max(rms, key=lambda z: rms[z])
    if rms[worst] > MAX_BOARD_RMS_PX:
        raise CalibrationError(
            f"{folders[worst]}: the board's parallax misses the depth model by"
            f" {rms[worst]:.2f} px RMS (at most {MAX_BOARD_RMS_PX:g}): these captures"
            " disagree with the other distances' (is the distance in the folder name"
            " right, and did the board stay still and flat?)"
        )
    for k, z in enumerate(poses["zs"]):
        change = depth_change(gradients[z], centre, shape)
        slope = None if rect_pitch is None else tilt_degrees(gradients[z], z_b, z_c, rect_pitch)
        too_much = (
            change > MAX_TILT_DEPTH_CHANGE if slope is None else math.hypot(*slope) > MAX_TILT_DEG
        )
        if too_much:
            what = (
                f"its depth changes by {100 * change:.1f}% across the frame (at most"
                f" {100 * MAX_TILT_DEPTH_CHANGE:g}%)"
                if slope is None
                else f"{math.hypot(*slope):.1f} degrees (at most {MAX_TILT_DEG:g})"
            )
            raise CalibrationError(
                f"{folders[z]}: the board is tilted beyond what the depth model handles:"
                f" {what}; turn it to face the camera"
            )
        boards[f"{z:g}"] = {
            "folder": str(folders[z]),
            "relative_to": f"{z_b:g}",
            "gradient_per_px": gradients[z].tolist(),
            "gradient_se_per_px": gradients_se[z].tolist(),
            "slope_deg": slope,
            "depth_change_across_frame": change,
            "residual_rms_px": rms[z],
            "cells_downweighted": float(poses["board_downweighted"][k]),
        }
    zs = np.array(poses["zs"])
    s = (zs - z_b) / (zs - z_c)
    fit = {
        "z_c": z_c,
        "z_c_se": float(poses["z_c_se"]),
        "offsets": np.asarray(poses["offsets"]),
        "offsets_se_px": np.asarray(poses["offsets_se"]).tolist(),
        "s": {f"{z:g}": float(v) for z, v in zip(zs, s)},
        "residual_rms_px": float(poses["rms_px"]),
        "iterations": int(poses["iterations"]),
        "boards": boards,
        "fronto_parallel_fit": {
            "z_c": float(start["z_c"]),
            "residual_rms_px": start["residual_rms_px"],
        },
    }
    return fit


def calibrate(
    cal_dir: str | os.PathLike[str],
    params: CalibrationParams | None = None,
    *,
    threads: int = 2,
    progress: Callable[[str], None] | None = None,
    **changes: Any,
) -> Calibration:
    """Calibrate a camera from a folder of captures (docs/design.md, "Calibration pipeline").

    Parameters
    ----------
    cal_dir : path
        The calibration folder (its layout: :mod:`lfcam.calibration.inputs`).
    params : CalibrationParams, optional
        What is known of the camera; fields left None come from the folder's
        ``camera.toml``, else their defaults.
    **changes
        Fields of :class:`CalibrationParams` given one by one (override ``params``):
    grid : (int, int), optional
        Lenslet rows and columns; default from ``camera.toml``, else (3, 4).
    reference : (int, int), optional
        Reference view (row, col); default from ``camera.toml``, else the view
        nearest the array centre, ``((R - 1) // 2, (C - 1) // 2)``.
    reference_distance : float, optional
        ``Z_b``: the board distance whose rectified frame products are given in;
        default the distance nearest 1 m.
    scale : float, optional
        Rectified px per pattern px; default: a rectified pixel about one raw
        pixel (the measured magnification, rounded to a multiple of 1/8).
    z_c : float, optional
        ``Z_c`` in metres, if known from the optics (``f D / (D - f)``); needed
        for metric depth from one board distance.
    pattern_pitch : float, optional
        Metres per pattern pixel on the board (makes X and Y metric).
    bayer : str, optional
        Bayer mosaic of the raw captures (RGGB, BGGR, GRBG, GBRG).
    flow : FlowParams, optional
        Optical-flow parameters.
    threads : int, optional
        Views registered concurrently (default 2).
    progress : callable, optional
        Called with a short description as each step starts.

    Returns
    -------
    Calibration
        Validated; ``report`` holds every measured number. Save it with
        ``cal.save("camera.lfcal")``.

    Raises
    ------
    lfcam.InputError
        A missing or malformed file or folder (named).
    lfcam.CalibrationError
        Captures that do not calibrate (named), e.g. no R x C circles, the
        pattern not found, flow not converging.

    Examples
    --------
    >>> cal = lfcam.calibrate("sim/calibration")     # doctest: +SKIP
    >>> cal.save("camera.lfcal")                      # doctest: +SKIP
    """
    return run_calibration(
        cal_dir, params, threads=threads, progress=progress, **changes
    ).calibration


def run_calibration(
    cal_dir: str | os.PathLike[str],
    params: CalibrationParams | None = None,
    *,
    threads: int = 2,
    progress: Callable[[str], None] | None = None,
    inputs: CalibrationInputs | None = None,
    **changes: Any,
) -> CalibrationRun:
    """:func:`calibrate`, also returning what the report picture shows. ``inputs``: the
    folder's files already found (a zoom setting's, :func:`find_settings`)."""
    say = progress or (lambda _msg: None)
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    p = (params or CalibrationParams()).replace(**changes)
    inputs = inputs if inputs is not None else find_inputs(cal_dir)
    p = p.merged(inputs.settings, str(inputs.root / "camera.toml"))
    grid = p.grid or DEFAULT_GRID
    R, C = grid
    N = R * C
    reference = p.reference or ((R - 1) // 2, (C - 1) // 2)
    if not (0 <= reference[0] < R and 0 <= reference[1] < C):
        raise InputError(f"reference: {reference!r} is not a view of the {R}x{C} grid")
    ref = reference[0] * C + reference[1]
    bayer, z_c, pattern_pitch, scale = p.bayer, p.z_c, p.pattern_pitch, p.scale
    distances = sorted(inputs.boards)
    z_b = p.reference_distance
    if z_b is None:
        z_b = min(distances, key=lambda z: (abs(z - 1.0), z))
    if z_b not in inputs.boards:
        raise InputError(
            f"reference_distance: no board folder for {z_b:g} m"
            f" (have {', '.join(f'{z:g}' for z in distances)})"
        )
    if z_c is not None and not (0 < z_c < z_b):
        raise InputError(f"z_c: must be between 0 and Z_b = {z_b:g} m, got {z_c!r}")
    flow = p.flow
    reader = CaptureReader(bayer)

    # 1-2. Layout and photometric gains --------------------------------------
    t0 = time.perf_counter()
    say("layout and gains (white captures)")
    white = mean_capture(reader, inputs.white)
    layout = find_layout(white, grid, name=str(inputs.root / "white"))
    gains = white_gains(white, layout.lit)
    timings["layout_and_gains"] = time.perf_counter() - t0

    # The pattern and the rectified frame -------------------------------------
    pattern = read_image(inputs.pattern)
    pattern = to_float(pattern)
    if pattern.ndim == 3:
        pattern = pattern.mean(axis=2)
    H_pat, W_pat = pattern.shape
    boards_b = [_apply_gains(reader(p), gains) for p in inputs.boards[z_b]]
    folder_b = inputs.boards[z_b][0].parent
    t0 = time.perf_counter()
    if scale is None:
        say("rectified scale")
        Hm = coarse_homography(
            pattern,
            np.mean([_crop(b, layout.crops[ref]) for b in boards_b], axis=0),
            name=f"{folder_b}: view {reference}",
        )
        J = Hm[:2, :2] / Hm[2, 2]  # near-affine: raw px per pattern px
        magnification = float(np.sqrt(abs(np.linalg.det(J))))
        scale = float(np.round(magnification * SCALE_STEPS) / SCALE_STEPS) or 1 / SCALE_STEPS
        if not (SCALE_RANGE[0] <= scale <= SCALE_RANGE[1]):
            raise CalibrationError(
                f"{folder_b}: the measured scale, {magnification:.3g} raw px per pattern px,"
                f" is outside {SCALE_RANGE[0]} .. {SCALE_RANGE[1]}"
            )
    H_rect, W_rect = round(H_pat * scale), round(W_pat * scale)
    if scale == 1.0:
        pat_rect = pattern
    else:
        interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
        pat_rect = cv2.resize(pattern, (W_rect, H_rect), interpolation=interp)

    # 3. Geometric: one warp map per view ----------------------------------------
    say(f"warp maps ({N} views, {len(boards_b)} captures at {z_b:g} m)")

    def one(i: int) -> Any:
        r, c = divmod(i, C)
        return register_view(
            pat_rect,
            [_crop(b, layout.crops[i]) for b in boards_b],
            name=f"{folder_b}: view ({r}, {c})",
            params=flow,
        )

    with ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
        regs = list(ex.map(one, range(N)))
    warps = np.stack([r.warp for r in regs]).astype(np.float32)
    masks = np.stack([r.mask for r in regs])
    warps[~masks] = np.nan
    timings["warp_maps"] = time.perf_counter() - t0
    residual_rms = []
    for i, r in enumerate(regs):
        if masks[i].mean() < MIN_VIEW_COVERAGE:
            raise CalibrationError(
                f"{folder_b}: view {divmod(i, C)} sees almost none of the pattern"
            )
        residual_rms.append(float(np.sqrt(np.mean(r.residual[masks[i]] ** 2))))

    # 4. Depth model -------------------------------------------------------------------
    t0 = time.perf_counter()
    say("depth model")
    centres_rect = np.full((N, 2), np.nan)
    for i in range(N):
        centres_rect[i] = invert_map(warps[i], masks[i], layout.centres[i] - layout.crops[i, :2])
    d = centres_rect - centres_rect[ref]
    parallax: dict[float, np.ndarray] = {}
    measured: dict[float, ParallaxMeasurement] = {}
    fit_info: dict[str, Any] = {}
    rect_grid = identity_grid(H_rect, W_rect)
    zero = None
    if len(distances) > 1:
        # The residual parallax of the reference board (the warp maps' registration
        # error), which every other board shows too and which is taken off theirs.
        say(f"residual parallax at {z_b:g} m")
        mean = np.mean(boards_b, axis=0)
        views = np.stack([remap(_crop(mean, layout.crops[i]), warps[i]) for i in range(N)])
        views[~masks] = np.nan
        zero = measure_parallax(views, masks, ref, flow)
    for z in distances:
        if z == z_b:
            continue
        say(f"parallax at {z:g} m")
        mean = np.mean([_apply_gains(reader(p), gains) for p in inputs.boards[z]], axis=0)
        crops = [_crop(mean, layout.crops[i]) for i in range(N)]
        views = np.stack([remap(crops[i], warps[i]) for i in range(N)])
        views[~masks] = np.nan

        def resample(
            i: int, shift: np.ndarray, crops: list[np.ndarray] = crops
        ) -> tuple[np.ndarray, np.ndarray]:
            # View i at p + shift: its warp map moved, one interpolation from the crop.
            moved = remap(warps[i], rect_grid + shift)
            return remap(crops[i], moved), np.isfinite(moved).all(-1)

        meas = measure_parallax(views, masks, ref, flow, resample=resample)
        P, cover, spread = meas.shift, meas.coverage, meas.spread
        pred, wrong = lattice_check(P, grid, ref)
        if wrong.any():
            redo = {int(i): pred[i] for i in np.nonzero(wrong)[0]}
            say(f"parallax at {z:g} m: measuring views {sorted(redo)} again from the lattice")
            again = measure_parallax(views, masks, ref, flow, init=redo, resample=resample)
            for i in redo:
                P[i], cover[i], spread[i] = again.shift[i], again.coverage[i], again.spread[i]
                if i in again.cells:
                    meas.cells[i] = again.cells[i]
            _, still = lattice_check(P, grid, ref)
            if still.any():
                bad = [divmod(int(i), C) for i in np.nonzero(still)[0]]
                raise CalibrationError(
                    f"{inputs.boards[z][0].parent}: the board's shift in views {bad} does"
                    " not fit the lenslet grid (is the board flat, fronto-parallel and"
                    " filling every view?)"
                )
        if np.isnan(P).any():
            bad = [divmod(int(i), C) for i in np.nonzero(np.isnan(P).any(1))[0]]
            raise CalibrationError(
                f"{inputs.boards[z][0].parent}: cannot measure the board's parallax in views {bad}"
            )
        if zero is not None:
            meas = less_reference(meas, zero)
            P = meas.shift
        parallax[z] = P
        measured[z] = meas
        fit_info[f"{z:g}"] = {
            "parallax_px": P.tolist(),
            "coverage": cover.tolist(),
            "spread_px": spread.tolist(),
        }
    use_centres = len(parallax) == 1 and np.isfinite(d).all()
    if len(parallax) >= 2 or use_centres:
        fit = fit_depth_model(parallax, z_b, d if use_centres else None)
        rect_pitch = pattern_pitch / scale if pattern_pitch is not None else None
        centre = centres_rect[ref]
        if not np.isfinite(centre).all():
            centre = np.array([(W_rect - 1) / 2, (H_rect - 1) / 2])
        say("board poses")
        fit = _fit_with_poses(
            fit,
            measured,
            z_b,
            ref,
            centre,
            d if use_centres else None,
            rect_pitch,
            (H_rect, W_rect),
            {z: inputs.boards[z][0].parent for z in distances},
        )
        z_c_est, offsets, metric = fit["z_c"], fit["offsets"], True
        route = "distances" + (" + optical centres" if use_centres else "") + " + board poses"
    elif z_c is not None:
        z_c_est, offsets, metric = float(z_c), d * float(z_c) / z_b, True
        fit = {"z_c": z_c_est}
        route = "optical centres + given Z_c"
    else:
        z_c_est, offsets, metric = float("nan"), d, False
        fit = {}
        route = "optical centres (relative depth)"
    if z_c is not None and metric and route != "optical centres + given Z_c":
        fit["z_c_given"] = float(z_c)
    offsets = np.asarray(offsets, np.float64) - np.asarray(offsets, np.float64)[ref]
    # Agreement of both routes: the optical centres predict o_i Z_b / Z_c.
    agree: dict[str, Any] = {}
    if metric and np.isfinite(d).all():
        pred = offsets * z_b / z_c_est
        nz = np.linalg.norm(d, axis=1) > 1e-9
        rel = np.linalg.norm(pred - d, axis=1)[nz] / np.linalg.norm(d, axis=1)[nz]
        agree = {
            "centres_vs_fit_rel_median": float(np.median(rel)),
            "centres_vs_fit_rel_max": float(rel.max()),
        }
    # Perpendicular component of the measured parallax (pure error).
    perp: list[float] = []
    for P in parallax.values():
        for i in range(N):
            o = offsets[i]
            n = np.linalg.norm(o)
            if i != ref and n > 1e-9:
                perp.append(float(abs(P[i, 0] * o[1] - P[i, 1] * o[0]) / n))
    timings["depth_model"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all

    coverage = [float(masks[i].mean()) for i in range(N)]
    report: dict[str, Any] = {
        "summary": {
            "views": N,
            "reference": list(reference),
            "z_b_m": z_b,
            "z_c_m": None if not metric else z_c_est,
            "depth": "metric" if metric else "relative",
            "depth_model_route": route,
            "warp_residual_rms_max": max(residual_rms),
            "parallax_fit_rms_px": fit.get("residual_rms_px"),
            "perpendicular_parallax_rms_px": float(np.sqrt(np.mean(np.square(perp))))
            if perp
            else None,
            "seconds": timings["total"],
        },
        "views": [
            {
                "index": i,
                "row_col": list(divmod(i, C)),
                "crop": [int(v) for v in layout.crops[i]],
                "centre_px": [float(v) for v in layout.centres[i]],
                "circle_radius_px": float(layout.radii[i]),
                "coverage": coverage[i],
                "photometric_residual_rms": residual_rms[i],
                "flow_iterations": regs[i].iterations,
                "last_flow_update_px": regs[i].last_update,
                "centre_rect": [float(v) for v in centres_rect[i]],
                "offset_px": [float(v) for v in offsets[i]],
            }
            for i in range(N)
        ],
        "depth_model": {k: v for k, v in fit.items() if k != "offsets"}
        | {"route": route, "optical_centre_route": agree, "parallax": fit_info}
        | ({} if zero is None else {"reference_board_parallax_px": zero.shift.tolist()}),
        "inputs": {
            "folder": str(inputs.root),
            "white": [p.name for p in inputs.white],
            "boards": {f"{z:g}": [p.name for p in ps] for z, ps in inputs.boards.items()},
            "bayer": bayer,
        },
        "timings_s": timings,
    }
    # NaN (an image-circle centre outside its warp map, a standard error the fit could
    # not give) is None in the report.
    report = _finite_json(json.loads(json.dumps(report, default=float)))
    cal = Calibration(
        grid=(R, C),
        reference=ref,
        raw_shape=(int(white.shape[0]), int(white.shape[1])),
        rect_shape=(H_rect, W_rect),
        pattern_shape=(H_pat, W_pat),
        scale=float(scale),
        crops=layout.crops,
        centres=layout.centres,
        warps=warps,
        masks=masks,
        offsets=offsets,
        z_b=float(z_b),
        z_c=float(z_c_est),
        metric=bool(metric),
        distances=np.array(distances, np.float64),
        pattern_pitch=float(pattern_pitch) if pattern_pitch is not None else float("nan"),
        gains=gains,
        bayer=bayer,
        report=report,
    )
    return CalibrationRun(cal, white, [r.residual for r in regs])
