"""The ``lfcam`` command line: parse, report progress, set exit codes.

Exit codes: 0 success, 2 bad input (a clear message names the file or
argument), 1 an unexpected internal error.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from .errors import CalibrationError, InputError, LfcamError
from .progress import Progress, configure_logging

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line usage error naming the argument (exit 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _check_output_folder(path: Path, flag: str) -> None:
    """Refuse an output folder that cannot be made or written, before any long work."""
    if path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: exists and is not a folder")
    parent = path
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{flag} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {path}: {parent} is not writable")


def _pair(text: str, sep: str, name: str, form: str) -> tuple[int, int]:
    """Two integers separated by ``sep`` (``form`` names them in the error: ``RxC``)."""
    parts = text.lower().split(sep)
    try:
        a, b = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{name}: expected two integers as {form}, got {text!r}"
        ) from None
    return a, b


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def _progress(args: argparse.Namespace, total: int, desc: str, unit: str = "step") -> Progress:
    return Progress(total, desc, unit=unit, quiet=args.quiet)


#: Options every command takes (each subparser inherits them).
_COMMON = argparse.ArgumentParser(add_help=False)
_COMMON.add_argument(
    "-q", "--quiet", action="store_true", help="no progress bar or progress log lines"
)


class _HelpFormatter(argparse.HelpFormatter):
    """Wraps descriptions as usual; keeps the examples' lines as written."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("examples:"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


def _command(sub: Any, name: str, *, examples: Sequence[str], **kwargs: Any) -> Any:
    """A subcommand's parser: common options, and its examples at the end of --help."""
    epilog = "examples:\n" + "\n".join(f"  {e}" for e in examples)
    return sub.add_parser(
        name,
        parents=[_COMMON],
        epilog=epilog,
        formatter_class=_HelpFormatter,
        **kwargs,
    )


# ---------------------------------------------------------------------------
# lfcam simulate
# ---------------------------------------------------------------------------
def _add_simulate(sub: Any) -> None:
    p = _command(
        sub,
        "simulate",
        examples=[
            "lfcam simulate sim/",
            "lfcam simulate sim/ --grid 3x3 --view-size 320x240 --bit-depth 16 --format tiff",
            "lfcam simulate sim/ --bayer RGGB --scenes planes,board --distances 0.7,1,1.5",
        ],
        help="simulate a camera: calibration captures and scenes with ground truth",
        description=(
            "Render a simulated light-field camera (docs/design.md, 'Simulator'): a calibration "
            "folder (pattern, white and board captures) and scene captures, with ground "
            "truth (warp maps, o_i, Z_c, depth, 2x reference image). Camera parameters "
            "come from --config (TOML, keys as in lfcam.SimConfig) and the flags below, "
            "which override it."
        ),
    )
    p.add_argument(
        "out_dir", type=Path, metavar="OUT_DIR", help="output folder (must be new or empty)"
    )
    p.add_argument("--config", type=Path, metavar="CAM.toml", help="TOML file of camera parameters")
    p.add_argument("--seed", type=int, metavar="S", help="random seed (default 0)")
    p.add_argument(
        "--grid",
        type=lambda t: _pair(t, "x", "--grid", "RxC"),
        metavar="RxC",
        help="lenslet grid, rows x columns, e.g. 3x4",
    )
    p.add_argument(
        "--view-size",
        type=lambda t: _pair(t, "x", "--view-size", "WxH"),
        metavar="WxH",
        help="width x height of one view in raw pixels, e.g. 480x360",
    )
    p.add_argument(
        "--full-size", action="store_true", help="the full-size camera: 1200x900 px views"
    )
    p.add_argument("--bit-depth", type=int, choices=(8, 16), help="raw bit depth")
    p.add_argument("--bayer", choices=("RGGB", "BGGR", "GRBG", "GBRG"), help="Bayer raw")
    p.add_argument(
        "--format",
        dest="raw_format",
        choices=("png", "tiff", "dng"),
        help="raw file format (dng: camera raw, needs --bayer)",
    )
    p.add_argument(
        "--scenes", metavar="S1,S2", help="comma-separated scenes: planes, spheres, layered, board"
    )
    p.add_argument(
        "--distances",
        type=_floats,
        metavar="Z1,Z2",
        help="board distances in metres, e.g. 0.8,1,1.25",
    )
    p.add_argument(
        "--zoom",
        type=_floats,
        metavar="F1,F2",
        help="a parfocal zoom: one setting per focal length in mm, e.g. 50,75,100",
    )
    p.add_argument(
        "--board-tilt",
        type=float,
        metavar="DEG",
        help="tilt each calibration board by a random angle of up to DEG degrees (seeded)",
    )
    p.add_argument(
        "--board-drift",
        type=float,
        metavar="MM",
        help="move each calibration board sideways by up to MM millimetres (seeded)",
    )
    p.add_argument(
        "--captures", type=int, metavar="N", help="board captures per distance (default 5)"
    )
    p.add_argument("--no-truth", action="store_true", help="skip the ground truth")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUT_DIR")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from .sim import SimConfig, simulate

    changes: dict[str, Any] = {}
    if args.full_size:
        changes["view_size"] = (1200, 900)
    keys = ("seed", "grid", "view_size", "bit_depth", "bayer", "raw_format", "distances")
    for key in (*keys, "board_tilt", "board_drift", "zoom"):
        value = getattr(args, key)
        if value is not None:
            changes[key] = value
    if args.scenes is not None:
        changes["scenes"] = tuple(s.strip() for s in args.scenes.split(",") if s.strip())
    if args.captures is not None:
        changes["captures_per_distance"] = args.captures
    if args.config is not None:
        cfg = SimConfig.from_toml(args.config, **changes)
    else:
        cfg = SimConfig.from_dict({}, source="command line", **changes)
    steps = (4 + len(cfg.distances) + len(cfg.scenes) + (0 if args.no_truth else 1)) * max(
        1, len(cfg.zoom)
    )
    t0 = time.perf_counter()
    with _progress(args, steps, "simulate") as bar:
        res = simulate(
            args.out_dir, cfg, overwrite=args.overwrite, truth=not args.no_truth, progress=bar
        )
    cam = res.camera
    print(f"simulated a {cfg.grid[0]}x{cfg.grid[1]} camera in {time.perf_counter() - t0:.1f} s")
    print(
        f"  raw frames      {cam.W_raw} x {cam.H_raw}, {cfg.bit_depth}-bit"
        f"{', Bayer ' + cfg.bayer if cfg.bayer else ' RGB'}"
    )
    print(
        f"  rectified frame {cam.W_rect} x {cam.H_rect} px, Z_b = {cam.z_b:g} m, "
        f"Z_c = {cam.z_c:.4f} m"
    )
    for f, r in res.zoom.items():
        print(f"  zoom {f:g} mm     Z_c = {r.camera.z_c:.4f} m, {r.calibration_dir}")
    print(f"  calibration     {res.calibration_dir}")
    for name, path in res.captures.items():
        print(f"  capture         {path}  ({name})")
    if not args.no_truth:
        print(f"  ground truth    {res.truth_dir}")
    return EXIT_OK


