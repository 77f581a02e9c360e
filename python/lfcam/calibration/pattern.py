"""The digital calibration pattern and the procedural textures of the simulator.

The pattern is what the camera is calibrated against (docs/design.md, "Calibration pipeline"): dense
texture at every scale from a few pixels to a large fraction of the image, so
that optical flow can lock onto it everywhere, and a clear cross at the centre
for the coarse alignment of each view.
"""

from __future__ import annotations

import cv2
import numpy as np

from .._validate import check_positive_int
from ..errors import InputError

__all__ = ["MAX_PATTERN_SIDE", "make_pattern", "multiscale_noise", "procedural_texture"]

#: Largest pattern width or height, px (an 8K screen is 7680 px wide).
MAX_PATTERN_SIDE = 16384


def multiscale_noise(
    height: int,
    width: int,
    rng: np.random.Generator,
    *,
    finest: float = 2.0,
    coarsest: float | None = None,
    channels: int = 1,
) -> np.ndarray:
    """Band-limited noise with equal energy in every octave (a 1/f spectrum).

    Octave ``k`` is white noise on a grid ``finest * 2**k`` pixels apart,
    upsampled with bicubic interpolation, so the image has detail at every
    scale from ``finest`` to ``coarsest`` pixels.

    Parameters
    ----------
    height, width : int
        Output size in pixels.
    rng : numpy.random.Generator
        Source of randomness (the output is deterministic given its state).
    finest : float, optional
        Period of the finest octave in pixels (>= 1). Default 2.
    coarsest : float, optional
        Period of the coarsest octave; default half the larger side.
    channels : int, optional
        Independent noise channels. Default 1.

    Returns
    -------
    numpy.ndarray
        ``(height, width, channels)`` float32, zero mean, unit standard deviation
        per channel.
    """
    if coarsest is None:
        coarsest = max(height, width) / 2.0
    # A pyramid: start from white noise on the coarsest grid, then repeatedly
    # upsample x2 (bicubic) and add fresh white noise, so octave k has period
    # 2**k grid steps; the grid step is `finest` pixels. Cost ~ 4/3 of one image.
    levels = max(1, int(np.floor(np.log2(max(coarsest / finest, 1.0)))) + 1)
    gh = int(np.ceil(height / finest)) + 4
    gw = int(np.ceil(width / finest)) + 4
    sizes = [(gh, gw)]
    for _ in range(levels - 1):
        h2, w2 = sizes[-1]
        sizes.append((max(2, -(-h2 // 2) + 1), max(2, -(-w2 // 2) + 1)))
    img = rng.standard_normal(sizes[-1] + (channels,)).astype(np.float32)
    for h2, w2 in reversed(sizes[:-1]):
        up = cv2.resize(img, (img.shape[1] * 2, img.shape[0] * 2), interpolation=cv2.INTER_CUBIC)
        if up.ndim == 2:
            up = up[:, :, None]
        img = up[:h2, :w2] + rng.standard_normal((h2, w2, channels)).astype(np.float32)
    big = cv2.resize(img, (round(gw * finest), round(gh * finest)), interpolation=cv2.INTER_CUBIC)
    if big.ndim == 2:
        big = big[:, :, None]
    out = np.ascontiguousarray(big[:height, :width])
    out -= out.mean(axis=(0, 1), keepdims=True)
    std = out.std(axis=(0, 1), keepdims=True)
    out /= np.maximum(std, 1e-12)
    return out


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, count: int, max_size: float) -> None:
    """Draw ``count`` random filled discs and polygons (sharp edges at all scales).

    Sizes are log-uniform from 3 pixels to ``max_size``.
    """
    h, w = img.shape[:2]
    ch = img.shape[2]
    for _ in range(count):
        size = float(np.exp(rng.uniform(np.log(3.0), np.log(max(4.0, max_size)))))
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        colour = tuple(float(v) for v in rng.uniform(0.0, 1.0, ch))
        if rng.random() < 0.5:
            cv2.circle(img, (int(cx), int(cy)), max(1, int(size)), colour, -1, cv2.LINE_AA)
        else:
            n = int(rng.integers(3, 7))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = size * rng.uniform(0.5, 1.5, n)
            pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], axis=1)
            cv2.fillPoly(img, [np.round(pts).astype(np.int32)], colour, cv2.LINE_AA)


def procedural_texture(
    height: int, width: int, rng: np.random.Generator, *, finest: float = 2.0
) -> np.ndarray:
    """A colour texture rich at all scales, for the simulator's scene surfaces.

    Coloured 1/f noise plus random discs and polygons (sharp edges), with
    values in about [0.04, 0.96].

    Parameters
    ----------
    height, width : int
        Size in texels.
    rng : numpy.random.Generator
        Source of randomness.
    finest : float, optional
        Period of the finest noise octave in texels.

    Returns
    -------
    numpy.ndarray
        ``(height, width, 3)`` float32 linear RGB albedo.
    """
    noise = multiscale_noise(height, width, rng, finest=finest, channels=3)
    # Correlate the channels so colours look natural (mostly luminance texture).
    mix = np.array([[0.8, 0.15, 0.05], [0.1, 0.8, 0.1], [0.05, 0.15, 0.8]], np.float32)
    lum = noise.mean(axis=2, keepdims=True)
    tex = 0.6 * lum + 0.4 * (noise @ mix.T)
    tex = 0.5 + 0.16 * tex
    tint = rng.uniform(0.7, 1.1, 3).astype(np.float32)
    tex = np.ascontiguousarray(tex * tint)
    n_shapes = int(max(8, height * width / 2500))
    shapes = np.zeros_like(tex)
    alpha = np.zeros((height, width, 1), np.float32)
    _draw_shapes(shapes, rng, n_shapes, max_size=40.0)
    alpha[..., 0] = (shapes.max(axis=2) > 0).astype(np.float32)
    alpha = cv2.GaussianBlur(alpha, (0, 0), 0.5)[..., None] * 0.7
    tex = (1 - alpha) * tex + alpha * (0.15 + 0.7 * shapes)
    return np.clip(tex, 0.04, 0.96).astype(np.float32)


def make_pattern(width: int, height: int, seed: int = 0) -> np.ndarray:
    """Make the digital calibration pattern.

    Dense multi-scale texture (1/f noise whose finest octave has a 3-pixel
    period, plus random sharp-edged shapes) that optical flow can lock onto
    everywhere, with a clear black cross on a white square at the centre for
    the coarse alignment of each view. Deterministic given ``seed``.

    How to show it: display it full screen on a monitor at its native
    resolution (one pattern pixel per screen pixel, no scaling, brightness
    well below clipping), or print it without scaling onto a rigid, flat,
    matte board. Measure the size of one pattern pixel on the board in metres
    (screen width / ``width``, or the printed width / ``width``): that is the
    pattern pitch that makes X and Y metric. Keep the board flat and
    fronto-parallel, and fill every view's image circle with it.

    Parameters
    ----------
    width, height : int
        Size in pixels (each from 64 to :data:`MAX_PATTERN_SIDE`).
    seed : int, optional
        Random seed. Default 0.

    Returns
    -------
    numpy.ndarray
        ``(height, width)`` uint8 grey-level image.

    Raises
    ------
    lfcam.InputError
        If ``width`` or ``height`` is not an integer from 64 to :data:`MAX_PATTERN_SIDE`.

    Examples
    --------
    >>> import lfcam
    >>> pat = lfcam.make_pattern(640, 480, seed=1)
    >>> pat.shape, pat.dtype
    ((480, 640), dtype('uint8'))
    """
    width = check_positive_int(width, "width", minimum=64)
    height = check_positive_int(height, "height", minimum=64)
    for name, v in (("width", width), ("height", height)):
        if v > MAX_PATTERN_SIDE:
            raise InputError(
                f"{name}: at most {MAX_PATTERN_SIDE} px (beyond any screen or print), got {v}"
            )
    rng = np.random.default_rng(np.random.SeedSequence([0x1FCA, int(seed) & 0xFFFFFFFF]))
    noise = multiscale_noise(height, width, rng, finest=3.0)[..., 0]
    img = 0.5 + 0.17 * noise
    shapes = np.zeros((height, width, 1), np.float32)
    _draw_shapes(
        shapes, rng, int(max(10, height * width / 3000)), max_size=min(height, width) / 20.0
    )
    mask = shapes[..., 0] > 0
    img[mask] = 0.5 * img[mask] + 0.5 * (0.1 + 0.8 * shapes[..., 0][mask])
    img = np.clip(img, 0.02, 0.98)
    # The cross: black bars on a white square, about a tenth of the short side.
    s = min(width, height)
    arm = max(8, s // 14)
    bar = max(2, s // 90)
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    x0, x1 = round(cx - arm), round(cx + arm) + 1
    y0, y1 = round(cy - arm), round(cy + arm) + 1
    img[y0:y1, x0:x1] = 0.98
    bx0, bx1 = round(cx - bar / 2.0), round(cx + bar / 2.0) + 1
    by0, by1 = round(cy - bar / 2.0), round(cy + bar / 2.0) + 1
    img[y0:y1, bx0:bx1] = 0.02
    img[by0:by1, x0:x1] = 0.02
    return np.round(img * 255.0).astype(np.uint8)
