"""Advisory locks on output paths, and removal of what killed runs left behind.

Every atomic write (:mod:`lfcam.io.atomic`) holds the lock of its destination while its
temporary exists, and a batch holds a capture's lock from the "is it complete?" check
to the rename. So a temporary whose destination nobody holds the lock of belongs to a
run that died, and :func:`remove_stale` can delete it. The lock of ``DIR/NAME`` is the
file ``DIR/.NAME.lfcam-lock`` (``flock``; a name no other program uses), removed again
on release.

On systems without ``fcntl`` (Windows) the locks are no-ops and nothing is swept.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

from ..errors import LfcamError

__all__ = ["LockBusy", "lock_path", "path_lock", "remove_stale"]

#: The temporaries lfcam's atomic writers make beside ``NAME`` (``tempfile``'s random
#: part is 8 characters from ``[a-z0-9_]``): ``.NAME.tmp-XXXXXXXX[.ext]`` while a file
#: or folder is written, ``.NAME.old-XXXXXXXX/`` while a replaced folder is set aside.
_TEMP = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-[a-z0-9_]{8}(?:\.[^./]*)?$")
_LOCK = re.compile(r"^\.(?P<name>.+)\.lfcam-lock$")

# Locks this process holds, by (thread, lock file): a thread may take a lock it already
# holds (the batch's lock, then the atomic writer's), other threads may not.
_held: dict[tuple[int, str], int] = {}


class LockBusy(LfcamError):
    """Another run (or thread) holds the lock of an output path."""


def lock_path(path: str | os.PathLike[str]) -> Path:
    """The lock file of ``path``: ``.NAME.lfcam-lock`` beside it."""
    p = Path(path)
    return p.parent / f".{p.name}.lfcam-lock"


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    fst = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (fst.st_dev, fst.st_ino)


def _acquire(lock: Path, wait: bool) -> int:
    # A holder unlinks the lock file before it lets go, so a lock taken on a file that
    # is no longer at its path is worthless: take it again on the new file.
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise LockBusy(f"{lock}: held by another run") from None
            raise
        if _same_file(fd, lock):
            return fd
        os.close(fd)


@contextlib.contextmanager
def path_lock(path: str | os.PathLike[str], *, wait: bool = True) -> Iterator[Path]:
    """Hold the advisory lock of output ``path`` (a file or folder) for the block.

    Parameters
    ----------
    path : path-like
        The output; its parent folder must exist.
    wait : bool
        Wait for another holder to let go; if False, raise :class:`LockBusy` at once.

    Yields
    ------
    Path
        The lock file (removed when the block ends).
    """
    lock = lock_path(path)
    key = (threading.get_ident(), str(lock.absolute()))
    if fcntl is None or key in _held:
        yield lock
        return
    fd = _acquire(lock, wait)
    _held[key] = fd
    try:
        yield lock
    finally:
        del _held[key]
        with contextlib.suppress(FileNotFoundError):
            os.unlink(lock)
        os.close(fd)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def remove_stale(folder: str | os.PathLike[str], name: str | None = None) -> list[Path]:
    """Remove the temporaries that killed lfcam runs left in ``folder`` (not below it).

    Only lfcam's own names are touched (``.NAME.tmp-XXXXXXXX``, ``.NAME.old-XXXXXXXX``,
    ``.NAME.lfcam-lock``), and each only while holding ``NAME``'s lock, taken without waiting:
    what a live run holds is left alone. A folder set aside by an ``--overwrite`` that
    died before its replacement was renamed in is put back under ``NAME``.

    Parameters
    ----------
    folder : path-like
        Where to look.
    name : str, optional
        Only the temporaries of this ``NAME``.

    Returns
    -------
    list of Path
        What was removed (lock files not counted).
    """
    d = Path(folder)
    if fcntl is None or not d.is_dir():
        return []
    removed: list[Path] = []
    for entry in sorted(os.scandir(d), key=lambda e: e.name):
        m = _TEMP.match(entry.name) or _LOCK.match(entry.name)
        if m is None or (name is not None and m["name"] != name):
            continue
        target = d / m["name"]
        try:
            with path_lock(target, wait=False):
                p = Path(entry.path)
                if not os.path.lexists(p) or "kind" not in m.groupdict():
                    continue
                aside = p / m["name"]
                if m["kind"] == "old" and aside.is_dir() and not os.path.lexists(target):
                    os.replace(aside, target)
                _remove(p)
                removed.append(p)
        except LockBusy:
            continue
    return removed
