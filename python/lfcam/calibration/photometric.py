"""Calibration step 2: photometric gains from white captures (docs/design.md, "Photometric gains").

Per pixel and channel, the multiplier that makes the white target come out
neutral and flat (1.0 in every channel): white balance and vignetting at once.
Pixels not fully lit (outside the image circles, on their edges, in the gaps
between lenslets) get gain 0: masked.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["white_gains"]


def white_gains(
    white: np.ndarray, lit: np.ndarray, *, smoothing: float = 1.5, min_lit: float = 0.97
) -> np.ndarray:
    """Gains ``(H, W, C)`` float32 from the mean white capture.

    Parameters
    ----------
    white : (H, W, C) float array
        Mean of the white captures, raw values scaled to [0, 1].
    lit : (H, W) float array
        Lit fraction of each pixel (:attr:`lfcam.layout.Layout.lit`).
    smoothing : float
        Gaussian sigma (px) of a mask-aware smoothing of the white image before
        inverting it: vignetting is smooth, noise is not. 0 disables it (keep
        per-pixel response differences).
    min_lit : float
        Pixels lit less than this fraction (edges, gaps) are masked; the mask is
        also eroded by one pixel.

    Returns
    -------
    numpy.ndarray
        ``(H, W, C)`` float32; ``white * gains == 1`` where not masked, 0 elsewhere.
    """
    if white.ndim == 2:
        white = white[..., None]
    mask = (lit >= min_lit).astype(np.uint8)
    mask = cv2.erode(mask, np.ones((3, 3), np.uint8)) > 0
    gains = np.zeros(white.shape, np.float32)
    m = mask.astype(np.float32)
    for c in range(white.shape[2]):
        w = np.where(mask, white[..., c], 0.0).astype(np.float32)
        if smoothing > 0:
            num = cv2.GaussianBlur(w, (0, 0), smoothing)
            den = cv2.GaussianBlur(m, (0, 0), smoothing)
            with np.errstate(invalid="ignore", divide="ignore"):
                w = np.where(mask, num / den, 0.0)
        with np.errstate(divide="ignore"):
            gains[..., c] = np.where(mask & (w > 1e-3), 1.0 / w, 0.0)
    return gains