# ---------------------------------------------------------------------------
# lfcam pattern
# ---------------------------------------------------------------------------
def _add_pattern(sub: Any) -> None:
    p = _command(
        sub,
        "pattern",
        examples=[
            "lfcam pattern cal/pattern.png --width 1920 --height 1080",
            "lfcam pattern board.tiff --width 4000 --height 3000 --seed 7",
        ],
        help="write the digital calibration pattern",
        description=(
            "Write the calibration pattern: dense multi-scale texture with a cross at the "
            "centre. Show it full screen on a monitor at native resolution (one pattern "
            "pixel per screen pixel), or print it unscaled on a rigid flat board; the "
            "size of one pattern pixel on the board in metres is the pattern pitch."
        ),
    )
    p.add_argument("out", type=Path, metavar="OUT.png", help="output image (.png, .tif or .tiff)")
    p.add_argument("--width", type=int, required=True, metavar="W", help="width in pixels")
    p.add_argument("--height", type=int, required=True, metavar="H", help="height in pixels")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.set_defaults(func=_cmd_pattern)


def _cmd_pattern(args: argparse.Namespace) -> int:
    from .calibration import make_pattern
    from .io import write_image_atomic

    img = make_pattern(args.width, args.height, seed=args.seed)
    write_image_atomic(args.out, img)
    print(f"wrote {args.out} ({args.width} x {args.height}, seed {args.seed})")
    return EXIT_OK


# ---------------------------------------------------------------------------
# lfcam calibrate / lfcam info
# ---------------------------------------------------------------------------
def _rc(text: str) -> tuple[int, int]:
    return _pair(text, ",", "--reference", "ROW,COL")


