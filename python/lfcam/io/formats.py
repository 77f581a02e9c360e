"""Array file formats other than images: PFM (portable float map) and Middlebury ``.flo``."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_output

__all__ = ["read_flo", "read_pfm", "write_pfm"]

# PFM (portable float map): a text header "PF" (RGB) or "Pf" (grey), "W H", and a
# scale whose sign gives the byte order (negative: little-endian), then W*H*C float32
# samples, rows stored bottom to top. The HCI 4D light-field benchmark's format.
_PFM_HEADER = re.compile(rb"\A(P[Ff])\s+(\d+)\s+(\d+)\s+(\S+)\s")


def read_pfm(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a PFM (portable float map) file, top row first.

    Parameters
    ----------
    path : path-like
        The ``.pfm`` file: ``Pf`` (one channel) or ``PF`` (RGB), either byte order.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` or ``(H, W, 3)`` float32 (native byte order, C-contiguous). PFM
        stores rows bottom to top; they are flipped here, so row 0 is the top of the
        image. Samples are multiplied by the magnitude of the header's scale when it
        is not 1 (HCI files use -1: little-endian, unscaled).

    Raises
    ------
    lfcam.InputError
        If the file is missing, its header is malformed, or its data are truncated
        or too long for the size the header gives.

    Examples
    --------
    >>> gt = lfcam.read_pfm("hci4d_antinous/gt_disp_lowres.pfm")  # doctest: +SKIP
    >>> gt.shape, gt.dtype                                         # doctest: +SKIP
    ((512, 512), dtype('float32'))
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    data = p.read_bytes()
    m = _PFM_HEADER.match(data[:256])
    if m is None:
        head = data[:24].split(b"\n")[0][:16]
        raise InputError(
            f"{p}: not a PFM file (expected a header 'PF' or 'Pf', width height, scale;"
            f" the file starts with {head!r})"
        )
    magic, w, h = m.group(1), int(m.group(2)), int(m.group(3))
    try:
        scale = float(m.group(4))
    except ValueError:
        scale = math.nan
    if not math.isfinite(scale) or scale == 0:
        raise InputError(
            f"{p}: PFM scale must be a non-zero number (its sign gives the byte order),"
            f" got {m.group(4).decode('latin-1')!r}"
        )
    if w == 0 or h == 0:
        raise InputError(f"{p}: PFM header gives an empty image ({w} x {h})")
    channels = 3 if magic == b"PF" else 1
    expected = w * h * channels * 4
    body = memoryview(data)[m.end() :]
    if len(body) != expected:
        what = "truncated" if len(body) < expected else "longer than its header says"
        raise InputError(
            f"{p}: PFM data {what}: {w} x {h} x {channels} float32 need {expected} bytes,"
            f" found {len(body)}"
        )
    arr = np.frombuffer(body, dtype="<f4" if scale < 0 else ">f4")
    shape = (h, w) if channels == 1 else (h, w, 3)
    out = np.flipud(arr.reshape(shape)).astype(np.float32)  # native order, a copy
    if abs(scale) != 1.0:
        out *= np.float32(abs(scale))
    return np.ascontiguousarray(out)


def read_flo(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a Middlebury ``.flo`` optical-flow file.

    Parameters
    ----------
    path : path-like
        Tag ``202021.25`` (float32), width and height (int32), then ``(u, v)``
        float32 pairs, row-major, top row first, little-endian.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 2)`` float32, ``[..., 0]`` = u (x); NaN where the file marks the
        flow unknown (``|value| > 1e9``).

    Raises
    ------
    lfcam.InputError
        If the file is missing, has the wrong tag, or its size does not match.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    data = p.read_bytes()
    if len(data) < 12 or np.frombuffer(data[:4], "<f4")[0] != 202021.25:
        raise InputError(f"{p}: not a Middlebury .flo file (tag 202021.25 missing)")
    w, h = (int(x) for x in np.frombuffer(data[4:12], "<i4"))
    if w <= 0 or h <= 0 or len(data) != 12 + 8 * w * h:
        raise InputError(f"{p}: .flo size {w} x {h} does not match its {len(data)} bytes")
    flow = np.frombuffer(data[12:], "<f4").reshape(h, w, 2).astype(np.float32)
    return np.where(np.abs(flow).max(-1, keepdims=True) < 1e9, flow, np.nan).astype(np.float32)


def write_pfm(path: str | os.PathLike[str], array: np.ndarray, *, scale: float = -1.0) -> None:
    """Write a PFM file atomically (a temporary file beside ``path``, then a rename).

    Parameters
    ----------
    path : path-like
        The file to write (``.pfm`` by convention; any name is accepted).
    array : (H, W), (H, W, 1) or (H, W, 3) array
        Real numbers, stored as float32 (NaN and infinities are kept). Row 0 is the
        top of the image; PFM's bottom-to-top row order is applied here.
    scale : float, optional
        The header's scale: its sign picks the byte order (negative, the default:
        little-endian; positive: big-endian). A magnitude other than 1 divides the
        stored samples so that :func:`read_pfm` gives ``array`` back.

    Raises
    ------
    lfcam.InputError
        If ``array`` is not an image of real numbers, ``scale`` is zero or not
        finite, or the folder of ``path`` does not exist.

    Examples
    --------
    >>> lfcam.write_pfm("disparity.pfm", disparity)  # doctest: +SKIP
    """
    p = Path(path)
    arr = np.asarray(array)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3) or arr.size == 0:
        raise InputError(
            f"array: PFM holds a non-empty (H, W) or (H, W, 3) image, got shape {arr.shape}"
        )
    if arr.dtype.kind not in "fiu":
        raise InputError(f"array: PFM holds real numbers, not {arr.dtype}")
    scale = float(scale)
    if not math.isfinite(scale) or scale == 0:
        raise InputError(f"scale: must be a finite non-zero number, got {scale!r}")
    data = arr.astype(np.float32)
    if abs(scale) != 1.0:
        data = data / np.float32(abs(scale))
    h, w = arr.shape[:2]
    header = f"{'PF' if arr.ndim == 3 else 'Pf'}\n{w} {h}\n{scale:g}\n".encode("ascii")
    body = np.ascontiguousarray(np.flipud(data), dtype="<f4" if scale < 0 else ">f4")
    with atomic_output(p) as tmp:
        tmp.write_bytes(header + body.tobytes())
