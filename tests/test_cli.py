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