def _add_calibrate(sub: Any) -> None:
    p = _command(
        sub,
        "calibrate",
        examples=[
            "lfcam calibrate cal/ -o camera.lfcal",
            "lfcam calibrate cal/ -o camera.lfcal --grid 3x4 --reference 1,1 --pattern-pitch 2.5e-4"
            " --overwrite",
            "lfcam calibrate cal/ -o camera.lfcal --z-c 0.052 --bayer RGGB",
        ],
        help="calibrate a camera from white and board captures",
        description=(
            "Calibrate a camera (docs/design.md, 'Calibration pipeline') from CAL_DIR: "
            "pattern.png, white/*, "
            "board_<distance>m/* (one or more distances; three or more, or two plus the "
            "optical centres, give metric depth with no optics known), and an optional "
            "camera.toml (grid, reference, z_c, pattern_pitch, bayer), which the flags "
            "override. Writes CAMERA.lfcal, CAMERA.report.json, CAMERA.report.png and "
            "CAMERA.report.html (the report as a page: per view numbers, pass/warn/fail "
            "verdicts against stated thresholds, o_i on the sensor layout, the parallax fit)."
        ),
    )
    p.add_argument("cal_dir", type=Path, metavar="CAL_DIR", help="the calibration folder")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="CAMERA.lfcal",
        help="calibration file to write",
    )
    p.add_argument(
        "--grid",
        type=lambda t: _pair(t, "x", "--grid", "RxC"),
        metavar="RxC",
        help="lenslet grid, rows x columns, e.g. 3x4",
    )
    p.add_argument("--reference", type=_rc, metavar="ROW,COL", help="reference view (zero-based)")
    p.add_argument(
        "--reference-distance",
        type=float,
        metavar="M",
        help="Z_b, metres (default: the board distance nearest 1 m)",
    )
    p.add_argument(
        "--scale", type=float, metavar="S", help="rectified px per pattern px (default: ~1 raw px)"
    )
    p.add_argument("--z-c", type=float, metavar="M", help="Z_c = f D / (D - f) in metres, if known")
    p.add_argument(
        "--pattern-pitch", type=float, metavar="M", help="metres per pattern pixel on the board"
    )
    p.add_argument("--bayer", choices=("RGGB", "BGGR", "GRBG", "GBRG"), help="Bayer raw")
    p.add_argument(
        "--warps-per-setting",
        action="store_true",
        help="zoom settings: each keeps its own warp maps (default: shared where they agree)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing CAMERA.lfcal")
    p.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from .calibration import run_calibration

    out: Path = args.output
    if out.suffix != ".lfcal":
        out = out.with_name(out.name + ".lfcal")
    if out.exists() and not args.overwrite:
        raise InputError(f"{out}: exists (use --overwrite to replace it)")
    if not out.parent.is_dir():
        raise InputError(f"{out}: folder {out.parent} does not exist")
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise InputError(f"{out}: folder {out.parent} is not writable")
    steps = ["layout", "scale", "warp", "depth"]
    t0 = time.perf_counter()
    with _progress(args, len(steps) + 3, "calibrate") as bar:
        from .calibration.inputs import find_settings

        if None not in find_settings(args.cal_dir):
            return _calibrate_zoom(args, out, bar, t0)
        run = run_calibration(
            args.cal_dir,
            grid=args.grid,
            reference=args.reference,
            reference_distance=args.reference_distance,
            scale=args.scale,
            z_c=args.z_c,
            pattern_pitch=args.pattern_pitch,
            bayer=args.bayer,
            progress=bar,
        )
        paths = run.save(out)
    cal = run.calibration
    rep = cal.report["summary"]
    print(f"calibrated a {cal.grid[0]}x{cal.grid[1]} camera in {time.perf_counter() - t0:.1f} s")
    print(f"  depth            {rep['depth']} ({rep['depth_model_route']})")
    print(f"  Z_b, Z_c         {cal.z_b:g} m, " + (f"{cal.z_c:.4f} m" if cal.metric else "unknown"))
    print(f"  rectified frame  {cal.rect_shape[1]} x {cal.rect_shape[0]} px (scale {cal.scale:g})")
    if rep.get("parallax_fit_rms_px") is not None:
        print(f"  parallax fit     {rep['parallax_fit_rms_px']:.4f} px rms")
    print("  view    crop x0, y0, w, h       o_i (rectified px)    frame seen  residual")
    for v in cal.report["views"]:
        crop = ", ".join(str(c) for c in v["crop"])
        o = f"({v['offset_px'][0]:8.3f}, {v['offset_px'][1]:8.3f})"
        rc = "({}, {})".format(*v["row_col"])
        print(
            f"  {rc:7} {crop:23} {o}  {100 * v['coverage']:8.1f} %"
            f"  {v['photometric_residual_rms']:.3f}"
        )
    for k, p in paths.items():
        print(f"  {k:16} {p}")
    return EXIT_OK


def _calibrate_zoom(args: argparse.Namespace, out: Path, bar: Any, t0: float) -> int:
    """``lfcam calibrate`` of a folder of zoom settings (``zoom_<f>mm/``)."""
    from .calibration.zoom import run_zoom_calibration

    zrun = run_zoom_calibration(
        args.cal_dir,
        share_warps=False if args.warps_per_setting else None,
        grid=args.grid,
        reference=args.reference,
        reference_distance=args.reference_distance,
        scale=args.scale,
        z_c=args.z_c,
        pattern_pitch=args.pattern_pitch,
        bayer=args.bayer,
        progress=bar,
    )
    paths = zrun.save(out)
    print(f"calibrated {len(zrun.calibrations)} zoom settings in {time.perf_counter() - t0:.1f} s")
    print("  focal length  Z_b, Z_c          warp maps")
    for cal in zrun.calibrations:
        z = cal.report.get("zoom", {})
        diff = z.get("warp_difference_to_first")
        src = z.get("warps_from_mm")
        where = "own" if src == cal.focal_length else f"from {src:g} mm"
        d = f" (differ by {diff['rms_px']:.3f} px rms)" if diff else ""
        zc = f"{cal.z_c:.4f} m" if cal.metric else "unknown"
        print(f"  {cal.focal_length:8g} mm   {cal.z_b:g} m, {zc:10}  {where}{d}")
    for k, p in paths.items():
        print(f"  {k:24} {p}")
    return EXIT_OK


