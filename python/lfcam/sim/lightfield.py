"""Light fields made elsewhere: a grid of already-rectified views as lfcam input.

A :class:`LightField` holds R x C views of one scene taken from a regular grid of
camera positions (a camera array, a gantry, a rendered light field such as the HCI
4D benchmark's), already rectified: a scene point moves along the grid's rows and
columns only. Its views feed the same depth chain as a calibrated lfcam capture
(flow from the reference view to every view, then robust triangulation of the
parallax ``s``; docs/design.md, "Light fields from elsewhere").

Convention (HCI 4D benchmark): a larger column index means the camera sits further
right, a larger row index further down, and a scene point at reference pixel
``(x, y)`` with disparity ``d`` appears in view ``(r, c)`` at
``(x - d (c - c_ref), y - d (r - r_ref))``. The parallax vectors are therefore

    o_i = (-(c_i - c_ref), -(r_i - r_ref))   px per unit parallax,

so the triangulated parallax ``s`` *is* the disparity ``d`` in pixels per grid step
(positive nearer than the zero-parallax plane). A rig numbered the other way round
(columns growing to the left, rows growing upwards) is described with ``flip``.
"""

from __future__ import annotations

import configparser
import math
import os
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Union

import numpy as np

from ..errors import InputError
from ..io import IMAGE_EXTENSIONS, read_image, read_pfm, to_float
from ..processing import DepthParams, DepthResult, depth_from_views

__all__ = [
    "LightField",
    "RigParameters",
    "ViewSelection",
    "parse_views",
    "points_from_lightfield",
]

_HCI_NAME = re.compile(r"^input_Cam(\d+)\.png$", re.IGNORECASE)
_INT = re.compile(r"\d+")
_GT_NAME = "gt_disp_lowres.pfm"
_CFG_NAME = "parameters.cfg"

Flip = Literal["", "x", "y", "xy"]
#: A subset of views: ``"3:6,3:7"`` (rows, columns as Python slices of absolute grid
#: indices), or a pair of slices / ints / index sequences.
ViewSelection = Union[
    str, tuple[Union[slice, int, Sequence[int]], Union[slice, int, Sequence[int]]]
]


