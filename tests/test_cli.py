"""The lfcam command line: exit codes, messages, outputs."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from lfcam.cli import main
from lfcam.io import read_image


def test_help_and_module_entry_point() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "lfcam", "--help"], capture_output=True, text=True, check=True
    )
    assert "simulate" in out.stdout
    assert "pattern" in out.stdout


def test_pattern_command(tmp_path, capsys) -> None:
    out = tmp_path / "p.png"
    assert main(["pattern", str(out), "--width", "320", "--height", "200", "--seed", "2"]) == 0
    img = read_image(out)
    assert img.shape == (200, 320)
    assert img.dtype == np.uint8
    assert list(tmp_path.iterdir()) == [out]  # no temporary file left behind


def test_pattern_bad_arguments(tmp_path, capsys) -> None:
    assert main(["pattern", str(tmp_path / "p.png"), "--width", "10", "--height", "200"]) == 2
    assert "width" in capsys.readouterr().err
    assert main(["pattern", str(tmp_path / "p.jpg"), "--width", "100", "--height", "100"]) == 2
    assert "p.jpg" in capsys.readouterr().err
    assert (
        main(["pattern", str(tmp_path / "nodir" / "p.png"), "--width", "100", "--height", "100"])
        == 2
    )
    assert "does not exist" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_simulate_command(tmp_path, capsys) -> None:
    out = tmp_path / "sim"
    code = main(
        [
            "simulate",
            str(out),
            "--view-size",
            "96x72",
            "--grid",
            "3x3",
            "--captures",
            "1",
            "--scenes",
            "planes",
            "--seed",
            "5",
            "--bit-depth",
            "16",
            "--format",
            "tiff",
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "3x3 camera" in text
    assert str(out / "calibration") in text
    raw = read_image(out / "captures" / "planes.tiff")
    assert raw.shape == (216, 288, 3)
    assert raw.dtype == np.uint16
    # A second run into the same folder refuses, and leaves it as it was.
    before = sorted(p.name for p in out.rglob("*"))
    assert main(["simulate", str(out), "--view-size", "96x72"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert sorted(p.name for p in out.rglob("*")) == before


def test_simulate_bad_config(tmp_path, capsys) -> None:
    cfg = tmp_path / "cam.toml"
    cfg.write_text("grid = [3, 4]\nwhat = 1\n")
    assert main(["simulate", str(tmp_path / "o"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "cam.toml" in err
    assert "what" in err
    assert main(["simulate", str(tmp_path / "o"), "--config", str(tmp_path / "none.toml")]) == 2
    assert "none.toml" in capsys.readouterr().err
    assert main(["simulate", str(tmp_path / "o"), "--scenes", "moon"]) == 2
    assert "moon" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


COMMANDS = ("simulate", "pattern", "calibrate", "info", "process", "depth-views", "demo")


def test_every_command_has_examples_and_a_description(capsys) -> None:
    import pytest

    for cmd in COMMANDS:
        with pytest.raises(SystemExit) as exc:
            main([cmd, "--help"])
        assert exc.value.code == 0
        text = capsys.readouterr().out
        assert "\nexamples:\n" in text, cmd
        examples = text.split("\nexamples:\n")[1].splitlines()
        assert examples
        assert all(line.startswith(f"  lfcam {cmd}") for line in examples if line), cmd
        head = text.split("\n\n")[1]  # the description, after the usage
        assert len(head.split()) > 10, f"{cmd}: no description"
        assert "-q, --quiet" in text


def test_metavars_are_consistent(capsys) -> None:
    import pytest

    for cmd, expect in (
        ("calibrate", ("--grid RxC", "--reference ROW,COL")),
        ("simulate", ("--grid RxC", "--view-size WxH")),
        ("depth-views", ("--reference ROW,COL", "--views ROWS,COLS")),
        ("process", ("--refocus Z1,Z2", "--frame {valid,full}")),
    ):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        text = capsys.readouterr().out
        for e in expect:
            assert e in text, (cmd, e)


def test_grid_error_names_the_form(capsys) -> None:
    import pytest

    with pytest.raises(SystemExit):
        main(["simulate", "out", "--grid", "3-4"])
    assert "--grid: expected two integers as RxC, got '3-4'" in capsys.readouterr().err


def test_closed_pipe_ends_quietly(tmp_path) -> None:
    """`lfcam ... | head`: the reader goes away; no traceback, no error message, the
    shell's exit code for a closed pipe (141); argparse's help ignores the closed
    pipe itself (0)."""
    for code, args in (
        (0, ["process", "--help"]),
        (141, ["pattern", str(tmp_path / "p.png"), "--width", "64", "--height", "64"]),
    ):
        proc = subprocess.Popen(
            [sys.executable, "-m", "lfcam", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        assert proc.stdout is not None
        proc.stdout.close()  # long before the interpreter has started and written
        _, err = proc.communicate(timeout=60)
        assert err == b"", args
        assert proc.returncode == code, args


def test_demo_writes_outside_the_source_tree() -> None:
    import tempfile
    from pathlib import Path

    from lfcam.cli import _default_demo_dir

    d = _default_demo_dir()
    assert d.parent == Path(tempfile.gettempdir())
    repo = Path(__file__).resolve().parents[1]
    assert repo not in d.resolve().parents


def test_version_shows_the_simd_paths_in_use() -> None:
    import os

    import lfcam

    env = {**os.environ, "LFCAM_SIMD": "portable"}
    out = subprocess.run(
        [sys.executable, "-m", "lfcam", "--version"],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    ).stdout
    assert out.startswith(f"lfcam {lfcam.__version__}\n")
    assert "portable in use" in out
    assert "LFCAM_SIMD=portable" in out
    info = lfcam.build_info()
    assert info["version"] == lfcam.__version__
    # Every kernel family's build is named, and none is above the level in use.
    order = ["portable", "avx2", "avx512"]
    simd = info["simd"]
    kernels = {k: v for k, v in simd.items() if k not in ("setting", "cpu", "level")}
    assert kernels
    assert all(order.index(v) <= order.index(simd["level"]) for v in kernels.values())
    assert order.index(simd["level"]) <= order.index(simd["cpu"])


def test_progress_log_lines_off_a_terminal(caplog) -> None:
    import io
    import logging

    from lfcam.progress import Progress

    caplog.set_level(logging.INFO, logger="lfcam.progress")
    with Progress(4, "process", unit="capture", stream=io.StringIO()) as p:
        p.step("a.png done")
        p.skip()  # complete already: not counted in the total any more
        p.step("b.png done")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2
    assert lines[0].startswith("process 1/4 a.png done (")
    assert lines[1].startswith("process 2/3 b.png done (")
    assert all("s elapsed" in m and "capture/s)" in m for m in lines)
    caplog.clear()
    with Progress(2, "x", quiet=True, stream=io.StringIO()) as p:
        p.step("a")
    assert not caplog.records