def _add_info(sub: Any) -> None:
    p = _command(
        sub,
        "info",
        examples=["lfcam info camera.lfcal", "lfcam info camera.lfcal | less"],
        help="show what is in a calibration file",
        description=(
            "Print what a calibration file holds: its path, format version, creation "
            "time and SHA-256 (the one result.json files cite), the lenslet grid and "
            "reference view, the raw, rectified and pattern sizes, Z_b and Z_c (metric "
            "or relative depth), the board distances, the pattern pitch, the Bayer "
            "mosaic, a table of the views and the calibration report's summary. The "
            "file's datasets are described in docs/design.md, 'Calibration file'."
        ),
    )
    p.add_argument("calibration", type=Path, metavar="CAMERA.lfcal", help="the calibration file")
    p.set_defaults(func=_cmd_info)


def _cmd_info(args: argparse.Namespace) -> int:
    from .calibration import info

    print(info(args.calibration))
    return EXIT_OK


# ---------------------------------------------------------------------------
# lfcam process
# ---------------------------------------------------------------------------
EXIT_PARTIAL = 3
#: Most processes ``--jobs`` may start, and most ``--orbit`` frames (two minutes of
#: video at 30 frames per second): beyond them a run would not end in reasonable time.
MAX_JOBS = 256
MAX_ORBIT_FRAMES = 3600


def _add_process(sub: Any) -> None:
    p = _command(
        sub,
        "process",
        examples=[
            "lfcam process capture.png -c camera.lfcal -o out/",
            "lfcam process captures/ -c camera.lfcal -o out/ --jobs 2",
            "lfcam process capture.png -c camera.lfcal -o out/ --superres 2 --refocus 0.8,1.5",
            "lfcam process capture.png -c camera.lfcal -o out/ --mesh --novel-view 0.01,0,0",
            "lfcam process captures/ -c camera.lfcal -o out/ --frame full --overwrite",
            "lfcam process captures/ -c camera.lfcal -o out/ --cluster slurm:4",
            "lfcam process captures/ -c zoom.lfcal -o out/ --zoom 75",
        ],
        help="depth (and more) for raw captures",
        description=(
            "Process raw captures with a calibration: rectify, optical flow, triangulate. "
            "INPUT is a file or a folder (searched recursively, sorted). For each capture, "
            "OUT_DIR/<relative path without suffix>/ gets depth.tiff (float32 metres, NaN "
            "unknown), depth.png (preview with a colour bar), confidence.tiff, points.ply "
            "and result.json. Images are in the reference view's rectified frame, cropped "
            "to the part the reference view sees (--frame full: uncropped); result.json "
            "gives the crop offset, and each TIFF says what it holds in its description "
            "(docs/design.md, 'Capture outputs'). A calibration of several zoom settings "
            "gives each capture the setting its EXIF focal length matches within 2% "
            "(--zoom F: the setting of F for every capture); result.json records it. "
            "Complete outputs are skipped unless "
            "--overwrite. A capture that fails (also one whose focal length matches no "
            "setting, or is unknown) is reported and skipped; "
            f"the exit code is then {EXIT_PARTIAL}."
        ),
    )
    p.add_argument("input", type=Path, metavar="INPUT", help="a raw capture or a folder of them")
    p.add_argument(
        "-c",
        "--calibration",
        type=Path,
        required=True,
        metavar="CAMERA.lfcal",
        help="the calibration file",
    )
    p.add_argument(
        "-o", "--output", type=Path, required=True, metavar="OUT_DIR", help="output folder"
    )
    p.add_argument(
        "--zoom",
        type=float,
        metavar="F",
        help="the front lens's focal length in mm for every capture: picks the "
        "calibration's zoom setting within 2%% (default: each capture's EXIF focal length)",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        metavar="N",
        help="captures processed in parallel on this machine",
    )
    p.add_argument(
        "--cluster",
        metavar="WHERE",
        help="run on a Dask cluster (needs lfcam[dask]): a scheduler's address "
        "(tcp://HOST:8786), local:N (N local worker processes), or slurm[:JOBS], pbs, sge, "
        "lsf, htcondor (batch jobs of workers through dask-jobqueue, see --cluster-config)",
    )
    p.add_argument(
        "--cluster-config",
        type=Path,
        metavar="YAML",
        help="Dask configuration for --cluster slurm etc. (jobqueue: slurm: cores: ...; "
        "default: Dask's own, ~/.config/dask/jobqueue.yaml)",
    )
    p.add_argument(
        "--cluster-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="seconds to wait for the scheduler to answer (default 10)",
    )
    p.add_argument("--save-views", action="store_true", help="also write the rectified views")
    p.add_argument(
        "--superres",
        type=int,
        metavar="F",
        help="also write superres.tiff (float32, linear) and superres.png: the reference "
        "view super-resolved F times (1-4)",
    )
    p.add_argument(
        "--refocus",
        type=_floats,
        metavar="Z1,Z2",
        help="also write refocus_<Z>m.tiff and .png, refocused at these distances in metres",
    )
    p.add_argument(
        "--frame",
        choices=("valid", "full"),
        default="valid",
        help="valid (default): crop the products to the reference view's valid bounding "
        "box; full: the calibration's whole rectified frame. result.json records the "
        "crop offset",
    )
    p.add_argument("--overwrite", action="store_true", help="redo complete outputs")
    p.add_argument("--mesh", action="store_true", help="also write mesh.ply (coloured triangles)")
    p.add_argument(
        "--novel-view",
        metavar="TX,TY,TZ[,RX,RY,RZ]",
        help="write novel_view.png from this pose relative to the reference camera: "
        "translation in metres, rotation vector in degrees",
    )
    p.add_argument(
        "--orbit", type=int, default=0, metavar="N", help="write N orbit frames and orbit.mp4"
    )
    p.set_defaults(func=_cmd_process)


