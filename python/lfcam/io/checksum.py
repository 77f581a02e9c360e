"""Checksums of files: which calibration a result was made with."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import BinaryIO

from ..errors import InputError

__all__ = ["file_hash"]


def file_hash(source: str | os.PathLike[str] | BinaryIO, *, offset: int = 0) -> str:
    """SHA-256 of a file's bytes from ``offset`` to its end, as 64 hex digits.

    Processing outputs record it to say which calibration they used; the calibration
    file's own checksum covers what follows its user block.

    Parameters
    ----------
    source : path-like or binary file object
        Any file, usually an ``.lfcal``, or a file already open for reading (read from
        ``offset``; its position is left at the end).
    offset : int
        Bytes to leave out at the start.

    Returns
    -------
    str

    Raises
    ------
    InputError
        If ``source`` is a path and not an existing file.
    """
    if isinstance(source, (str, os.PathLike)):
        p = Path(source)
        if not p.is_file():
            raise InputError(f"{p}: no such file")
        with open(p, "rb") as fh:
            return file_hash(fh, offset=offset)
    h = hashlib.sha256()
    source.seek(offset)
    for block in iter(lambda: source.read(1 << 20), b""):
        h.update(block)
    return h.hexdigest()
