"""Atomic writing: a file or a folder appears complete under its name, or not at all.

Everything lfcam writes is assembled under a hidden temporary name beside its
destination and renamed into place when complete, so an interrupted run never leaves
a half-written result, and readers never see one. The destination's lock
(:func:`lfcam.io.lock.path_lock`) is held meanwhile, so the temporaries of a run that
was killed can be told from those of a live one and removed
(:func:`lfcam.io.lock.remove_stale`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from ..errors import InputError
from .lock import path_lock

__all__ = [
    "atomic_folder",
    "atomic_output",
    "file_mode",
    "write_text_atomic",
]


def file_mode() -> int:
    """Permissions a new file gets under the current umask (mkstemp makes 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``.

    On any error the temporary file is removed and ``path`` is left untouched,
    so a failed write never leaves a half-written file behind.
    """
    p = Path(path)
    if not p.parent.is_dir():
        raise InputError(f"{p}: folder {p.parent} does not exist")
    if p.is_dir():
        raise InputError(f"{p}: is a folder")
    with path_lock(p):
        # Hidden, marked ".tmp-", and ending in the destination's extension (writers that
        # pick a format by extension see the right one).
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.tmp-", suffix=p.suffix, dir=p.parent)
        os.close(fd)
        try:
            yield Path(tmp)
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.chmod(tmp, file_mode())
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


@contextlib.contextmanager
def atomic_folder(out: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; when the block succeeds, it becomes ``out``.

    An existing ``out`` is replaced only then, and never goes missing on the way: it
    is renamed aside, the new folder renamed in, and only then the old one deleted.
    On any error the temporary folder is removed and ``out`` is left as it was.
    """
    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise InputError(
            f"{out}: cannot make its folder {out.parent}: a file is in the way"
        ) from None
    with path_lock(out):
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
        old: Path | None = None
        try:
            yield tmp
            mode = file_mode()
            for p in tmp.rglob("*"):
                os.chmod(p, (mode | 0o111) if p.is_dir() else mode)
            os.chmod(tmp, mode | 0o111)
            if out.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
                os.replace(out, old / out.name)
            os.replace(tmp, out)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        except BaseException:
            # Interrupted between the two renames: the old folder goes back under its name.
            if old is not None and not os.path.lexists(out) and (old / out.name).is_dir():
                os.replace(old / out.name, out)
                shutil.rmtree(old, ignore_errors=True)
            shutil.rmtree(tmp, ignore_errors=True)
            raise


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write a text file atomically (see :func:`atomic_output`)."""
    with atomic_output(path) as tmp:
        tmp.write_text(text)
