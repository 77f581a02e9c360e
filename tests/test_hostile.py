"""Hostile input, as a table: command-line and API cases that must each fail cleanly.

Every case asserts the exit code (command line) or the exception type (API), that the
message names the file or argument at fault, that no traceback reaches the user, and
that nothing is left behind (no file appears, hidden temporary files included).
docs/robustness.md lists what is checked and how.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tifffile

import lfcam
from lfcam.calibration.calibrate import run_calibration
from lfcam.cli import main
from lfcam.errors import CalibrationError, InputError
from lfcam.sim import SimConfig


@dataclass
class Ctx:
    sim_dir: Path
    cal_dir: Path
    cal_path: Path
    capture: Path
    cal: lfcam.Calibration
    raw: np.ndarray
    res: lfcam.pipeline.CaptureResult


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> Ctx:
    root = tmp_path_factory.mktemp("hostile")
    cfg = SimConfig(
        view_size=(200, 150), captures_per_distance=2, white_captures=2, scenes=("layered",), seed=3
    )
    sim = lfcam.simulate(root / "sim", cfg, truth=False)
    run = run_calibration(sim.calibration_dir)
    cal_path = run.save(root / "cam.lfcal")["calibration"]
    capture = sim.captures["layered"]
    raw = lfcam.read_raw(capture)
    res = lfcam.process_capture(raw, run.calibration)
    return Ctx(root / "sim", sim.calibration_dir, cal_path, capture, run.calibration, raw, res)


def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if not p.is_dir()}


# --------------------------------------------------------------------------- command line

# A case builds its inputs in ``tmp`` and returns (argv, words the message must contain).
CliBuild = Callable[[Ctx, Path], tuple[list[str], list[str]]]


def _flip_byte(src: Path, dst: Path, at: int) -> Path:
    data = bytearray(src.read_bytes())
    data[at % len(data)] ^= 0x10
    dst.write_bytes(bytes(data))
    return dst


def _png_header(dst: Path, width: int, height: int) -> Path:
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    crc = zlib.crc32(b"IHDR" + ihdr) & 0xFFFFFFFF
    dst.write_bytes(
        b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", crc)
    )
    return dst


def _bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _image(path: Path, img: np.ndarray) -> Path:
    lfcam.io.write_image(path, img)
    return path


def _folder(path: Path) -> Path:
    path.mkdir()
    return path


def _cal_copy(c: Ctx, tmp: Path, toml: str | None = None) -> Path:
    dst = tmp / "cal"
    shutil.copytree(c.cal_dir, dst)
    if toml is not None:
        (dst / "camera.toml").write_text(toml)
    return dst


def _with_junk_white(cal_dir: Path) -> Path:
    _bytes(cal_dir / "white" / f"{BAD_NAME}.png", b"\x89PNG\r\n\x1a\n junk")
    return cal_dir


def _views_folder(tmp: Path, size: int, grid: int = 3) -> Path:
    d = tmp / "views"
    d.mkdir()
    rng = np.random.default_rng(0)
    for r in range(grid):
        for c in range(grid):
            img = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
            lfcam.io.write_image(d / f"{r:02d}_{c:02d}.png", img)
    return d


def _proc(c: Ctx, tmp: Path, *extra: str, src: Path | None = None) -> list[str]:
    return ["process", str(src or c.capture), "-c", str(c.cal_path), "-o", str(tmp / "out"), *extra]


def _cal(c: Ctx, tmp: Path, *extra: str, cal_dir: Path | None = None) -> list[str]:
    return ["calibrate", str(cal_dir or c.cal_dir), "-o", str(tmp / "cam.lfcal"), *extra]


BAD_NAME = os.fsdecode(b"bad\xff\xfe")

CLI_CASES: dict[str, tuple[CliBuild, int]] = {
    # process: files
    "process-missing-input": (
        lambda c, t: (_proc(c, t, src=t / "none.png"), ["none.png", "no such file"]),
        2,
    ),
    "process-missing-cal": (
        lambda c, t: (
            ["process", str(c.capture), "-c", str(t / "no.lfcal"), "-o", str(t / "o")],
            ["no.lfcal"],
        ),
        2,
    ),
    "process-cal-not-hdf5": (
        lambda c, t: (
            [
                "process",
                str(c.capture),
                "-c",
                str(_bytes(t / "j.lfcal", b"junk" * 100)),
                "-o",
                str(t / "o"),
            ],
            ["j.lfcal", "not an HDF5 file"],
        ),
        2,
    ),
    "process-cal-one-byte-changed": (
        lambda c, t: (
            [
                "process",
                str(c.capture),
                "-c",
                str(_flip_byte(c.cal_path, t / "f.lfcal", 5000)),
                "-o",
                str(t / "o"),
            ],
            ["f.lfcal", "checksum"],
        ),
        2,
    ),
    "process-cal-user-block-changed": (
        lambda c, t: (
            [
                "process",
                str(c.capture),
                "-c",
                str(_flip_byte(c.cal_path, t / "u.lfcal", 40)),
                "-o",
                str(t / "o"),
            ],
            ["u.lfcal", "checksum"],
        ),
        2,
    ),
    "process-cal-is-folder": (
        lambda c, t: (
            ["process", str(c.capture), "-c", str(t), "-o", str(t / "o")],
            [str(t), "folder"],
        ),
        2,
    ),
    "process-empty-folder": (
        lambda c, t: (_proc(c, t, src=_folder(t / "empty")), ["empty", "no raw captures"]),
        2,
    ),
    "process-huge-header": (
        lambda c, t: (
            _proc(c, t, src=_png_header(t / "huge.png", 65535, 65535)),
            ["huge.png", "larger"],
        ),
        3,
    ),
    "process-bad-name-junk": (
        lambda c, t: (
            _proc(c, t, src=_bytes(t / f"{BAD_NAME}.png", b"\x89PNG junk")),
            ["bad", ".png", "not a readable PNG"],
        ),
        3,
    ),
    "process-truncated-capture": (
        lambda c, t: (
            _proc(c, t, src=_bytes(t / "cut.png", c.capture.read_bytes()[:2000])),
            ["cut.png"],
        ),
        3,
    ),
    "process-wrong-size-capture": (
        lambda c, t: (
            _proc(c, t, src=_image(t / "small.png", np.zeros((50, 60, 3), np.uint8))),
            ["small.png", "raw", "the calibration expects"],
        ),
        3,
    ),
    "process-grey-capture-rgb-cal": (
        lambda c, t: (
            _proc(c, t, src=_image(t / "grey.png", c.raw[..., 1])),
            ["grey.png", "channel"],
        ),
        3,
    ),
    "process-jobs-0": (lambda c, t: (_proc(c, t, "--jobs", "0"), ["--jobs"]), 2),
    "process-jobs-negative": (lambda c, t: (_proc(c, t, "--jobs", "-3"), ["--jobs"]), 2),
    "process-jobs-huge": (lambda c, t: (_proc(c, t, "--jobs", "100000"), ["--jobs"]), 2),
    "process-superres-9": (lambda c, t: (_proc(c, t, "--superres", "9"), ["--superres"]), 2),
    "process-superres-0": (lambda c, t: (_proc(c, t, "--superres", "0"), ["--superres"]), 2),
    "process-refocus-negative": (lambda c, t: (_proc(c, t, "--refocus", "-1"), ["--refocus"]), 2),
    "process-refocus-nan": (lambda c, t: (_proc(c, t, "--refocus", "nan"), ["--refocus"]), 2),
    "process-refocus-inf": (lambda c, t: (_proc(c, t, "--refocus", "inf"), ["--refocus"]), 2),
    "process-refocus-text": (lambda c, t: (_proc(c, t, "--refocus", "far"), ["--refocus"]), 2),
    "process-orbit-negative": (lambda c, t: (_proc(c, t, "--orbit", "-1"), ["--orbit"]), 2),
    "process-orbit-huge": (lambda c, t: (_proc(c, t, "--orbit", "100000"), ["--orbit"]), 2),
    "process-novel-view-overflow": (
        lambda c, t: (_proc(c, t, "--novel-view", "1e300,0,0"), ["--novel-view"]),
        2,
    ),
    "process-novel-view-nan": (
        lambda c, t: (_proc(c, t, "--novel-view", "nan,0,0"), ["--novel-view"]),
        2,
    ),
    "process-novel-view-rotation-inf": (
        lambda c, t: (_proc(c, t, "--novel-view", "0,0,0,inf,0,0"), ["--novel-view"]),
        2,
    ),
    "process-novel-view-text": (
        lambda c, t: (_proc(c, t, "--novel-view", "left"), ["--novel-view"]),
        2,
    ),
    "process-novel-view-two": (
        lambda c, t: (_proc(c, t, "--novel-view", "1,2"), ["--novel-view"]),
        2,
    ),
    "process-output-under-a-file": (
        lambda c, t: (
            [
                "process",
                str(c.capture),
                "-c",
                str(c.cal_path),
                "-o",
                str(_bytes(t / "file", b"x") / "out"),
            ],
            ["file"],
        ),
        2,
    ),
    "process-output-is-a-file": (
        lambda c, t: (
            ["process", str(c.capture), "-c", str(c.cal_path), "-o", str(_bytes(t / "file", b"x"))],
            ["file"],
        ),
        2,
    ),
    "calibrate-missing-folder": (
        lambda c, t: (_cal(c, t, cal_dir=t / "none"), ["none"]),
        2,
    ),
    "calibrate-output-folder-missing": (
        lambda c, t: (
            ["calibrate", str(c.cal_dir), "-o", str(t / "no" / "cam.lfcal")],
            ["cam.lfcal", "does not exist"],
        ),
        2,
    ),
    "calibrate-output-under-a-file": (
        lambda c, t: (
            ["calibrate", str(c.cal_dir), "-o", str(_bytes(t / "file", b"x") / "cam.lfcal")],
            ["cam.lfcal"],
        ),
        2,
    ),
    "calibrate-output-exists": (
        lambda c, t: (
            ["calibrate", str(c.cal_dir), "-o", str(_bytes(t / "cam.lfcal", b"old"))],
            ["cam.lfcal", "--overwrite"],
        ),
        2,
    ),
    "calibrate-pitch-negative": (
        lambda c, t: (_cal(c, t, "--pattern-pitch=-1e-3"), ["pattern"]),
        2,
    ),
    "calibrate-pitch-nan": (lambda c, t: (_cal(c, t, "--pattern-pitch", "nan"), ["pattern"]), 2),
    "calibrate-z-c-negative": (lambda c, t: (_cal(c, t, "--z-c", "-1"), ["z"]), 2),
    "calibrate-z-c-beyond": (lambda c, t: (_cal(c, t, "--z-c", "50"), ["z_c"]), 2),
    "calibrate-scale-zero": (lambda c, t: (_cal(c, t, "--scale", "0"), ["scale"]), 2),
    "calibrate-scale-huge": (lambda c, t: (_cal(c, t, "--scale", "1e9"), ["scale"]), 2),
    "calibrate-reference-distance-negative": (
        lambda c, t: (_cal(c, t, "--reference-distance", "-1"), ["reference_distance"]),
        2,
    ),
    "calibrate-reference-distance-unknown": (
        lambda c, t: (_cal(c, t, "--reference-distance", "7.5"), ["reference_distance", "7.5"]),
        2,
    ),
    "calibrate-grid-zero": (lambda c, t: (_cal(c, t, "--grid", "0x3"), ["grid"]), 2),
    "calibrate-grid-huge": (lambda c, t: (_cal(c, t, "--grid", "100000x100000"), ["grid"]), 2),
    "calibrate-grid-text": (lambda c, t: (_cal(c, t, "--grid", "axb"), ["--grid"]), 2),
    "calibrate-reference-outside": (
        lambda c, t: (_cal(c, t, "--reference", "9,9"), ["reference"]),
        2,
    ),
    "calibrate-toml-grid-string": (
        lambda c, t: (
            _cal(c, t, cal_dir=_cal_copy(c, t, 'grid = "three"\n')),
            ["camera.toml", "grid"],
        ),
        2,
    ),
    "calibrate-toml-z-c-string": (
        lambda c, t: (_cal(c, t, cal_dir=_cal_copy(c, t, 'z_c = "x"\n')), ["camera.toml", "z_c"]),
        2,
    ),
    "calibrate-toml-pitch-list": (
        lambda c, t: (
            _cal(c, t, cal_dir=_cal_copy(c, t, "pattern_pitch = [1]\n")),
            ["camera.toml", "pattern_pitch"],
        ),
        2,
    ),
    "calibrate-toml-bayer-number": (
        lambda c, t: (_cal(c, t, cal_dir=_cal_copy(c, t, "bayer = 3\n")), ["camera.toml", "bayer"]),
        2,
    ),
    "calibrate-toml-reference-float": (
        lambda c, t: (
            _cal(c, t, cal_dir=_cal_copy(c, t, "reference = [1.5, 2]\n")),
            ["camera.toml", "reference"],
        ),
        2,
    ),
    "calibrate-toml-grid-bool": (
        lambda c, t: (
            _cal(c, t, cal_dir=_cal_copy(c, t, "grid = [true, 3]\n")),
            ["camera.toml", "grid"],
        ),
        2,
    ),
    "calibrate-toml-syntax": (
        lambda c, t: (_cal(c, t, cal_dir=_cal_copy(c, t, "grid = [3,\n")), ["camera.toml"]),
        2,
    ),
    "calibrate-toml-unknown-key": (
        lambda c, t: (_cal(c, t, cal_dir=_cal_copy(c, t, "zoom = 3\n")), ["camera.toml", "zoom"]),
        2,
    ),
    "calibrate-white-bad-name-junk": (
        lambda c, t: (
            _cal(c, t, cal_dir=_with_junk_white(_cal_copy(c, t))),
            ["white", ".png"],
        ),
        2,
    ),
    "info-missing": (lambda c, t: (["info", str(t / "no.lfcal")], ["no.lfcal"]), 2),
    "info-junk": (
        lambda c, t: (
            ["info", str(_bytes(t / "j.lfcal", b"\x89HDF\r\n\x1a\n" + b"\0" * 300))],
            ["j.lfcal"],
        ),
        2,
    ),
    "info-byte-changed": (
        lambda c, t: (
            ["info", str(_flip_byte(c.cal_path, t / "x.lfcal", -100))],
            ["x.lfcal", "checksum"],
        ),
        2,
    ),
    # pattern
    "pattern-width-zero": (
        lambda c, t: (["pattern", str(t / "p.png"), "--width", "0", "--height", "100"], ["width"]),
        2,
    ),
    "pattern-negative": (
        lambda c, t: (
            ["pattern", str(t / "p.png"), "--width", "100", "--height", "-5"],
            ["height"],
        ),
        2,
    ),
    "pattern-huge": (
        lambda c, t: (
            ["pattern", str(t / "p.png"), "--width", "100000", "--height", "100000"],
            ["width"],
        ),
        2,
    ),
    "pattern-jpeg": (
        lambda c, t: (
            ["pattern", str(t / "p.jpg"), "--width", "100", "--height", "100"],
            ["p.jpg"],
        ),
        2,
    ),
    # depth-views
    "depth-views-missing": (
        lambda c, t: (["depth-views", str(t / "none"), "-o", str(t / "o")], ["none"]),
        2,
    ),
    "depth-views-tiny-views": (
        lambda c, t: (
            ["depth-views", str(_views_folder(t, 8)), "-o", str(t / "o")],
            ["views", "8"],
        ),
        2,
    ),
    "depth-views-bad-subset": (
        lambda c, t: (
            ["depth-views", str(_views_folder(t, 32)), "-o", str(t / "o"), "--views", "x"],
            ["views", "'x'"],
        ),
        2,
    ),
    "depth-views-reference-outside": (
        lambda c, t: (
            ["depth-views", str(_views_folder(t, 32)), "-o", str(t / "o"), "--reference", "9,9"],
            ["reference"],
        ),
        2,
    ),
    "depth-views-one-view": (
        lambda c, t: (["depth-views", str(_views_folder(t, 32, 1)), "-o", str(t / "o")], ["view"]),
        2,
    ),
    # simulate
    "simulate-grid-zero": (lambda c, t: (["simulate", str(t / "s"), "--grid", "0x0"], ["grid"]), 2),
    "simulate-view-size-tiny": (
        lambda c, t: (["simulate", str(t / "s"), "--view-size", "1x1"], ["view_size"]),
        2,
    ),
    "simulate-view-size-huge": (
        lambda c, t: (["simulate", str(t / "s"), "--view-size", "100000x100000"], ["view_size"]),
        2,
    ),
    "simulate-captures-negative": (
        lambda c, t: (["simulate", str(t / "s"), "--captures", "-1"], ["captures"]),
        2,
    ),
    "simulate-distances-negative": (
        lambda c, t: (["simulate", str(t / "s"), "--distances", "-1"], ["distances"]),
        2,
    ),
    "simulate-config-type": (
        lambda c, t: (
            ["simulate", str(t / "s"), "--config", str(_bytes(t / "c.toml", b'grid = "big"\n'))],
            ["c.toml", "grid"],
        ),
        2,
    ),
}


@pytest.mark.parametrize("case", list(CLI_CASES), ids=list(CLI_CASES))
def test_cli_case(case: str, ctx: Ctx, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    build, code = CLI_CASES[case]
    argv, words = build(ctx, tmp_path)
    before = _files(tmp_path)
    try:
        got = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        got = exc.code
    err = capsys.readouterr().err
    assert got == code, err
    for w in words:
        assert w in err, (w, err)
    assert "Traceback" not in err
    assert "internal error" not in err
    assert err.count("\n") <= 3, err
    assert _files(tmp_path) == before  # nothing written, no temporary file left


# --------------------------------------------------------------------------- API

ApiCall = Callable[[Ctx, Path], Any]

API_CASES: dict[str, tuple[ApiCall, type[Exception], list[str]]] = {
    "rectify-cal-none": (lambda c, t: lfcam.rectify(c.raw, None), InputError, ["cal"]),  # type: ignore[arg-type]
    "rectify-raw-1d": (lambda c, t: lfcam.rectify(c.raw.reshape(-1), c.cal), InputError, ["raw"]),
    "rectify-raw-complex": (
        lambda c, t: lfcam.rectify(c.raw.astype(np.complex64), c.cal),
        InputError,
        ["raw"],
    ),
    "rectify-raw-none": (lambda c, t: lfcam.rectify(None, c.cal), InputError, ["raw"]),  # type: ignore[arg-type]
    "rectify-raw-4-channels": (
        lambda c, t: lfcam.rectify(np.dstack([c.raw, c.raw[..., :1]]), c.cal),
        InputError,
        ["raw"],
    ),
    "rectify-interp": (
        lambda c, t: lfcam.rectify(c.raw, c.cal, interp="cubic!"),
        InputError,
        ["interp"],
    ),
    "depth-reference-text": (
        lambda c, t: lfcam.depth_from_views(c.res.views, c.cal.offsets, reference="a"),  # type: ignore[arg-type]
        InputError,
        ["reference"],
    ),
    "depth-reference-outside": (
        lambda c, t: lfcam.depth_from_views(c.res.views, c.cal.offsets, reference=99),
        InputError,
        ["reference"],
    ),
    "depth-views-empty": (
        lambda c, t: lfcam.depth_from_views([], c.cal.offsets, reference=0),  # type: ignore[arg-type]
        InputError,
        ["views"],
    ),
    "depth-offsets-shape": (
        lambda c, t: lfcam.depth_from_views(c.res.views, c.cal.offsets[:2], reference=0),
        InputError,
        ["offsets"],
    ),
    "depth-offsets-nan": (
        lambda c, t: lfcam.depth_from_views(c.res.views, c.cal.offsets * np.nan, reference=0),
        InputError,
        ["offsets"],
    ),
    "estimate-depth-cal-none": (
        lambda c, t: lfcam.estimate_depth(c.res.views, None),  # type: ignore[arg-type]
        InputError,
        ["cal"],
    ),
    "estimate-depth-views-wrong": (
        lambda c, t: lfcam.estimate_depth(c.res.views[:2], c.cal),
        InputError,
        ["views"],
    ),
    "load-none": (lambda c, t: lfcam.Calibration.load(None), InputError, ["path"]),  # type: ignore[arg-type]
    "load-number": (lambda c, t: lfcam.Calibration.load(7), InputError, ["path"]),  # type: ignore[arg-type]
    "load-flipped": (
        lambda c, t: lfcam.Calibration.load(_flip_byte(c.cal_path, t / "f.lfcal", 3000)),
        CalibrationError,
        ["f.lfcal"],
    ),
    "superres-depth-complex": (
        lambda c, t: lfcam.super_resolve(c.raw, c.cal, c.res.depth.parallax.astype(np.complex64)),
        InputError,
        ["depth"],
    ),
    "superres-grey-raw-rgb-cal": (
        lambda c, t: lfcam.super_resolve(c.raw[..., 0], c.cal, c.res.depth),
        InputError,
        ["raw"],
    ),
    "superres-views-empty": (
        lambda c, t: lfcam.super_resolve(c.raw, c.cal, c.res.depth, views=[]),
        InputError,
        ["views"],
    ),
    "superres-factor-9": (
        lambda c, t: lfcam.super_resolve(c.raw, c.cal, c.res.depth, 9),
        InputError,
        ["factor"],
    ),
    "superres-factor-float": (
        lambda c, t: lfcam.super_resolve(c.raw, c.cal, c.res.depth, 2.5),  # type: ignore[arg-type]
        InputError,
        ["factor"],
    ),
    "superres-cal-none": (
        lambda c, t: lfcam.super_resolve(c.raw, None, c.res.depth),  # type: ignore[arg-type]
        InputError,
        ["cal"],
    ),
    "superres-window-too-wide": (
        lambda c, t: lfcam.super_resolve(
            c.raw, c.cal, c.res.depth, params=lfcam.SuperResParams(window=1000)
        ),
        InputError,
        ["window"],
    ),
    "refocus-depth-nan": (
        lambda c, t: lfcam.refocus(c.raw, c.cal, math.nan),
        InputError,
        ["depth"],
    ),
    "refocus-cal-none": (lambda c, t: lfcam.refocus(c.raw, None, 1.0), InputError, ["cal"]),  # type: ignore[arg-type]
    "process-capture-none": (
        lambda c, t: lfcam.process_capture(None, c.cal),  # type: ignore[arg-type]
        InputError,
        ["raw"],
    ),
    "process-capture-missing": (
        lambda c, t: lfcam.process_capture(t / "none.png", c.cal),
        InputError,
        ["none.png"],
    ),
    "read-image-none": (lambda c, t: lfcam.read_image(None), InputError, ["path"]),  # type: ignore[arg-type]
    "read-raw-bayer": (lambda c, t: lfcam.read_raw(c.capture, bayer="XYZW"), InputError, ["bayer"]),
    "read-image-huge-header": (
        lambda c, t: lfcam.read_image(_png_header(t / "h.png", 65535, 65535)),
        InputError,
        ["h.png"],
    ),
    "make-pattern-huge": (lambda c, t: lfcam.make_pattern(100_000, 100_000), InputError, ["width"]),
    "make-pattern-float": (lambda c, t: lfcam.make_pattern(100.5, 100), InputError, ["width"]),  # type: ignore[arg-type]
    "crop-rects-outside": (
        lambda c, t: lfcam.crop_lenslets(c.raw, [[0, 0, 10**6, 10]]),
        InputError,
        ["rects"],
    ),
    "remap-map-shape": (
        lambda c, t: lfcam.remap_bilinear(c.raw.astype(np.float32), np.zeros((3, 3), np.float32)),
        InputError,
        ["map"],
    ),
    "nan-median-complex": (
        lambda c, t: lfcam.nan_median(np.zeros((3, 4, 4), np.complex64)),
        InputError,
        ["stack"],
    ),
    "nan-median-axis": (
        lambda c, t: lfcam.nan_median(np.zeros((3, 4, 4), np.float32), axis=5),
        InputError,
        ["axis"],
    ),
    "triangulate-reference": (
        lambda c, t: lfcam.triangulate(np.zeros((3, 4, 4, 2), np.float32), np.zeros((3, 2)), 7),
        InputError,
        ["reference"],
    ),
    "mesh-depth-1d": (
        lambda c, t: lfcam.mesh_from_depth(np.zeros(5, np.float32), c.cal),
        InputError,
        ["depth"],
    ),
    "set-threads-zero": (lambda c, t: lfcam.set_num_threads(0), InputError, ["n"]),
    "set-threads-text": (lambda c, t: lfcam.set_num_threads("two"), InputError, ["n"]),  # type: ignore[arg-type]
    "superres-params-window": (
        lambda c, t: lfcam.SuperResParams(window=-1),
        InputError,
        ["window"],
    ),
    "depth-params-margin": (
        lambda c, t: lfcam.DepthParams(flow_margin=math.nan),
        InputError,
        ["flow_margin"],
    ),
    "simulate-out-under-file": (
        lambda c, t: ((t / "f").write_text("x"), lfcam.simulate(t / "f" / "s"))[1],
        InputError,
        ["f"],
    ),
}


@pytest.mark.parametrize("case", list(API_CASES), ids=list(API_CASES))
def test_api_case(case: str, ctx: Ctx, tmp_path: Path) -> None:
    call, exc_type, words = API_CASES[case]
    before = _files(tmp_path)
    with pytest.raises(exc_type) as e:
        call(ctx, tmp_path)
    msg = str(e.value)
    for w in words:
        assert w in msg, (w, msg)
    assert _files(tmp_path) - before <= {"f", "f.lfcal", "h.png"}  # only the case's own inputs


def test_table_size() -> None:
    assert len(CLI_CASES) + len(API_CASES) >= 60


def test_names_with_any_bytes_process(
    ctx: Ctx, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A capture and a calibration whose names are not valid UTF-8 are processed."""
    src = tmp_path / "in" / f"{BAD_NAME}.png"
    src.parent.mkdir()
    shutil.copyfile(ctx.capture, src)
    cal = tmp_path / f"{BAD_NAME}.lfcal"
    shutil.copyfile(ctx.cal_path, cal)
    assert main(["process", str(src.parent), "-c", str(cal), "-o", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / BAD_NAME / "depth.tiff").is_file()


def test_all_nan_capture_is_flagged(
    ctx: Ctx, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A degenerate result (all-NaN capture: no depth) is a warning and a flag, not silence."""
    import json

    src = tmp_path / "nan.tiff"
    tifffile.imwrite(src, np.full(ctx.raw.shape, np.nan, np.float32), photometric="rgb")
    code = main(["process", str(src), "-c", str(ctx.cal_path), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 0, err
    for word in ("warning", "nan.tiff", "covers 0.0 %"):
        assert word in err, err
    result = json.loads((tmp_path / "out" / "nan" / "result.json").read_text())
    assert result["degenerate"] is True
    assert result["statistics"]["coverage"] < 0.05