def _degenerate_warning(result_json: Path) -> str | None:
    """The warning for a capture whose ``result.json`` says it is degenerate."""
    import json

    from .outputs import degenerate_message

    try:
        return degenerate_message(json.loads(result_json.read_text()))
    except (OSError, ValueError):
        return None


def _novel_options(args: argparse.Namespace, settings: Sequence[Any]) -> Any:
    """--mesh / --novel-view / --orbit as :class:`lfcam.outputs.NovelViewOptions`, for
    captures calibrated by any of ``settings``."""
    import math

    from .outputs import NovelViewOptions
    from .products.geometry import parse_pose

    if not 0 <= args.orbit <= MAX_ORBIT_FRAMES:
        raise InputError(f"--orbit: expected 0 to {MAX_ORBIT_FRAMES} frames, got {args.orbit}")
    pose = None
    if args.novel_view is not None:
        try:
            pose = parse_pose(args.novel_view)
        except InputError as exc:
            raise InputError(f"--novel-view: {exc}") from None
    opts = NovelViewOptions(mesh=args.mesh, pose=pose, orbit=args.orbit)
    if (pose is not None or opts.orbit) and not all(
        cal.metric and math.isfinite(cal.pattern_pitch) for cal in settings
    ):
        raise InputError(
            "--novel-view/--orbit: need a metric calibration with a known pattern pitch"
        )
    return opts


def _process_options(args: argparse.Namespace) -> Any:
    """The options of ``lfcam process``, checked against the calibration, as
    :class:`lfcam.batch.ProcessOptions`. The calibration loaded for the checks is
    dropped on return: the batch loads its own (with --jobs 1 in this process, where a
    second copy of a full-size calibration would add about half a gigabyte)."""
    from .batch import ProcessOptions
    from .calibration import ZoomCalibration
    from .calibration.settings import check_focal_length

    if args.refocus and not all(math.isfinite(z) and z > 0 for z in args.refocus):
        raise InputError(f"--refocus: expected finite distances > 0 m, got {list(args.refocus)}")
    if args.zoom is not None:
        check_focal_length(args.zoom, "--zoom")
    zoom = ZoomCalibration.load(args.calibration)
    # The settings captures may use: --zoom's, else any.
    settings = zoom.settings if args.zoom is None else (zoom.select(args.zoom, "--zoom"),)
    for cal in settings:
        at = f" ({cal.focal_length:g} mm setting)" if math.isfinite(cal.focal_length) else ""
        if args.refocus and cal.metric:
            bad = [z for z in args.refocus if not z > cal.z_c]
            if bad:
                raise InputError(
                    f"--refocus: distances must be beyond Z_c = {cal.z_c:.3f} m{at}: {bad}"
                )
        elif args.refocus:
            raise InputError(
                f"--refocus: the calibration{at} is relative (no Z_c): no metric focus"
            )
    return ProcessOptions(
        save_views=args.save_views,
        superres=args.superres,
        refocus=tuple(args.refocus or ()),
        novel=_novel_options(args, settings),
        overwrite=args.overwrite,
        frame=args.frame,
        focal_length=args.zoom,
    )


