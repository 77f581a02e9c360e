"""Which SIMD builds of the kernels run, and the switch that caps them (LFCAM_SIMD)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from lfcam import _lfcam

LEVELS = ("portable", "avx2", "avx512")
KERNELS = {"rectify", "rectify_plan", "superres", "triangulate", "triangulate_few_views"}


def _info_in_subprocess(value: str | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "LFCAM_SIMD"}
    if value is not None:
        env["LFCAM_SIMD"] = value
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            "import json; from lfcam import _lfcam; print(json.dumps(_lfcam.simd_info()))",
        ],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    info: dict[str, str] = json.loads(out.stdout)
    return info


def test_info_names_every_kernel_family_within_the_cpu() -> None:
    info = _lfcam.simd_info()
    assert set(info) == {"setting", "cpu", "level"} | KERNELS
    assert info["setting"] in ("auto", "avx2", "portable")
    rank = LEVELS.index
    assert rank(info["level"]) <= rank(info["cpu"])
    assert all(rank(info[k]) <= rank(info["level"]) for k in KERNELS)


@pytest.mark.parametrize(
    ("value", "setting"),
    [(None, "auto"), ("portable", "portable"), ("avx2", "avx2"), (" AUTO", "auto"), ("x", "auto")],
)
def test_env_var_caps_the_builds(value: str | None, setting: str) -> None:
    info = _info_in_subprocess(value)
    assert info["setting"] == setting
    cap = {"portable": 0, "avx2": 1, "auto": 2}[setting]
    assert LEVELS.index(info["level"]) == min(LEVELS.index(info["cpu"]), cap)
    if setting == "portable":
        assert all(info[k] == "portable" for k in KERNELS)