@dataclass(frozen=True)
class RigParameters:
    """The camera rig of a light field, as the HCI benchmark's ``parameters.cfg`` gives it.

    Attributes
    ----------
    baseline_m : float
        Distance between neighbouring cameras, metres.
    focal_length_mm, sensor_size_mm : float
        Focal length and sensor width, millimetres.
    resolution : (int, int)
        Image width and height (px) the parameters refer to.
    offset_px : float
        Disparity of infinity, negated: absolute (parallel-camera) disparity is
        ``d + offset_px`` (the views converge on the zero-parallax plane). From the
        file's ``offset``, else ``baseline_mm * focal_mm / focus_m / 1000 / sensor_mm
        * width`` (the benchmark toolkit's formula).
    focus_distance_m : float or None
        Distance of the zero-parallax plane, metres.
    grid : (int, int) or None
        Cameras per column and per row (``num_cams_y``, ``num_cams_x``).
    source : str
        The file read.
    """

    baseline_m: float
    focal_length_mm: float
    sensor_size_mm: float
    resolution: tuple[int, int]
    offset_px: float
    focus_distance_m: float | None = None
    grid: tuple[int, int] | None = None
    source: str = ""

    def focal_px(self, width: int | None = None) -> float:
        """Focal length in pixels for images ``width`` px wide (default: the file's)."""
        w = self.resolution[0] if width is None else width
        return self.focal_length_mm / self.sensor_size_mm * w

    def offset_for(self, width: int | None = None) -> float:
        """``offset_px`` for images ``width`` px wide (it scales with the width)."""
        w = self.resolution[0] if width is None else width
        return self.offset_px * w / self.resolution[0]

    @classmethod
    def from_cfg(cls, path: str | os.PathLike[str]) -> RigParameters | None:
        """Read an HCI ``parameters.cfg``.

        Returns
        -------
        RigParameters or None
            None when the file lacks what metric depth needs (baseline, focal length,
            sensor size, resolution, and an offset or a focus distance).

        Raises
        ------
        lfcam.InputError
            If the file cannot be parsed, or a value that is there is not a number.
        """
        p = Path(path)
        cp = configparser.ConfigParser()
        try:
            cp.read_string(p.read_text(encoding="utf-8", errors="replace"), source=str(p))
        except configparser.Error as exc:
            msg = str(exc).splitlines()[0]
            raise InputError(f"{p}: not a readable parameters file ({msg})") from None

        def num(section: str, key: str) -> float | None:
            if not cp.has_option(section, key):
                return None
            text = cp.get(section, key)
            try:
                value = float(text)
            except ValueError:
                raise InputError(f"{p}: [{section}] {key} = {text!r} is not a number") from None
            if not math.isfinite(value):
                raise InputError(f"{p}: [{section}] {key} = {text!r} is not finite")
            return value

        ny, nx = num("extrinsics", "num_cams_y"), num("extrinsics", "num_cams_x")
        grid = (int(ny), int(nx)) if ny is not None and nx is not None else None
        if grid is not None and min(grid) < 1:
            raise InputError(f"{p}: num_cams_y, num_cams_x = {grid} must be >= 1")
        baseline_mm = num("extrinsics", "baseline_mm")
        focal = num("intrinsics", "focal_length_mm")
        sensor = num("intrinsics", "sensor_size_mm")
        res_x = num("intrinsics", "image_resolution_x_px")
        res_y = num("intrinsics", "image_resolution_y_px")
        focus = num("extrinsics", "focus_distance_m")
        offset = num("extrinsics", "offset")
        if baseline_mm is None or focal is None or sensor is None or res_x is None:
            return None
        for key, v in (("baseline_mm", baseline_mm), ("focal_length_mm", focal)):
            if v <= 0:
                raise InputError(f"{p}: {key} = {v:g} must be > 0")
        if sensor <= 0 or res_x < 1:
            raise InputError(f"{p}: sensor_size_mm and image_resolution_x_px must be > 0")
        if offset is None:
            if focus is None or focus <= 0:
                return None
            offset = baseline_mm * focal / focus / 1000.0 / sensor * res_x
        return cls(
            baseline_m=baseline_mm / 1000.0,
            focal_length_mm=focal,
            sensor_size_mm=sensor,
            resolution=(int(res_x), int(res_y if res_y is not None else res_x)),
            offset_px=offset,
            focus_distance_m=focus,
            grid=grid,
            source=str(p),
        )


def _parse_axis(text: str, name: str) -> slice:
    t = text.strip()
    try:
        if ":" not in t:
            i = int(t)
            return slice(i, i + 1 if i != -1 else None)
        parts = t.split(":")
        if len(parts) > 3:
            raise ValueError
        vals = [int(v) if v.strip() else None for v in parts]
    except ValueError:
        raise InputError(
            f"views: {name} {text!r} is not a Python slice of grid indices (e.g. 3:6)"
        ) from None
    if len(vals) == 3 and vals[2] == 0:
        raise InputError(f"views: {name} {text!r} has a zero step")
    return slice(*vals)


def parse_views(text: str) -> tuple[slice, slice]:
    """``"3:6,3:7"`` -> ``(slice(3, 6), slice(3, 7))``: rows, then columns.

    Each part is a Python slice (``start:stop[:step]``, half-open, any part may be
    empty) or one index, in absolute grid indices.

    Raises
    ------
    lfcam.InputError
        If ``text`` is not two such parts separated by a comma.
    """
    parts = str(text).split(",")
    if len(parts) != 2:
        raise InputError(f"views: expected ROWS,COLS as Python slices, e.g. 3:6,3:7, got {text!r}")
    return _parse_axis(parts[0], "rows"), _parse_axis(parts[1], "columns")


