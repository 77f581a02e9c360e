"""The ``lfcam`` command line: parse, report progress, set exit codes.

Exit codes: 0 success, 2 bad input (a clear message names the file or
argument), 1 an unexpected internal error.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .errors import CalibrationError, InputError, LfcamError

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2


def _pair(text: str, sep: str, name: str) -> tuple[int, int]:
    parts = text.lower().split(sep)
    try:
        a, b = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{name}: expected two integers as A{sep}B, got {text!r}"
        ) from None
    return a, b


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def _progress(total: int, desc: str) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", file=sys.stderr, disable=None, leave=False)


# ---------------------------------------------------------------------------
# lfcam simulate
# ---------------------------------------------------------------------------
def _add_simulate(sub: Any) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate a camera: calibration captures and scenes with ground truth",
        description=(
            "Render a simulated light-field camera (docs/design.md, 'Simulator'): a calibration "
            "folder (pattern, white and board captures) and scene captures, with ground "
            "truth (warp maps, o_i, Z_c, depth, 2x reference image). Camera parameters "
            "come from --config (TOML, keys as in lfcam.SimConfig) and the flags below, "
            "which override it."
        ),
    )
    p.add_argument("out_dir", type=Path, help="output folder (must be new or empty)")
    p.add_argument("--config", type=Path, help="TOML file of camera parameters")
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--grid", type=lambda t: _pair(t, "x", "--grid"), help="lenslet grid, e.g. 3x4")
    p.add_argument(
        "--view-size",
        type=lambda t: _pair(t, "x", "--view-size"),
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
    p.add_argument("--scenes", help="comma-separated scenes: planes, spheres, layered, board")
    p.add_argument("--distances", type=_floats, help="board distances in metres, e.g. 0.8,1,1.25")
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
    p.add_argument("--captures", type=int, help="board captures per distance (default 5)")
    p.add_argument("--no-truth", action="store_true", help="skip the ground truth")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty out_dir")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from .sim import SimConfig, simulate

    changes: dict[str, Any] = {}
    if args.full_size:
        changes["view_size"] = (1200, 900)
    keys = ("seed", "grid", "view_size", "bit_depth", "bayer", "raw_format", "distances")
    for key in (*keys, "board_tilt", "board_drift"):
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
    steps = 4 + len(cfg.distances) + len(cfg.scenes) + (0 if args.no_truth else 1)
    t0 = time.perf_counter()
    with _progress(steps, "simulate") as bar:

        def step(msg: str) -> None:
            bar.set_postfix_str(msg)
            bar.update(1)

        res = simulate(
            args.out_dir, cfg, overwrite=args.overwrite, truth=not args.no_truth, progress=step
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
    p = sub.add_parser(
        "pattern",
        help="write the digital calibration pattern",
        description=(
            "Write the calibration pattern: dense multi-scale texture with a cross at the "
            "centre. Show it full screen on a monitor at native resolution (one pattern "
            "pixel per screen pixel), or print it unscaled on a rigid flat board; the "
            "size of one pattern pixel on the board in metres is the pattern pitch."
        ),
    )
    p.add_argument("out", type=Path, help="output image (.png, .tif or .tiff)")
    p.add_argument("--width", type=int, required=True, help="width in pixels")
    p.add_argument("--height", type=int, required=True, help="height in pixels")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
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
    return _pair(text, ",", "--reference")


def _add_calibrate(sub: Any) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate a camera from white and board captures",
        description=(
            "Calibrate a camera (docs/design.md, 'Calibration pipeline') from CAL_DIR: "
            "pattern.png, white/*, "
            "board_<distance>m/* (one or more distances; three or more, or two plus the "
            "optical centres, give metric depth with no optics known), and an optional "
            "camera.toml (grid, reference, z_c, pattern_pitch, bayer), which the flags "
            "override. Writes CAMERA.lfcal, CAMERA.report.json and CAMERA.report.png."
        ),
    )
    p.add_argument("cal_dir", type=Path, help="the calibration folder")
    p.add_argument("-o", "--output", type=Path, required=True, help="CAMERA.lfcal to write")
    p.add_argument("--grid", type=lambda t: _pair(t, "x", "--grid"), help="lenslet grid, e.g. 3x4")
    p.add_argument("--reference", type=_rc, help="reference view ROW,COL (zero-based)")
    p.add_argument("--reference-distance", type=float, help="Z_b, metres (default: nearest 1 m)")
    p.add_argument("--scale", type=float, help="rectified px per pattern px (default: ~1 raw px)")
    p.add_argument("--z-c", type=float, help="Z_c = f D / (D - f) in metres, if known")
    p.add_argument("--pattern-pitch", type=float, help="metres per pattern pixel on the board")
    p.add_argument("--bayer", choices=("RGGB", "BGGR", "GRBG", "GBRG"), help="Bayer raw")
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
    steps = ["layout", "scale", "warp", "depth"]
    t0 = time.perf_counter()
    with _progress(len(steps) + 3, "calibrate") as bar:

        def step(msg: str) -> None:
            bar.set_postfix_str(msg)
            bar.update(1)

        run = run_calibration(
            args.cal_dir,
            grid=args.grid,
            reference=args.reference,
            reference_distance=args.reference_distance,
            scale=args.scale,
            z_c=args.z_c,
            pattern_pitch=args.pattern_pitch,
            bayer=args.bayer,
            progress=step,
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


def _add_info(sub: Any) -> None:
    p = sub.add_parser("info", help="show what is in a calibration file")
    p.add_argument("calibration", type=Path, help="CAMERA.lfcal")
    p.set_defaults(func=_cmd_info)


def _cmd_info(args: argparse.Namespace) -> int:
    from .calibration import info

    print(info(args.calibration))
    return EXIT_OK


# ---------------------------------------------------------------------------
# lfcam process
# ---------------------------------------------------------------------------
EXIT_PARTIAL = 3


def _add_process(sub: Any) -> None:
    p = sub.add_parser(
        "process",
        help="depth (and more) for raw captures",
        description=(
            "Process raw captures with a calibration: rectify, optical flow, triangulate. "
            "INPUT is a file or a folder (searched recursively, sorted). For each capture, "
            "OUT_DIR/<relative path without suffix>/ gets depth.tiff (float32 metres, NaN "
            "unknown, the reference view's rectified frame), depth.png (preview with a "
            "colour bar), confidence.tiff, points.ply and result.json. Complete outputs "
            "are skipped unless --overwrite. A capture that fails is reported and skipped; "
            f"the exit code is then {EXIT_PARTIAL}."
        ),
    )
    p.add_argument("input", type=Path, help="a raw capture or a folder of them")
    p.add_argument("-c", "--calibration", type=Path, required=True, help="CAMERA.lfcal")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    p.add_argument("--jobs", type=int, default=1, help="captures processed in parallel")
    p.add_argument("--save-views", action="store_true", help="also write the rectified views")
    p.add_argument(
        "--superres",
        type=int,
        metavar="F",
        help="also write superres.png: the reference view super-resolved F times (1-4)",
    )
    p.add_argument(
        "--refocus",
        type=_floats,
        metavar="Z1,Z2",
        help="also write refocus_<Z>m.png, refocused at these distances in metres",
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


def _find_captures(path: Path, out_dir: Path) -> list[tuple[Path, Path]]:
    """(capture, its output folder) pairs, sorted."""
    from .io import is_image_file

    if path.is_file():
        return [(path, out_dir / path.stem)]
    if not path.is_dir():
        raise InputError(f"{path}: no such file or folder")
    out_res = out_dir.resolve()
    found = []
    for p in sorted(path.rglob("*")):
        if not is_image_file(p):
            continue
        if out_res in p.resolve().parents:
            continue
        found.append((p, out_dir / p.relative_to(path).with_suffix("")))
    if not found:
        raise InputError(f"{path}: no raw captures (PNG, TIFF, JPEG or camera raw) found")
    return found


_WORKER: dict[str, Any] = {}


def _worker_init(cal_path: str, threads: int) -> None:
    import cv2

    from . import set_num_threads
    from .calibration import Calibration

    set_num_threads(threads)
    cv2.setNumThreads(threads)
    _WORKER["cal"] = Calibration.load(cal_path)
    _WORKER["threads"] = threads


def _process_one(
    src: str, dst: str, extra: dict[str, Any], save_views: bool, novel: Any = None
) -> tuple[str, str | None]:
    from .outputs import write_capture
    from .pipeline import process_capture

    try:
        cal = _WORKER["cal"]
        products = extra.get("products", {})
        res = process_capture(
            src,
            cal,
            threads=_WORKER["threads"],
            superres=products.get("superres"),
            refocus=products.get("refocus") or (),
        )
        write_capture(dst, res, cal, extra=extra, save_views=save_views, novel=novel)
        return src, None
    except (LfcamError, OSError, ValueError) as exc:
        return src, str(exc)


def _novel_options(args: argparse.Namespace, cal: Any) -> Any:
    """--mesh / --novel-view / --orbit as :class:`lfcam.outputs.NovelViewOptions`."""
    import math

    from .outputs import NovelViewOptions
    from .products.geometry import parse_pose

    if args.orbit < 0:
        raise InputError(f"--orbit: must be >= 0, got {args.orbit}")
    pose = None
    if args.novel_view is not None:
        try:
            pose = parse_pose(args.novel_view)
        except InputError as exc:
            raise InputError(f"--novel-view: {exc}") from None
    opts = NovelViewOptions(mesh=args.mesh, pose=pose, orbit=args.orbit)
    if (pose is not None or opts.orbit) and not (cal.metric and math.isfinite(cal.pattern_pitch)):
        raise InputError(
            "--novel-view/--orbit: need a metric calibration with a known pattern pitch"
        )
    return opts


def _cmd_process(args: argparse.Namespace) -> int:
    from .calibration import Calibration
    from .io import file_hash

    if args.jobs < 1:
        raise InputError(f"--jobs: must be >= 1, got {args.jobs}")
    if args.superres is not None and not (1 <= args.superres <= 4):
        raise InputError(f"--superres: expected a factor from 1 to 4, got {args.superres}")
    cal = Calibration.load(args.calibration)
    if args.refocus and cal.metric:
        bad = [z for z in args.refocus if not z > cal.z_c]
        if bad:
            raise InputError(f"--refocus: distances must be beyond Z_c = {cal.z_c:.3f} m: {bad}")
    elif args.refocus:
        raise InputError("--refocus: the calibration is relative (no Z_c): no metric focus")
    novel = _novel_options(args, cal)
    pairs = _find_captures(args.input, args.output)
    todo = [(s, d) for s, d in pairs if args.overwrite or not (d / "result.json").is_file()]
    skipped = len(pairs) - len(todo)
    args.output.mkdir(parents=True, exist_ok=True)
    cores = os.cpu_count() or 1
    jobs = min(args.jobs, max(1, len(todo)))
    threads = max(1, cores // jobs)
    extra = {
        "calibration": str(args.calibration),
        "calibration_sha256": file_hash(args.calibration),
        "parameters": {"interp": "bilinear", "jobs": jobs, "threads": threads},
    }
    if args.superres is not None or args.refocus:
        extra["products"] = {"superres": args.superres, "refocus": list(args.refocus or [])}
    failures: list[tuple[str, str]] = []
    t0 = time.perf_counter()
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc="process", unit="capture", file=sys.stderr, disable=None)
    if jobs == 1:
        _WORKER.update(cal=cal, threads=threads)
        for s, d in todo:
            src, err = _process_one(str(s), str(d), extra, args.save_views, novel)
            if err:
                failures.append((src, err))
            bar.update(1)
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        # "spawn": a forked child inherits OpenCV's and BLAS's thread pools in an
        # undefined state and can hang; fresh interpreters are safe everywhere.
        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(
            jobs,
            mp_context=ctx,
            initializer=_worker_init,
            initargs=(str(args.calibration), threads),
        ) as ex:
            futs = [
                ex.submit(_process_one, str(s), str(d), extra, args.save_views, novel)
                for s, d in todo
            ]
            for f in futs:
                src, err = f.result()
                if err:
                    failures.append((src, err))
                bar.update(1)
    bar.close()
    done = len(todo) - len(failures)
    print(
        f"processed {done} capture(s) in {time.perf_counter() - t0:.1f} s"
        + (f", skipped {skipped} complete" if skipped else "")
        + (f", {len(failures)} FAILED" if failures else "")
        + f" -> {args.output}"
    )
    for src, err in failures:
        print(f"  failed: {src}: {err}", file=sys.stderr)
    return EXIT_PARTIAL if failures else EXIT_OK


# ---------------------------------------------------------------------------
# lfcam depth-views
# ---------------------------------------------------------------------------
def _add_depth_views(sub: Any) -> None:
    p = sub.add_parser(
        "depth-views",
        help="depth of a folder of rectified views (HCI 4D light field, row_col images)",
        description=(
            "Depth from a light field made elsewhere: a folder of already-rectified views "
            "on a regular grid, either the HCI 4D benchmark's layout (input_CamNNN.png, "
            "parameters.cfg, optional gt_disp_lowres.pfm) or images named by row and "
            "column (03_04.png, view_3_4.png). Runs the depth chain of 'lfcam process' "
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
    from .outputs import write_lightfield
    from .sim import HCI_BORDER, LightField

    out: Path = args.output
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:
        raise InputError(f"{out}: exists (use --overwrite to replace it)")
    t0 = time.perf_counter()
    lf = LightField.from_folder(args.folder, args.views, args.reference, flip=args.flip)
    t1 = time.perf_counter()
    res = lf.estimate_depth(threads=max(1, os.cpu_count() or 1))
    t2 = time.perf_counter()
    _, info = write_lightfield(
        out,
        lf,
        res,
        timings={"read": t1 - t0, "depth": t2 - t1},
        extra={"command": "depth-views"},
    )
    t3 = time.perf_counter()
    stats = info["statistics"]
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
    p = sub.add_parser(
        "demo",
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
        default=Path("lfcam-demo"),
        help="output folder (default ./lfcam-demo)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulated camera")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty out_dir")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    import numpy as np
    import tifffile

    from .calibration import run_calibration
    from .outputs import write_capture
    from .pipeline import process_capture
    from .sim import SimConfig, depth_accuracy, simulate

    out: Path = args.out_dir
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise InputError(f"{out}: folder is not empty (use --overwrite)")
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    cfg = SimConfig(captures_per_distance=3, seed=args.seed)
    n_steps = 3 + len(cfg.scenes)
    with _progress(n_steps, "demo") as bar:
        bar.set_postfix_str("simulating the camera")
        sim = simulate(out / "sim", cfg, overwrite=True)
        bar.update(1)
        bar.set_postfix_str("calibrating")
        run = run_calibration(sim.calibration_dir)
        paths = run.save(out / "camera.lfcal")
        bar.update(1)
        cal = run.calibration
        rows = []
        for name, raw in sim.captures.items():
            bar.set_postfix_str(f"depth of {name}")
            res = process_capture(raw, cal)
            folder = write_capture(out / "results" / name, res, cal)
            truth = tifffile.imread(sim.truth_dir / name / "depth.tiff")
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
            bar.update(1)
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
    print(f"    calibration report  {paths['report_png']}")
    for name, *_, folder in rows:
        print(f"    {name:19} {folder / 'depth.png'}")
    return EXIT_OK


# ---------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The ``lfcam`` argument parser (all subcommands)."""
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="lfcam",
        description="Multiview light-field camera: simulate, calibrate, process.",
    )
    parser.add_argument("--version", action="version", version=f"lfcam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_simulate(sub)
    _add_pattern(sub)
    _add_calibrate(sub)
    _add_info(sub)
    _add_process(sub)
    _add_depth_views(sub)
    _add_demo(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfcam`` command line; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_INPUT
    try:
        code: int = args.func(args)
        return code
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
