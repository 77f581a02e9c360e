"""Pictures for people: the calibration report image.

Drawn with OpenCV (no plotting library needed): RGB uint8 arrays.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from .file import Calibration

__all__ = ["TITLE_BAND", "calibration_figure", "flow_colours"]


def flow_colours(d: np.ndarray, valid: np.ndarray, max_mag: float | None = None) -> np.ndarray:
    """Displacements ``(H, W, 2)`` -> RGB: hue = direction, brightness = magnitude."""
    d = np.nan_to_num(d)
    mag = np.hypot(d[..., 0], d[..., 1])
    ang = np.arctan2(d[..., 1], d[..., 0])
    top = max_mag or float(np.nanpercentile(mag[valid], 99)) if valid.any() else 1.0
    top = max(top, 1e-6)
    hsv = np.zeros((*d.shape[:2], 3), np.uint8)
    hsv[..., 0] = np.round(((ang + np.pi) / (2 * np.pi)) * 179).astype(np.uint8)
    hsv[..., 1] = 255
    hsv[..., 2] = np.round(np.clip(np.nan_to_num(mag) / top, 0, 1) * 255).astype(np.uint8)
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    rgb[~valid] = 0
    return rgb


def _affine_residual(warp: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The warp map minus its best affine fit: the lenslet's non-linear distortion."""
    vv, uu = np.nonzero(mask)
    A = np.column_stack([uu, vv, np.ones(len(uu))]).astype(np.float64)
    coef = np.linalg.lstsq(A, warp[vv, uu].astype(np.float64), rcond=None)[0]
    H, W = mask.shape
    yy, xx = np.mgrid[0:H, 0:W]
    fit = np.stack([xx, yy, np.ones_like(xx)], -1).astype(np.float64) @ coef
    return (warp - fit).astype(np.float32)


#: Height of the white band above each part of the report picture that holds its title.
TITLE_BAND = 32


def _label(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` under a white band with its title, drawn once: never over the picture."""
    band = np.full((TITLE_BAND, img.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([band, img], axis=0)


def _fit(img: np.ndarray, width: int) -> np.ndarray:
    h = max(1, round(img.shape[0] * width / img.shape[1]))
    return cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)


def _tiles(images: Sequence[np.ndarray], cols: int, width: int) -> np.ndarray:
    tiles = [_fit(t, width // cols - 4) for t in images]
    th, tw = tiles[0].shape[:2]
    rows = -(-len(tiles) // cols)
    out = np.full((rows * (th + 4), cols * (tw + 4), 3), 255, np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        out[r * (th + 4) + 2 : r * (th + 4) + 2 + th, c * (tw + 4) + 2 : c * (tw + 4) + 2 + tw] = t
    return out


def calibration_figure(
    cal: Calibration,
    white: np.ndarray | None = None,
    residuals: Sequence[np.ndarray] | None = None,
    width: int = 1600,
) -> np.ndarray:
    """The calibration report picture (RGB uint8).

    Top: the white frame with each view's crop (green) and image-circle centre
    (red). Middle: each view's warp map beyond its best affine fit (its
    non-axial distortion), hue = direction, brightness = magnitude, like
    figures 5 and 6 of the paper. Bottom (if given): each view's photometric
    residual after rectification (white = large) and its mask.
    """
    C = cal.grid[1]
    parts = []
    if white is not None:
        w = np.clip(white / max(float(np.percentile(white, 99.5)), 1e-6), 0, 1)
        img = np.round((w if w.ndim == 3 else np.repeat(w[..., None], 3, 2)) * 255).astype(np.uint8)
        img = np.ascontiguousarray(img)
        for i, (x0, y0, cw, ch) in enumerate(cal.crops):
            cv2.rectangle(
                img, (int(x0), int(y0)), (int(x0 + cw - 1), int(y0 + ch - 1)), (0, 200, 0), 3
            )
            cx, cy = cal.centres[i]
            s = max(6, int(cw) // 30)
            cv2.line(img, (int(cx) - s, int(cy)), (int(cx) + s, int(cy)), (230, 0, 0), 3)
            cv2.line(img, (int(cx), int(cy) - s), (int(cx), int(cy) + s), (230, 0, 0), 3)
            cv2.putText(
                img,
                f"{divmod(i, C)}",
                (int(x0) + 10, int(y0) + 40),
                cv2.FONT_HERSHEY_SIMPLEX,
                1.2,
                (255, 255, 255),
                3,
                cv2.LINE_AA,
            )
        parts.append(_label(_fit(img, width), "white frame: crops (green), circle centres (red)"))
    dist = [_affine_residual(cal.warps[i], cal.masks[i]) for i in range(cal.n_views)]
    top = max(
        float(np.nanpercentile(np.hypot(*np.moveaxis(d[m], -1, 0)), 99))
        for d, m in zip(dist, cal.masks)
    )
    tiles = [flow_colours(d, m, top) for d, m in zip(dist, cal.masks)]
    parts.append(
        _label(
            _tiles(tiles, C, width),
            f"warp maps beyond affine (hue: direction; full brightness {top:.1f} px)",
        )
    )
    if residuals is not None:
        res_tiles = []
        for r, m in zip(residuals, cal.masks):
            v = np.clip(np.nan_to_num(r) / 1.0, 0, 1)
            t = np.round(np.repeat(v[..., None], 3, 2) * 255).astype(np.uint8)
            t[~m] = (60, 0, 80)
            res_tiles.append(t)
        parts.append(
            _label(
                _tiles(res_tiles, C, width),
                "photometric residual after rectification (purple: masked)",
            )
        )
    wmax = max(p.shape[1] for p in parts)
    parts = [
        np.pad(p, ((0, 8), (0, wmax - p.shape[1]), (0, 0)), constant_values=255) for p in parts
    ]
    return np.concatenate(parts, axis=0)