def _select(spec: slice | int | Sequence[int], present: Sequence[int], name: str) -> list[int]:
    """The grid indices of ``present`` that ``spec`` picks, in ``spec``'s order."""
    n = max(present) + 1
    if isinstance(spec, slice):
        picked = list(range(n))[spec]
    elif isinstance(spec, (int, np.integer)):
        i = int(spec)
        if not -n <= i < n:
            raise InputError(f"views: {name} index {i} is outside the grid (0..{n - 1})")
        picked = [i % n]
    else:
        try:
            picked = [int(i) for i in spec]
        except (TypeError, ValueError):
            raise InputError(
                f"views: {name} must be a slice, an index or indices, got {spec!r}"
            ) from None
    if not picked:
        raise InputError(f"views: the {name} selection {spec!r} is empty (grid 0..{n - 1})")
    return picked


def _row_col_names(folder: Path, files: list[Path]) -> dict[Path, tuple[int, int]]:
    """(row, col) of the images whose names hold them: the last two integers of the
    name. Names with exactly two integers (``03_04.png``, ``view_3_4.png``) are taken
    first; otherwise the names may share leading integers (a capture number, as in
    Lytro exports: ``2067_05_05.png``), which must then be the same in every name."""
    ints = {
        p: [int(t) for t in _INT.findall(p.stem)]
        for p in files
        if p.suffix.lower() in IMAGE_EXTENSIONS
    }
    two = {p: (v[0], v[1]) for p, v in ints.items() if len(v) == 2}
    if two:
        return two
    longer = {p: v for p, v in ints.items() if len(v) > 2}
    if not longer:
        return {}
    counts = Counter(len(v) for v in longer.values())
    n = max(counts, key=lambda k: (counts[k], -k))
    picked = {p: v for p, v in longer.items() if len(v) == n}
    first = next(iter(picked))
    for p, v in picked.items():
        if v[:-2] != picked[first][:-2]:
            raise InputError(
                f"{folder}: view names hold more than a row and a column, and their leading"
                f" numbers differ ({first.name}, {p.name}): put one capture per folder"
            )
    return {p: (v[-2], v[-1]) for p, v in picked.items()}