def _cmd_process(args: argparse.Namespace) -> int:
    from .batch import process_folder

    if not 1 <= args.jobs <= MAX_JOBS:
        raise InputError(f"--jobs: expected 1 to {MAX_JOBS}, got {args.jobs}")
    if args.superres is not None and not (1 <= args.superres <= 4):
        raise InputError(f"--superres: expected a factor from 1 to 4, got {args.superres}")
    _check_output_folder(args.output, "-o")
    options = _process_options(args)
    if args.cluster is not None and args.jobs != 1:
        raise InputError("--jobs: not with --cluster (the cluster's workers run the captures)")
    if not args.cluster_timeout > 0:
        raise InputError(f"--cluster-timeout: must be > 0, got {args.cluster_timeout}")

    with contextlib.ExitStack() as stack:
        client = None
        if args.cluster is not None:
            from .batch.cluster import cluster_client

            client = stack.enter_context(
                cluster_client(
                    args.cluster, config=args.cluster_config, timeout=args.cluster_timeout
                )
            )
            print(f"dask cluster {args.cluster}: dashboard {client.dashboard_link}", flush=True)
        bars: list[Progress] = []
        stack.callback(lambda: [bar.close() for bar in bars])

        def progress(outcome: Any, finished: int, total: int) -> None:
            # Done / total, rate and ETA over the captures that need work.
            if not bars:  # the total is known once the folder is scanned
                bars.append(_progress(args, total, "process", unit="capture"))
            if outcome.status == "skipped":
                bars[0].skip()
            else:
                bars[0].step(f"{outcome.source} {outcome.status}")

        summary = process_folder(
            args.input,
            args.calibration,
            args.output,
            client=client,
            jobs=args.jobs,
            options=options,
            progress=progress,
        )
    done, skipped, failures = summary.done, summary.skipped, summary.failed
    print(
        f"processed {len(done)} capture(s) in {summary.seconds:.1f} s"
        + (f", skipped {len(skipped)} complete" if skipped else "")
        + (f", {len(failures)} FAILED" if failures else "")
        + f" -> {args.output}"
    )
    for o in summary.outcomes:
        warn = o.status == "done" and _degenerate_warning(Path(o.out) / "result.json")
        if warn:
            print(f"lfcam process: warning: {o.source}: {warn}", file=sys.stderr)
    for src, err in failures:
        print(f"  failed: {src}: {err}", file=sys.stderr)
    return EXIT_PARTIAL if failures else EXIT_OK


