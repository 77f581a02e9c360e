"""Checksums of files: which calibration a result was made with."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from ..errors import InputError

__all__ = ["file_hash"]


def file_hash(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes, as 64 hex digits.

    Processing outputs record it to say which calibration they used.

    Parameters
    ----------
    path : path-like
        Any file, usually an ``.lfcal``.

    Returns
    -------
    str

    Raises
    ------
    InputError
        If ``path`` is not an existing file.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    h = hashlib.sha256()
    with open(p, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
