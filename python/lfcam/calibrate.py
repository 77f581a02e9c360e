"""Calibration (DESIGN.md section 4): a folder of captures -> a :class:`Calibration`.

Folder layout::

    CAL_DIR/pattern.png            the digital pattern shown on the board
    CAL_DIR/white/*                captures of a uniform white target
    CAL_DIR/board_<distance>m/*    pattern captures at that distance (metres)
    CAL_DIR/camera.toml            optional: grid, reference, z_c, pattern_pitch, bayer

Steps: the layout of the views (white captures), photometric gains, one warp map
per view (board captures at the reference distance ``Z_b``), the depth model
(``o_i`` and ``Z_c`` from the other distances and/or the optical centres) and a
report.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .calibration import Calibration
from .errors import CalibrationError, InputError
from .flow import FlowParams, dis_flow, prepare
from .geometric import coarse_homography, register_view, remap
from .io import (
    BAYER_PATTERNS,
    read_image,
    read_raw,
    to_float,
    write_image_atomic,
    write_text_atomic,
)
from .layout import find_layout
from .photometric import white_gains

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["CalibrationInputs", "CalibrationRun", "calibrate", "find_inputs", "run_calibration"]

_IMAGE_EXT = {".png", ".tif", ".tiff", ".jpg", ".jpeg"}
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
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_EXT)


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
        raise InputError(f"{wdir}: no images (PNG, TIFF or JPEG) of the white target")
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


class _Reader:
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


def _mean(reader: _Reader, paths: list[Path]) -> np.ndarray:
    acc = None
    for p in paths:
        img = reader(p)
        acc = img.astype(np.float64) if acc is None else acc + img
    assert acc is not None
    return (acc / len(paths)).astype(np.float32)


def _crop(img: np.ndarray, rect: np.ndarray) -> np.ndarray:
    x0, y0, w, h = (int(v) for v in rect)
    return img[y0 : y0 + h, x0 : x0 + w]


def _apply_gains(img: np.ndarray, gains: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(gains > 0, img * gains, np.nan).astype(np.float32)


def invert_map(warp: np.ndarray, mask: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The rectified position ``(u, v)`` whose warp is ``xy`` (Newton on the map).

    Returns NaN if ``xy`` is not inside the masked map.
    """
    ok = mask & np.isfinite(warp).all(-1)
    if not ok.any():
        return np.full(2, np.nan)
    vv, uu = np.nonzero(ok)
    d = np.linalg.norm(warp[vv, uu] - xy, axis=1)
    k = int(np.argmin(d))
    u, v = float(uu[k]), float(vv[k])
    H, W = warp.shape[:2]
    for _ in range(20):
        iu, iv = min(max(int(u), 1), W - 2), min(max(int(v), 1), H - 2)
        J = np.column_stack(
            [
                (warp[iv, iu + 1] - warp[iv, iu - 1]) / 2.0,
                (warp[iv + 1, iu] - warp[iv - 1, iu]) / 2.0,
            ]
        ).astype(np.float64)
        cur = remap(warp, np.array([[[u, v]]], np.float32))[0, 0].astype(np.float64)
        if not np.isfinite(cur).all() or not np.isfinite(J).all():
            return np.full(2, np.nan)
        step = np.linalg.solve(J, xy - cur)
        u, v = u + step[0], v + step[1]
        if np.abs(step).max() < 1e-4:
            break
    return np.array([u, v])


