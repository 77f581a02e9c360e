"""Display encodings: linear [0, 1] values as 8 and 16-bit pictures, and colour maps.

Every picture lfcam writes for people (previews, super-resolved and refocused
PNGs, mesh and point colours) is encoded here, with one transfer curve: sRGB
(IEC 61966-2-1), which the PNG files also declare (an ``sRGB`` chunk, see
:func:`lfcam.io.write_image`), so viewers and scripts decode them the same way.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["colour_depth", "encode_u8", "encode_u16", "rgb_u8", "srgb_decode", "srgb_encode"]


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1), float64; clipped, NaN = 0.

    Examples
    --------
    >>> import numpy as np
    >>> srgb_encode(np.array([0.0, 0.0031308, 0.5, 1.0])).round(6)
    array([0.      , 0.04045 , 0.735357, 1.      ])
    """
    v = np.clip(np.nan_to_num(np.asarray(x, np.float64), nan=0.0), 0, 1)
    out: np.ndarray = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return out


def srgb_decode(v: np.ndarray) -> np.ndarray:
    """sRGB-encoded values -> linear [0, 1], float64; integers are scaled by their
    type's maximum (uint8 / 255, uint16 / 65535). The inverse of :func:`srgb_encode`.

    Examples
    --------
    >>> import numpy as np
    >>> srgb_decode(np.array([0, 188, 255], np.uint8)).round(4)
    array([0.    , 0.5029, 1.    ])
    """
    a = np.asarray(v)
    if a.dtype.kind in "ui":
        a = a / float(np.iinfo(a.dtype).max)
    e = np.asarray(a, np.float64)
    out: np.ndarray = np.where(e <= 0.04045, e / 12.92, np.power((e + 0.055) / 1.055, 2.4))
    return out


def _encode(img: np.ndarray, top: int, dtype: type[np.generic]) -> np.ndarray:
    out: np.ndarray = np.round(srgb_encode(img) * top).astype(dtype)
    return out


def encode_u8(img: np.ndarray) -> np.ndarray:
    """Linear [0, 1] (NaN = 0) -> 8-bit sRGB."""
    return _encode(img, 255, np.uint8)


def encode_u16(img: np.ndarray) -> np.ndarray:
    """Linear [0, 1] (NaN = 0) -> 16-bit sRGB."""
    return _encode(img, 65535, np.uint16)


def rgb_u8(colours: np.ndarray) -> np.ndarray:
    """Linear per-point colours ``(M,)``, ``(M, 1)`` or ``(M, C >= 3)`` -> ``(M, 3)`` uint8
    sRGB (grey repeated)."""
    c = np.asarray(colours)
    if c.ndim == 1:
        c = c[:, None]
    if c.shape[1] == 1:
        c = np.repeat(c, 3, 1)
    return encode_u8(c[:, :3])


def colour_depth(
    depth: np.ndarray,
    lo: float | None = None,
    hi: float | None = None,
    *,
    unit: str = "m",
    near_high: bool = False,
) -> np.ndarray:
    """Depth (m) -> RGB preview with a labelled colour bar (TURBO, near = red).

    ``unit`` labels the bar; ``near_high`` says larger values are nearer (disparity),
    so they are the red ones.
    """
    finite = np.isfinite(depth)
    if lo is None or hi is None:
        if finite.any():
            lo, hi = (float(v) for v in np.percentile(depth[finite], [1, 99]))
        else:
            lo, hi = 0.0, 1.0
    hi = max(hi, lo + 1e-6)
    t = np.clip((np.nan_to_num(depth, nan=hi) - lo) / (hi - lo), 0, 1)
    if near_high:
        t = 1 - t
    bgr = cv2.applyColorMap(np.round((1 - t) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~finite] = 0
    H = depth.shape[0]
    bar_w, pad, text_w = max(12, H // 30), 8, 90
    bar = np.full((H, bar_w + pad + text_w, 3), 255, np.uint8)
    ramp = np.linspace(0, 1, H)[:, None]  # top = near (lo)
    col = cv2.applyColorMap(np.round((1 - ramp) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bar[:, pad : pad + bar_w] = np.repeat(col, bar_w, axis=1)
    for k in range(6):
        y = round(k / 5 * (H - 1))
        z = hi - (hi - lo) * k / 5 if near_high else lo + (hi - lo) * k / 5
        yt = min(max(y + 5, 12), H - 3)
        cv2.putText(
            bar,
            f"{z:.3g} {unit}",
            (pad + bar_w + 4, yt),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return np.concatenate([bgr, bar], axis=1)[..., ::-1].copy()
