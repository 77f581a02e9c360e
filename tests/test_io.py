"""lfcam.io's file handling: atomic folders, reading untrusted files' bytes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from lfcam.errors import InputError
from lfcam.io import atomic, files
from lfcam.io.atomic import atomic_folder
from lfcam.io.files import read_file_bytes


def test_atomic_folder_interrupted_between_renames_keeps_the_old(tmp_path, monkeypatch) -> None:
    out = tmp_path / "cap"
    out.mkdir()
    (out / "result.json").write_text('{"old": 1}')
    real = os.replace

    def interrupted(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        # The old folder is set aside; the new one is never renamed in.
        if Path(src).name.startswith(".cap.tmp-"):
            raise KeyboardInterrupt
        real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt), atomic_folder(out) as tmp:
        (tmp / "result.json").write_text('{"new": 1}')
    monkeypatch.undo()
    assert (out / "result.json").read_text() == '{"old": 1}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]  # no temporaries, no lock
    # Uninterrupted, the new folder replaces the old.
    with atomic_folder(out) as tmp:
        (tmp / "result.json").write_text('{"new": 1}')
    assert (out / "result.json").read_text() == '{"new": 1}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]


def test_read_file_bytes_refuses_a_file_that_grew(tmp_path, monkeypatch) -> None:
    p = tmp_path / "big.png"
    p.write_bytes(bytes(120))
    assert read_file_bytes(p, 120) == bytes(120)
    real = os.fstat

    def stale(fd: int) -> os.stat_result:
        # The size when it was opened; then it grew (a writer appending to it).
        st = list(real(fd))
        st[6] = 100
        return os.stat_result(st)

    monkeypatch.setattr(files.os, "fstat", stale)
    with pytest.raises(InputError) as e:
        read_file_bytes(p, 110)
    assert str(e.value) == f"{p}: more than 110 bytes, larger than lfcam reads"