def _find_views(folder: Path) -> tuple[str, dict[tuple[int, int], Path], RigParameters | None]:
    """(layout, {(row, col): file}, parameters) of a folder of views."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    cfg = folder / _CFG_NAME
    params = RigParameters.from_cfg(cfg) if cfg.is_file() else None
    grid_cfg: tuple[int, int] | None = None
    if cfg.is_file() and params is None:
        # Not metric, but the grid may still be there.
        cp = configparser.ConfigParser()
        try:
            cp.read_string(cfg.read_text(encoding="utf-8", errors="replace"))
            grid_cfg = (
                cp.getint("extrinsics", "num_cams_y"),
                cp.getint("extrinsics", "num_cams_x"),
            )
        except (configparser.Error, ValueError):
            grid_cfg = None
    elif params is not None:
        grid_cfg = params.grid
    hci = {int(m.group(1)): p for p in files if (m := _HCI_NAME.match(p.name))}
    found: dict[tuple[int, int], Path] = {}
    if hci:
        if grid_cfg is None:
            side = math.isqrt(max(hci) + 1)
            if side * side != max(hci) + 1:
                raise InputError(
                    f"{folder}: HCI views input_CamNNN.png but no {_CFG_NAME} giving the grid"
                    f" (num_cams_x, num_cams_y), and {max(hci) + 1} is not a square number"
                )
            grid_cfg = (side, side)
        rows, cols = grid_cfg
        for k, p in sorted(hci.items()):
            if k >= rows * cols:
                raise InputError(
                    f"{p}: camera {k} is outside the {rows}x{cols} grid of {cfg}"
                    if cfg.is_file()
                    else f"{p}: camera {k} is outside the {rows}x{cols} grid"
                )
            found[divmod(k, cols)] = p
        return "hci", found, params
    for p, rc in _row_col_names(folder, files).items():
        if rc in found:
            raise InputError(
                f"{folder}: two files for view (row {rc[0]}, col {rc[1]}):"
                f" {found[rc].name} and {p.name}"
            )
        found[rc] = p
    if not found:
        raise InputError(
            f"{folder}: no views found (expected HCI input_CamNNN.png, or images named by"
            " row and column, such as 03_04.png, view_3_4.png or 2067_05_05.png)"
        )
    return "row_col", found, params


class LightField:
    """A grid of rectified views, their grid positions and parallax vectors.

    Parameters
    ----------
    views : array
        ``(R, C, H, W[, 3])`` (a full grid, row ``r`` col ``c`` at ``views[r, c]``)
        when ``positions`` is None, else ``(N, H, W[, 3])`` in the order of
        ``positions``. uint8, uint16 or float (float taken as [0, 1]).
    positions : (N, 2) int array, optional
        Absolute grid (row, column) of each view of a flat ``views``.
    reference : (int, int), optional
        Absolute (row, column) of the reference view: depth is given in its frame.
        Default: the view nearest the grid's centre (for an even count, the lower
        index: (1, 1) of a 3 x 4 grid).
    flip : {'', 'x', 'y', 'xy'}
        Which grid axes run against the HCI convention: ``'x'`` if a larger column
        index means the camera sits further *left*, ``'y'`` if a larger row means
        further *up*. The parallax vectors flip accordingly, so that ``s`` keeps
        meaning disparity, positive nearer than the zero-parallax plane.
    parameters : RigParameters, optional
        The rig, for metric depth.
    ground_truth : (H, W) array, optional
        Ground-truth disparity of the view at ``ground_truth_view``.
    ground_truth_view : (int, int), optional
        Absolute (row, column) the ground truth belongs to (default: the reference).

    Attributes
    ----------
    views : (N, H, W[, 3]) array
        As given or read (dtype kept).
    positions : (N, 2) int64
        Absolute (row, column) of each view, row-major.
    layout : str
        ``'arrays'``, ``'hci'`` or ``'row_col'``.
    files : list of Path or None
        The file of each view, when read from a folder.
    source : str or None
        The folder read.

    Notes
    -----
    ``o_i = (-s_x (c_i - c_ref), -s_y (r_i - r_ref))`` with ``s_x, s_y = -1`` for a
    flipped axis, else ``+1``: the reference pixel ``p`` appears at ``p + o_i s``
    in view ``i`` (docs/design.md, "Plane and parallax"), and ``s`` equals the HCI benchmark's
    disparity (px per grid step). A subset keeps absolute indices, so rows 2, 4, 6
    give offsets of 2 px per unit ``s``, and ``s`` is still disparity per grid step.

    Examples
    --------
    >>> lf = lfcam.LightField.from_folder("hci4d_antinous", views="3:6,3:7")  # doctest: +SKIP
    >>> lf.grid_shape, lf.reference_rc                                        # doctest: +SKIP
    ((3, 4), (4, 4))
    >>> res = lf.estimate_depth()                                             # doctest: +SKIP
    >>> disparity, metres = res.parallax, res.depth                           # doctest: +SKIP
    """

    def __init__(
        self,
        views: Any,
        positions: Any = None,
        *,
        reference: tuple[int, int] | None = None,
        flip: Flip = "",
        parameters: RigParameters | None = None,
        ground_truth: Any = None,
        ground_truth_view: tuple[int, int] | None = None,
    ) -> None:
        try:
            arr = np.asarray(views)
        except (TypeError, ValueError) as exc:
            raise InputError(f"views: not an array of images ({exc})") from None
        if not (arr.dtype in (np.uint8, np.uint16) or arr.dtype.kind == "f"):
            raise InputError(f"views: expected uint8, uint16 or float pixels, not {arr.dtype}")
        if positions is None:
            if arr.ndim not in (4, 5) or (arr.ndim == 5 and arr.shape[4] != 3):
                raise InputError(
                    f"views: expected a grid (R, C, H, W[, 3]) when no positions are given,"
                    f" got shape {arr.shape}"
                )
            R, C = arr.shape[:2]
            pos = np.array([(r, c) for r in range(R) for c in range(C)], np.int64)
            arr = arr.reshape((R * C, *arr.shape[2:]))
        else:
            if arr.ndim not in (3, 4) or (arr.ndim == 4 and arr.shape[3] != 3):
                raise InputError(
                    f"views: expected (N, H, W[, 3]) with positions, got shape {arr.shape}"
                )
            p = np.asarray(positions)
            if p.shape != (arr.shape[0], 2) or p.dtype.kind not in "iu":
                raise InputError(
                    f"positions: expected ({arr.shape[0]}, 2) integer (row, col) pairs,"
                    f" got {p.dtype} of shape {p.shape}"
                )
            pos = p.astype(np.int64)
        if arr.shape[0] < 2 or min(arr.shape[1:3]) < 1:
            raise InputError(f"views: need at least two non-empty views, got shape {arr.shape}")
        if (pos < 0).any():
            raise InputError("positions: grid indices must be >= 0")
        if len({(int(r), int(c)) for r, c in pos}) != len(pos):
            raise InputError("positions: two views share a grid position")
        # Row-major order, so flat indices read like the calibration's i = r*C + c.
        order = np.lexsort((pos[:, 1], pos[:, 0]))
        self.views: np.ndarray = np.ascontiguousarray(arr[order])
        self.positions: np.ndarray = pos[order]
        if flip not in ("", "x", "y", "xy"):
            raise InputError(f"flip: expected '', 'x', 'y' or 'xy', got {flip!r}")
        self.flip: Flip = flip
        self.parameters = parameters
        self.layout = "arrays"
        self.files: list[Path] | None = None
        self.source: str | None = None
        self._index = {(int(r), int(c)): i for i, (r, c) in enumerate(self.positions)}
        if reference is None:
            rows, cols = self.rows, self.cols
            reference = (rows[(len(rows) - 1) // 2], cols[(len(cols) - 1) // 2])
        ref = _pair_of_ints(reference, "reference")
        if ref not in self._index:
            raise InputError(
                f"reference: view (row {ref[0]}, col {ref[1]}) is not in the light field"
                f" (rows {_span(self.rows)}, cols {_span(self.cols)})"
            )
        self.reference_rc: tuple[int, int] = ref
        self.ground_truth: np.ndarray | None = None
        self.ground_truth_view: tuple[int, int] | None = None
        if ground_truth is not None:
            gt = np.asarray(ground_truth, np.float32)
            if gt.shape != self.views.shape[1:3]:
                raise InputError(
                    f"ground_truth: shape {gt.shape} does not match the views'"
                    f" {self.views.shape[1:3]}"
                )
            self.ground_truth = gt
            self.ground_truth_view = (
                ref if ground_truth_view is None else _pair_of_ints(ground_truth_view, "view")
            )

    # ------------------------------------------------------------------ folders
    @classmethod
    def from_folder(
        cls,
        path: str | os.PathLike[str],
        views: ViewSelection | None = None,
        reference: tuple[int, int] | None = None,
        *,
        flip: Flip = "",
    ) -> LightField:
        """Read a folder of rectified views.

        Parameters
        ----------
        path : path-like
            The folder. Two layouts are recognised:

            - **HCI 4D benchmark**: ``input_CamNNN.png`` with ``NNN = C * row + col``,
              ``parameters.cfg`` (grid, and baseline, focal length, sensor size and
              offset for metric depth) and an optional ``gt_disp_lowres.pfm``, the
              ground-truth disparity of the grid's centre view.
            - **row_col**: image files (PNG, TIFF, JPEG) whose name holds two
              integers, row then column: ``03_04.png``, ``view_3_4.tif``; or the
              same after leading integers shared by every name (Lytro exports:
              ``2067_05_05.png``, row and column are the last two). An optional
              ``parameters.cfg`` and ``gt_disp_lowres.pfm`` are read as for HCI.
        views : str or pair, optional
            The subset: ``"3:6,3:7"`` (rows 3-5, cols 3-6), Python slices of
            absolute grid indices; or a pair of slices, indices or index lists.
            Default: every view. Only the selected files are read.
        reference : (int, int), optional
            Absolute (row, column) of the reference view; default the view nearest
            the selected grid's centre.
        flip : {'', 'x', 'y', 'xy'}
            Grid axes numbered against the HCI convention (see :class:`LightField`).

        Returns
        -------
        LightField

        Raises
        ------
        lfcam.InputError
            If the folder is missing or holds no views, the selection is empty or
            has a hole, the reference is not selected, or views differ in size.
        """
        folder = Path(path)
        if not folder.is_dir():
            raise InputError(f"{folder}: no such folder")
        layout, found, params = _find_views(folder)
        all_rows = sorted({r for r, _ in found})
        all_cols = sorted({c for _, c in found})
        if views is None:
            rows, cols = all_rows, all_cols
        else:
            spec = parse_views(views) if isinstance(views, str) else views
            if not isinstance(spec, tuple) or len(spec) != 2:
                raise InputError(f"views: expected 'ROWS,COLS' or a pair, got {views!r}")
            rows = _select(spec[0], all_rows, "rows")
            cols = _select(spec[1], all_cols, "columns")
        missing = [(r, c) for r in rows for c in cols if (r, c) not in found]
        if missing:
            shown = ", ".join(f"({r}, {c})" for r, c in missing[:6])
            more = f" and {len(missing) - 6} more" if len(missing) > 6 else ""
            raise InputError(
                f"{folder}: no file for view(s) (row, col) {shown}{more} of the selected"
                f" rows {rows} x cols {cols}"
            )
        if len(rows) * len(cols) < 2:
            raise InputError(
                f"views: the selection rows {rows} x cols {cols} has one view; depth needs two"
            )
        picked = [(r, c) for r in rows for c in cols]
        imgs: list[np.ndarray] = []
        for rc in picked:
            img = read_image(found[rc])
            if imgs and (img.shape != imgs[0].shape or img.dtype != imgs[0].dtype):
                first = found[picked[0]].name
                raise InputError(
                    f"{found[rc]}: {img.shape[1]}x{img.shape[0]} {_kind(img)} differs from"
                    f" {first} ({imgs[0].shape[1]}x{imgs[0].shape[0]} {_kind(imgs[0])}):"
                    " every view must have the same size and pixel type"
                )
            imgs.append(img)
        gt = None
        gt_view = None
        gt_path = folder / _GT_NAME
        if gt_path.is_file():
            gt = read_pfm(gt_path)
            if gt.ndim != 2:
                raise InputError(f"{gt_path}: a disparity map has one channel, got {gt.shape}")
            if gt.shape != imgs[0].shape[:2]:
                raise InputError(
                    f"{gt_path}: {gt.shape[1]}x{gt.shape[0]} does not match the views'"
                    f" {imgs[0].shape[1]}x{imgs[0].shape[0]}"
                )
            gt_view = (all_rows[(len(all_rows) - 1) // 2], all_cols[(len(all_cols) - 1) // 2])
            if params is not None and params.grid is not None:
                gt_view = ((params.grid[0] - 1) // 2, (params.grid[1] - 1) // 2)
        if reference is None:
            reference = (rows[(len(rows) - 1) // 2], cols[(len(cols) - 1) // 2])
        ref = _pair_of_ints(reference, "reference")
        if ref not in set(picked):
            raise InputError(
                f"reference: view (row {ref[0]}, col {ref[1]}) is not in the selected"
                f" rows {rows} x cols {cols}"
            )
        lf = cls(
            np.stack(imgs),
            np.array(picked, np.int64),
            reference=ref,
            flip=flip,
            parameters=params,
            ground_truth=gt,
            ground_truth_view=gt_view,
        )
        lf.layout = layout
        lf.files = [found[(int(r), int(c))] for r, c in lf.positions]
        lf.source = str(folder)
        return lf

    # ------------------------------------------------------------------ geometry
    @property
    def rows(self) -> list[int]:
        """The grid rows present, ascending (absolute indices)."""
        return sorted({int(r) for r in self.positions[:, 0]})

    @property
    def cols(self) -> list[int]:
        """The grid columns present, ascending (absolute indices)."""
        return sorted({int(c) for c in self.positions[:, 1]})

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(rows, columns) of the views held."""
        return len(self.rows), len(self.cols)

    @property
    def n_views(self) -> int:
        """Number of views held."""
        return int(self.views.shape[0])

    def __len__(self) -> int:
        return self.n_views

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of one view."""
        return int(self.views.shape[1]), int(self.views.shape[2])

    @property
    def reference(self) -> int:
        """Flat index (into :attr:`views`) of the reference view."""
        return self._index[self.reference_rc]

    @property
    def offsets(self) -> np.ndarray:
        """``o_i`` (N, 2) float64, px per unit parallax: x then y (see the class notes)."""
        r0, c0 = self.reference_rc
        sx = -1.0 if "x" in self.flip else 1.0
        sy = -1.0 if "y" in self.flip else 1.0
        o = np.empty((self.n_views, 2), np.float64)
        o[:, 0] = -sx * (self.positions[:, 1] - c0)
        o[:, 1] = -sy * (self.positions[:, 0] - r0)
        return o + 0.0  # no negative zeros

    def index(self, row: int, col: int) -> int:
        """Flat index of the view at absolute grid (row, col)."""
        rc = (int(row), int(col))
        if rc not in self._index:
            raise InputError(
                f"view: (row {rc[0]}, col {rc[1]}) is not in the light field"
                f" (rows {_span(self.rows)}, cols {_span(self.cols)})"
            )
        return self._index[rc]

    def view(self, row: int, col: int) -> np.ndarray:
        """The image at absolute grid (row, col), as stored."""
        img: np.ndarray = self.views[self.index(row, col)]
        return img

    def to_float(self) -> np.ndarray:
        """The views as float32 in [0, 1] (uint8 / 255, uint16 / 65535)."""
        return to_float(self.views)

    # ------------------------------------------------------------------ depth
    @property
    def metric(self) -> bool:
        """Whether :meth:`disparity_to_depth` can give metres (rig parameters known)."""
        return self.parameters is not None

    def disparity_to_depth(self, disparity: Any) -> np.ndarray:
        """Disparity (px per grid step) -> depth (m), the HCI toolkit's ``disp2depth``.

        ``Z = baseline_m * f_px / (d + offset)``, with ``f_px = focal_mm / sensor_mm *
        W`` and ``offset`` scaled to the views' width ``W``. Depth is along the
        optical axis; NaN where ``d + offset <= 0`` (at or beyond infinity).

        Raises
        ------
        lfcam.InputError
            If the light field has no rig parameters (``parameters.cfg``).
        """
        if self.parameters is None:
            raise InputError(
                "disparity_to_depth: no rig parameters (baseline, focal length, sensor size"
                f" and offset in {_CFG_NAME}); only disparity is known"
            )
        w = self.image_shape[1]
        f_px = self.parameters.focal_px(w)
        offset = self.parameters.offset_for(w)
        d = np.asarray(disparity, np.float64) + offset
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.parameters.baseline_m * f_px / d
        return np.where(d > 0, z, np.nan).astype(np.float32)

    def estimate_depth(self, params: DepthParams | None = None, *, threads: int = 2) -> DepthResult:
        """Disparity (and depth) of the reference view by flow and triangulation.

        Calls :func:`lfcam.depth_from_views` with the views as float32 in [0, 1],
        :attr:`offsets` and :attr:`reference`.

        Parameters
        ----------
        params : DepthParams, optional
            The depth chain's settings.
        threads : int
            Concurrent flows.

        Returns
        -------
        DepthResult
            ``parallax`` is the disparity (px per grid step, HCI sign); ``depth``
            (metres) is filled when the rig is known (:attr:`metric`).
        """
        res = depth_from_views(
            self.to_float(), self.offsets, self.reference, params, threads=threads
        )
        if self.metric:
            res.depth = self.disparity_to_depth(res.parallax)
        return res

    def __repr__(self) -> str:
        h, w = self.image_shape
        return (
            f"LightField({self.grid_shape[0]}x{self.grid_shape[1]} views of {w}x{h},"
            f" rows {_span(self.rows)}, cols {_span(self.cols)},"
            f" reference {self.reference_rc}, layout {self.layout!r})"
        )


def _pair_of_ints(value: Any, name: str) -> tuple[int, int]:
    try:
        a, b = value
        if isinstance(a, (bool, np.bool_)) or isinstance(b, (bool, np.bool_)):
            raise TypeError
        pair = (int(a), int(b))
        if pair != (a, b):
            raise TypeError
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected (row, col) integers, got {value!r}") from None
    return pair


def _span(idx: Sequence[int]) -> str:
    if list(idx) == list(range(idx[0], idx[-1] + 1)):
        return f"{idx[0]}..{idx[-1]}"
    return ", ".join(str(i) for i in idx)


def _kind(img: np.ndarray) -> str:
    return f"{'RGB' if img.ndim == 3 else 'grey'} {img.dtype}"


def points_from_lightfield(depth: np.ndarray, lf: LightField) -> tuple[np.ndarray, np.ndarray]:
    """3-D points (metres) of finite depths, in the reference camera's frame.

    Pinhole model of the HCI rig: X right, Y down, Z along the optical axis, origin at
    the reference camera; focal length ``f_px`` from the rig parameters. The views
    converge (shifted sensors): the principal point of view i is the image centre
    moved by ``-offset * o_i'``, with ``o_i'`` its parallax vector relative to the
    grid's centre (infinity, at disparity ``-offset``, appears there).

    Returns
    -------
    points : (M, 3) float32
    index : (M, 2) int64
        Row and column of each point in the reference view.
    """
    p = lf.parameters
    if p is None:
        raise InputError("lf: the light field has no rig parameters; no metric points")
    H, W = depth.shape
    f = p.focal_px(W)
    offset = p.offset_for(W)
    if p.grid is not None:
        r_mid, c_mid = (p.grid[0] - 1) / 2.0, (p.grid[1] - 1) / 2.0
    else:
        r_mid = (min(lf.rows) + max(lf.rows)) / 2.0
        c_mid = (min(lf.cols) + max(lf.cols)) / 2.0
    sx = -1.0 if "x" in lf.flip else 1.0
    sy = -1.0 if "y" in lf.flip else 1.0
    r_ref, c_ref = lf.reference_rc
    cx = (W - 1) / 2.0 + offset * sx * (c_ref - c_mid)
    cy = (H - 1) / 2.0 + offset * sy * (r_ref - r_mid)
    vv, uu = np.nonzero(np.isfinite(depth))
    Z = depth[vv, uu].astype(np.float64)
    X = (uu - cx) * Z / f
    Y = (vv - cy) * Z / f
    return np.column_stack([X, Y, Z]).astype(np.float32), np.stack([vv, uu], 1)