# ---------------------------------------------------------------------------
# lfcam depth-views
# ---------------------------------------------------------------------------
def _add_depth_views(sub: Any) -> None:
    p = _command(
        sub,
        "depth-views",
        examples=[
            "lfcam depth-views hci4d_antinous/ -o antinous/",
            "lfcam depth-views hci4d_antinous/ -o antinous_3x4/ --views 3:6,3:7 --reference 4,4",
            "lfcam depth-views lytro_2067/ -o lytro/ --views 3:8,3:8",
            "lfcam depth-views rig/ -o rig_depth/ --flip x --overwrite",
        ],
        help="depth of a folder of rectified views (HCI 4D light field, row_col images)",
        description=(
            "Depth from a light field made elsewhere: a folder of already-rectified views "
            "on a regular grid, either the HCI 4D benchmark's layout (input_CamNNN.png, "
            "parameters.cfg, optional gt_disp_lowres.pfm) or images named by row and "
            "column (03_04.png, view_3_4.png; a shared numeric prefix is allowed, as in "
            "Lytro exports: 2067_05_05.png). Runs the depth chain of 'lfcam process' "
            "(optical flow from the reference view, triangulation) and writes OUT_DIR/ "
            "with disparity.tiff and disparity.pfm (px per grid step, HCI sign: positive "
            "nearer than the zero-parallax plane), disparity.png, confidence.tiff and "
            "result.json; with the rig's parameters.cfg also depth.tiff (metres), "
            "depth.png and points.ply. With ground truth for the reference view, "
            "result.json has BadPix0.07 and MSE*100 (full image and without a 15 px "
            "border). OUT_DIR appears complete or not at all."
        ),
    )
    p.add_argument("folder", type=Path, metavar="FOLDER", help="the folder of views")
    p.add_argument(
        "-o", "--output", type=Path, required=True, metavar="OUT_DIR", help="output folder"
    )
    p.add_argument(
        "--views",
        metavar="ROWS,COLS",
        help="subset ROWS,COLS as Python slices of grid indices, e.g. 3:6,3:7 (default: all)",
    )
    p.add_argument(
        "--reference",
        type=_rc,
        metavar="ROW,COL",
        help="reference view, absolute grid indices (default: the grid's centre)",
    )
    p.add_argument(
        "--flip",
        choices=("x", "y", "xy"),
        default="",
        help="grid axes numbered against the HCI convention: x if a larger column means "
        "the camera sits further left, y if a larger row means further up",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT_DIR")
    p.set_defaults(func=_cmd_depth_views)


def _cmd_depth_views(args: argparse.Namespace) -> int:
    from .outputs import degenerate_message, write_lightfield
    from .sim import HCI_BORDER, LightField

    out: Path = args.output
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:
        raise InputError(f"{out}: exists (use --overwrite to replace it)")
    t0 = time.perf_counter()
    with _progress(args, 3, "depth-views") as bar:
        lf = LightField.from_folder(args.folder, args.views, args.reference, flip=args.flip)
        t1 = time.perf_counter()
        bar.step(f"read {lf.n_views} views")
        res = lf.estimate_depth(threads=max(1, os.cpu_count() or 1))
        t2 = time.perf_counter()
        bar.step("depth")
        _, info = write_lightfield(
            out,
            lf,
            res,
            timings={"read": t1 - t0, "depth": t2 - t1},
            extra={"command": "depth-views"},
        )
        t3 = time.perf_counter()
        bar.step(f"wrote {out}")
    stats = info["statistics"]
    warn = degenerate_message(info)
    if warn:
        print(f"lfcam depth-views: warning: {args.folder}: {warn}", file=sys.stderr)
    h, w = lf.image_shape
    print(
        f"depth of a {lf.grid_shape[0]}x{lf.grid_shape[1]} light field ({w} x {h} px,"
        f" {lf.layout} layout) in {t3 - t0:.1f} s -> {out}"
    )
    print(
        f"  views            rows {lf.rows[0]}..{lf.rows[-1]}, cols {lf.cols[0]}..{lf.cols[-1]},"
        f" reference {lf.reference_rc}"
    )
    if stats["disparity_p1_p99_px"] is not None:
        lo, hi = stats["disparity_p1_p99_px"]
        print(
            f"  disparity        {lo:.3f} .. {hi:.3f} px (1st-99th percentile),"
            f" coverage {100 * stats['coverage']:.1f} %"
        )
    if info["metric"] and stats.get("depth_p1_p99_m") is not None:
        lo, hi = stats["depth_p1_p99_m"]
        print(f"  depth            {lo:.3f} .. {hi:.3f} m")
    elif not info["metric"]:
        print("  depth            not computed: no rig parameters (parameters.cfg)")
    gt = info.get("ground_truth")
    if gt is not None and "full" in gt:
        for key, label in (("full", "full image"), (f"without_{HCI_BORDER}px_border", "")):
            m = gt[key]
            label = label or f"without {HCI_BORDER} px border"
            print(
                f"  vs ground truth  BadPix0.07 {m['badpix_percent']:.2f} %,"
                f" MSE*100 {m['mse_x100'] if m['mse_x100'] is not None else float('nan'):.3f}"
                f" ({label})"
            )
    elif gt is not None:
        print(f"  ground truth     of view {tuple(gt['view'])}, not the reference: not scored")
    return EXIT_OK


# ---------------------------------------------------------------------------
# lfcam demo
# ---------------------------------------------------------------------------
def _add_demo(sub: Any) -> None:
    p = _command(
        sub,
        "demo",
        examples=[
            "lfcam demo",
            "lfcam demo /tmp/lfcam-demo --seed 3 --overwrite",
        ],
        help="simulate, calibrate and process a camera; print accuracy against the truth",
        description=(
            "The whole job on the built-in simulated camera: simulate a 3x4 camera with "
            "three scenes, calibrate it, compute depth for every scene and compare with "
            "the ground truth."
        ),
    )
    p.add_argument(
        "out_dir",
        type=Path,
        nargs="?",
        default=None,
        metavar="OUT_DIR",
        help="output folder (default: lfcam-demo in the system's temporary folder)",
    )
    p.add_argument(
        "--seed", type=int, default=0, metavar="S", help="random seed of the simulated camera"
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="320x240 px views and one scene: checks an installation in a fraction of the time",
    )
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUT_DIR")
    p.set_defaults(func=_cmd_demo)


def _default_demo_dir() -> Path:
    """The demo's default output: outside any source tree, in the temporary folder."""
    import tempfile

    return Path(tempfile.gettempdir()) / "lfcam-demo"


def _cmd_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from .calibration import run_calibration
    from .io import file_hash, read_image
    from .outputs import write_capture
    from .pipeline import process_capture
    from .sim import SimConfig, depth_accuracy, simulate

    out: Path = args.out_dir if args.out_dir is not None else _default_demo_dir()
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise InputError(f"{out}: folder is not empty (use --overwrite)")
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    if args.quick:
        # Smaller views, one scene: a check that an installation works end to end.
        cfg = SimConfig(
            view_size=(320, 240), scenes=("planes",), captures_per_distance=3, seed=args.seed
        )
    else:
        cfg = SimConfig(captures_per_distance=3, seed=args.seed)
    n_steps = 2 + len(cfg.scenes)
    with _progress(args, n_steps, "demo") as bar:
        sim = simulate(out / "sim", cfg, overwrite=True)
        bar.step("simulated the camera")
        run = run_calibration(sim.calibration_dir)
        paths = run.save(out / "camera.lfcal")
        bar.step("calibrated")
        cal = run.calibration
        cal_info = {
            "calibration": str(paths["calibration"]),
            "calibration_sha256": file_hash(paths["calibration"]),
        }
        rows = []
        for name, raw in sim.captures.items():
            res = process_capture(raw, cal)
            folder = write_capture(out / "results" / name, res, cal, extra=cal_info)
            truth = read_image(sim.truth_dir / name / "depth.tiff")
            z = res.depth.depth
            assert z is not None
            med, bad, cov = depth_accuracy(z, truth, cal.masks[cal.reference])
            rows.append(
                (
                    name,
                    med,
                    bad,
                    cov,
                    res.timings["total"],
                    folder,
                )
            )
            bar.step(f"depth of {name}")
    truth_cam = np.load(sim.truth_dir / "camera.npz")
    print(f"lfcam demo: simulated, calibrated and processed in {time.perf_counter() - t_all:.0f} s")
    o_err = np.abs(cal.offsets - truth_cam["offsets"]).max()
    print(
        f"  calibration  Z_c {cal.z_c:.4f} m (true {float(truth_cam['z_c']):.4f}),"
        f" o_i within {o_err:.3f} px of the truth -> {paths['calibration']}"
    )
    print("  scene      median |dZ|/Z   pixels off >5%   coverage   seconds")
    for name, med, bad, cov, sec, _ in rows:
        print(
            f"  {name:10} {100 * med:10.2f} %  {100 * bad:12.2f} %  {100 * cov:8.1f} %  {sec:7.1f}"
        )
    print("  pictures:")
    print(f"    calibration report  {paths['report_html']}")
    for name, *_, folder in rows:
        print(f"    {name:19} {folder / 'depth.png'}")
    return EXIT_OK


# ---------------------------------------------------------------------------
class _VersionAction(argparse.Action):
    """``--version``: the version and the code paths this machine runs
    (:func:`lfcam.build_info`), read only when asked."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *_: Any, **__: Any) -> None:
        from ._build import describe_build

        sys.stdout.write(describe_build() + "\n")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    """The ``lfcam`` argument parser (all subcommands)."""
    parser = _Parser(
        prog="lfcam",
        description="Multiview light-field camera: simulate, calibrate, process.",
        epilog="Each command's --help has examples. docs/design.md describes the method.",
    )
    parser.add_argument(
        "--version",
        action=_VersionAction,
        help="show the version, the SIMD code paths in use on this machine, and exit",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_simulate(sub)
    _add_pattern(sub)
    _add_calibrate(sub)
    _add_info(sub)
    _add_process(sub)
    _add_depth_views(sub)
    _add_demo(sub)
    return parser


#: Exit code after the reader of the output went away (128 + SIGPIPE, as the shell
#: reports for a program ended by a closed pipe).
EXIT_PIPE = 141


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfcam`` command line; returns the exit code.

    A closed standard output (``lfcam info X | head``) ends the command quietly with
    exit code 141, as for programs that the shell sees killed by SIGPIPE.
    """
    try:
        try:
            return _main(argv)
        except SystemExit:  # --help, --version, usage errors: their text is still buffered
            sys.stdout.flush()
            raise
    except BrokenPipeError:
        # Later writes (and the interpreter's final flush) go nowhere instead of
        # raising again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass  # stdout is not a file (a test's capture): nothing to silence
        finally:
            os.close(devnull)
        return EXIT_PIPE


def _main(argv: Sequence[str] | None) -> int:
    for stream in (sys.stdout, sys.stderr):
        # A file name with bytes that are not UTF-8 is printed escaped, never a crash.
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None:
            reconfigure(errors="backslashreplace")
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_INPUT
    configure_logging(quiet=args.quiet)
    try:
        code: int = args.func(args)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return code
    except BrokenPipeError:
        raise
    except InputError as exc:
        print(f"lfcam {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except OSError as exc:
        print(f"lfcam {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print(f"lfcam {args.command}: interrupted", file=sys.stderr)
        return 130
    except CalibrationError as exc:
        print(f"lfcam {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except LfcamError as exc:
        print(f"lfcam {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_INTERNAL
    except Exception as exc:  # a bug: say so plainly, with a hint for reporting
        if os.environ.get("LFCAM_DEBUG"):
            raise
        print(
            f"lfcam {args.command}: internal error: {type(exc).__name__}: {exc}\n"
            "  (set LFCAM_DEBUG=1 for the traceback, and please report it)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
