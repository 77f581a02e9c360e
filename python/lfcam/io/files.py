"""Reading an untrusted file's bytes: by Python (any byte in its name works), only a
regular file, within a size limit. Decoders then work on memory, never on a path."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ..errors import InputError

__all__ = [
    "MAX_IMAGE_FILE_BYTES",
    "MAX_IMAGE_PIXELS",
    "MAX_IMAGE_SIDE",
    "check_image_size",
    "read_file_bytes",
]

#: Largest width or height of an image lfcam reads (px); checked in the file's header
#: before anything is decoded.
MAX_IMAGE_SIDE = 65_535
#: Largest number of pixels (width x height) of an image lfcam reads: 2**28, about
#: 268 megapixels (1 GiB per float32 channel), beyond any light-field sensor.
MAX_IMAGE_PIXELS = 1 << 28

#: Largest image file lfcam reads into memory, bytes (a 16-bit RGB TIFF at
#: ``MAX_IMAGE_PIXELS`` is 1.5 GiB).
MAX_IMAGE_FILE_BYTES = 1 << 31


def read_file_bytes(path: str | os.PathLike[str], limit: int) -> bytes:
    """A file's bytes, or an :class:`~lfcam.InputError` naming it.

    Raises
    ------
    lfcam.InputError
        If the file is missing, a folder, not a regular file (a FIFO or device would
        block or never end), larger than ``limit`` bytes, or unreadable.
    """
    p = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer (refused just below).
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as fh:
            st = os.fstat(fh.fileno())
            if stat.S_ISDIR(st.st_mode):
                raise InputError(f"{p}: is a folder, not a file")
            if not stat.S_ISREG(st.st_mode):
                raise InputError(f"{p}: not a regular file")
            if st.st_size > limit:
                raise InputError(f"{p}: {st.st_size} bytes, larger than lfcam reads ({limit})")
            data = fh.read(limit + 1)
            if len(data) > limit:  # it grew since fstat
                raise InputError(f"{p}: more than {limit} bytes, larger than lfcam reads")
            return data
    except FileNotFoundError:
        raise InputError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a folder, not a file") from None
    except OSError as e:
        raise InputError(f"{p}: cannot read ({e.strerror or e})") from None


def check_image_size(width: int, height: int, channels: int, where: str) -> None:
    """Refuse an image size a file's header declares, before anything is decoded.

    Raises
    ------
    lfcam.InputError
        Naming ``where``, if the image is empty, has other than 1 to 4 channels, or
        is larger than :data:`MAX_IMAGE_SIDE` / :data:`MAX_IMAGE_PIXELS`.
    """
    if width < 1 or height < 1:
        raise InputError(f"{where}: the header declares an empty {width} x {height} image")
    if channels not in (1, 2, 3, 4):
        raise InputError(f"{where}: the header declares {channels} channels (expected 1 to 4)")
    if max(width, height) > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise InputError(
            f"{where}: the header declares a {width} x {height} image, larger than lfcam "
            f"reads ({MAX_IMAGE_SIDE} px a side, {MAX_IMAGE_PIXELS} px in all)"
        )