def fit_depth_model(
    parallax: dict[float, np.ndarray], z_b: float, centres_rect: np.ndarray | None = None
) -> dict[str, Any]:
    """Least-squares ``o_i`` and ``Z_c`` from measured parallax (DESIGN.md section 4).

    ``parallax[Z_k]`` is ``(N, 2)``: view i's board shift at distance ``Z_k`` in the
    reference distance's rectified frame, ``P_ik = o_i s_k`` with
    ``s_k = (Z_k - Z_b) / (Z_k - Z_c)``. ``centres_rect`` (``d_i = o_i Z_b / Z_c``)
    adds equations (needed with only two distances).

    A one-dimensional problem in ``Z_c`` (``o_i`` is linear given it), solved by a
    dense scan and golden-section refinement; the system is ``2N x K``, far too
    small for a sparse or iterative solver.
    """
    zs = np.array(sorted(parallax))
    P = np.stack([parallax[z] for z in zs])  # (K, N, 2)

    def solve(z_c: float) -> tuple[float, np.ndarray]:
        s = (zs - z_b) / (zs - z_c)  # (K,)
        num = np.einsum("k,kni->ni", s, P)
        den = float(s @ s)
        if centres_rect is not None:
            r = z_b / z_c
            num = num + r * centres_rect
            den = den + r * r
        o = num / den
        res = (P - s[:, None, None] * o[None]) ** 2
        cost = float(res.sum())
        if centres_rect is not None:
            cost += float(((centres_rect - o * z_b / z_c) ** 2).sum())
        return cost, o

    hi = min(min(zs), z_b) * 0.98
    grid = np.linspace(hi * 0.01, hi, 400)
    costs = [solve(z)[0] for z in grid]
    k = int(np.argmin(costs))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    g = (math.sqrt(5) - 1) / 2
    for _ in range(80):
        c, d = b - g * (b - a), a + g * (b - a)
        if solve(c)[0] < solve(d)[0]:
            b = d
        else:
            a = c
    z_c = (a + b) / 2
    _, o = solve(z_c)
    s = (zs - z_b) / (zs - z_c)
    resid = P - s[:, None, None] * o[None]
    return {
        "z_c": float(z_c),
        "offsets": o,
        "s": {f"{z:g}": float(v) for z, v in zip(zs, s)},
        "residual_rms_px": float(np.sqrt((resid**2).mean())),
        "residual_max_px": float(np.abs(resid).max()),
    }


def _measure_parallax(
    views: np.ndarray,
    masks: np.ndarray,
    ref: int,
    params: FlowParams,
    init: dict[int, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Median flow from the reference to each view (rectified board images).

    ``init`` maps a view index to an expected shift ``(2,)`` that starts its flow
    (and restricts the measurement to those views; the others get NaN).
    Returns the parallax ``(N, 2)``, the valid fraction ``(N,)`` and the flows'
    robust spread ``(N,)``.
    """
    N = views.shape[0]
    a = prepare(views[ref])
    grid = np.stack(np.meshgrid(np.arange(a.shape[1]), np.arange(a.shape[0])), -1).astype(
        np.float32
    )
    out = np.full((N, 2), np.nan) if init else np.zeros((N, 2))
    cover = np.zeros(N)
    spread = np.zeros(N)
    for i in range(N):
        if i == ref:
            out[i] = 0.0
            cover[i] = 1.0
            continue
        if init and i not in init:
            continue
        both = (
            masks[i] & masks[ref] & np.isfinite(views[i]).all(-1) & np.isfinite(views[ref]).all(-1)
        )
        both = cv2.erode(both.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        start = None
        if init:
            start = np.broadcast_to(np.asarray(init[i], np.float32), (*a.shape[:2], 2))
        v = prepare(views[i])
        f = dis_flow(a, v, params, init=start)
        b = dis_flow(v, a, params, init=None if start is None else -start)
        # Forward-backward check: follow the flow and come back.
        back = remap(b, grid + f)
        fb = np.linalg.norm(f + back, axis=-1)
        # The board must land inside view i's mask too.
        land = remap(masks[i].astype(np.float32), grid + f)
        good = both & (fb < 0.5) & (land > 0.99)
        cover[i] = good.sum() / max(both.sum(), 1)
        if good.sum() < 500:
            out[i] = np.nan
            continue
        out[i] = np.median(f[good], axis=0)
        spread[i] = float(np.median(np.abs(f[good] - out[i]))) * 1.4826
    return out, cover, spread


#: A view's board shift may differ from the lenslet lattice's prediction by this
#: much (px, or this share of the largest shift, whichever is larger) before it is
#: measured again from the prediction (:func:`_lattice_check`).
LATTICE_TOLERANCE_PX = 3.0
LATTICE_TOLERANCE_REL = 0.1


def _lattice_check(P: np.ndarray, grid: tuple[int, int], ref: int) -> tuple[np.ndarray, np.ndarray]:
    """Views whose measured board shift breaks the lenslet lattice.

    A fronto-parallel board shifts view i by ``o_i s``, and on a lenslet grid ``o_i``
    is nearly affine in the view's column and row: ``P_i ~ A dc_i + B dr_i``. Fits the
    two 2-vectors by least squares, dropping the worst view while it is off by more
    than the tolerance (flow on a large shift can lock onto a wrong match: the
    full-size camera's far corner view at 0.7 m measured (-2, -51) px instead of
    (52, -19), and the whole depth model went wrong). Returns the prediction
    ``(N, 2)`` and the outliers ``(N,)`` (all False with too few views to tell).
    """
    R, C = grid
    rows, cols = np.divmod(np.arange(R * C), C)
    X = np.column_stack([cols - cols[ref], rows - rows[ref]]).astype(np.float64)
    finite = np.isfinite(P).all(1)
    inl = finite & (np.arange(len(P)) != ref)
    pred = np.zeros_like(P)  # too few views to fit: no prediction, no outliers
    tol = max(LATTICE_TOLERANCE_PX, LATTICE_TOLERANCE_REL * float(np.nanmax(np.abs(P))))
    while inl.sum() >= 4:
        coef, *_ = np.linalg.lstsq(X[inl], P[inl], rcond=None)
        pred = X @ coef
        err = np.where(finite, np.linalg.norm(P - pred, axis=1), np.inf)
        err[ref] = 0.0
        worst = int(np.argmax(np.where(inl, err, -1.0)))
        if err[worst] <= tol:
            out = ~inl & (err > tol)
            out[ref] = False
            return pred, out
        inl[worst] = False
    return pred, np.zeros(len(P), bool)


@dataclass
class CalibrationRun:
    """A calibration and the intermediate images its report picture shows."""

    calibration: Calibration
    white: np.ndarray  # mean white capture, float RGB
    residuals: list[np.ndarray]  # per view photometric residual in the rectified frame

    def save(self, path: str | os.PathLike[str]) -> dict[str, Path]:
        """Write ``X.lfcal``, ``X.report.json`` and ``X.report.png``; each atomically.

        The ``.lfcal`` is written last, so its presence means a complete run.
        """
        from .report import calibration_figure

        out = Path(path)
        if out.suffix != ".lfcal":
            out = out.with_name(out.name + ".lfcal")
        if not out.parent.is_dir():
            raise InputError(f"{out}: folder {out.parent} does not exist")
        stem = out.with_suffix("")
        paths = {
            "report_json": stem.with_name(stem.name + ".report.json"),
            "report_png": stem.with_name(stem.name + ".report.png"),
            "calibration": out,
        }
        write_text_atomic(paths["report_json"], json.dumps(self.calibration.report, indent=2))
        fig = calibration_figure(self.calibration, self.white, self.residuals)
        write_image_atomic(paths["report_png"], fig)
        self.calibration.save(out)
        return paths


def calibrate(cal_dir: str | os.PathLike[str], **kwargs: Any) -> Calibration:
    """Calibrate a camera from a folder of captures (DESIGN.md section 4).

    Parameters
    ----------
    cal_dir : path
        The calibration folder (see the module docstring for its layout).
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
    return run_calibration(cal_dir, **kwargs).calibration


def run_calibration(
    cal_dir: str | os.PathLike[str],
    *,
    grid: tuple[int, int] | None = None,
    reference: tuple[int, int] | None = None,
    reference_distance: float | None = None,
    scale: float | None = None,
    z_c: float | None = None,
    pattern_pitch: float | None = None,
    bayer: str | None = None,
    flow: FlowParams | None = None,
    threads: int = 2,
    progress: Callable[[str], None] | None = None,
) -> CalibrationRun:
    """:func:`calibrate`, also returning what the report picture shows."""
    say = progress or (lambda _msg: None)
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    inputs = find_inputs(cal_dir)
    st = inputs.settings
    grid = tuple(grid or st.get("grid") or (3, 4))  # type: ignore[assignment]
    if (
        len(grid) != 2
        or not all(isinstance(g, int) and g >= 1 for g in grid)
        or grid[0] * grid[1] < 2
    ):
        raise InputError(f"grid: expected two positive integers (R, C), got {grid!r}")
    R, C = grid
    N = R * C
    reference = tuple(reference or st.get("reference") or ((R - 1) // 2, (C - 1) // 2))  # type: ignore[assignment]
    if len(reference) != 2 or not (0 <= reference[0] < R and 0 <= reference[1] < C):
        raise InputError(f"reference: {reference!r} is not a view of the {R}x{C} grid")
    ref = reference[0] * C + reference[1]
    bayer = bayer or st.get("bayer")
    if bayer is not None and bayer not in BAYER_PATTERNS:
        raise InputError(f"bayer: expected one of {', '.join(BAYER_PATTERNS)}, got {bayer!r}")
    z_c = z_c if z_c is not None else st.get("z_c")
    pattern_pitch = pattern_pitch if pattern_pitch is not None else st.get("pattern_pitch")
    distances = sorted(inputs.boards)
    z_b = reference_distance if reference_distance is not None else st.get("reference_distance")
    if z_b is None:
        z_b = min(distances, key=lambda z: (abs(z - 1.0), z))
    if z_b not in inputs.boards:
        raise InputError(
            f"reference_distance: no board folder for {z_b:g} m"
            f" (have {', '.join(f'{z:g}' for z in distances)})"
        )
    if z_c is not None and not (0 < z_c < z_b):
        raise InputError(f"z_c: must be between 0 and Z_b = {z_b:g} m, got {z_c!r}")
    params = flow or FlowParams()
    reader = _Reader(bayer)

    # 1-2. Layout and photometric gains --------------------------------------
    t0 = time.perf_counter()
    say("layout and gains (white captures)")
    white = _mean(reader, inputs.white)
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
        scale = float(np.round(np.sqrt(abs(np.linalg.det(J))) * 8) / 8) or 0.125
    if not (0.05 <= scale <= 8):
        raise InputError(f"scale: expected 0.05 .. 8 rectified px per pattern px, got {scale!r}")
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
            params=params,
        )

    with ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
        regs = list(ex.map(one, range(N)))
    warps = np.stack([r.warp for r in regs]).astype(np.float32)
    masks = np.stack([r.mask for r in regs])
    warps[~masks] = np.nan
    timings["warp_maps"] = time.perf_counter() - t0
    residual_rms = []
    for i, r in enumerate(regs):
        if masks[i].mean() < 0.02:
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
    fit_info: dict[str, Any] = {}
    for z in distances:
        if z == z_b:
            continue
        say(f"parallax at {z:g} m")
        mean = np.mean([_apply_gains(reader(p), gains) for p in inputs.boards[z]], axis=0)
        views = np.stack([remap(_crop(mean, layout.crops[i]), warps[i]) for i in range(N)])
        views[~masks] = np.nan
        P, cover, spread = _measure_parallax(views, masks, ref, params)
        pred, wrong = _lattice_check(P, grid, ref)
        if wrong.any():
            redo = {int(i): pred[i] for i in np.nonzero(wrong)[0]}
            say(f"parallax at {z:g} m: measuring views {sorted(redo)} again from the lattice")
            P2, cover2, spread2 = _measure_parallax(views, masks, ref, params, init=redo)
            for i in redo:
                P[i], cover[i], spread[i] = P2[i], cover2[i], spread2[i]
            _, still = _lattice_check(P, grid, ref)
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
        parallax[z] = P
        fit_info[f"{z:g}"] = {
            "parallax_px": P.tolist(),
            "coverage": cover.tolist(),
            "spread_px": spread.tolist(),
        }
    use_centres = len(parallax) == 1 and np.isfinite(d).all()
    if len(parallax) >= 2 or use_centres:
        fit = fit_depth_model(parallax, z_b, d if use_centres else None)
        z_c_est, offsets, metric = fit["z_c"], fit["offsets"], True
        route = "distances" + (" + optical centres" if use_centres else "")
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
        | {"route": route, "optical_centre_route": agree, "parallax": fit_info},
        "inputs": {
            "folder": str(inputs.root),
            "white": [p.name for p in inputs.white],
            "boards": {f"{z:g}": [p.name for p in ps] for z, ps in inputs.boards.items()},
            "bayer": bayer,
        },
        "timings_s": timings,
    }
    report["depth_model"] = json.loads(json.dumps(report["depth_model"], default=float))
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
