"""Type stub of the Rust extension module (rust/lfcam-py). Checked by mypy.stubtest."""

from typing import Any, Final, TypeVar, final

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "RectifyPlan",
    "__version__",
    "btv_deblur",
    "crop_lenslets",
    "data_weights",
    "fit_board_tilts",
    "get_num_threads",
    "invert_maps",
    "nan_median",
    "place_samples",
    "plane_sweep",
    "rasterize",
    "rectify",
    "remap_bilinear",
    "set_num_threads",
    "shift_and_add",
    "shift_and_add_mean",
    "simd_info",
    "triangulate",
    "weighted_median_fill",
]

_Pixel = TypeVar("_Pixel", np.uint8, np.uint16, np.float32)

__version__: Final[str]

def crop_lenslets(raw: NDArray[_Pixel], rects: NDArray[np.int64]) -> NDArray[_Pixel]:
    """Crop (N, 4) int64 rects (x0, y0, w, h) out of a C-contiguous (H, W[, C]) raw."""

def remap_bilinear(
    src: NDArray[np.float32],
    map: NDArray[np.float32],
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """Sample C-contiguous (H, W[, C]) float32 src at (H', W', 2) map positions (x, y)."""

def rectify(
    raw: NDArray[_Pixel],
    gains: NDArray[np.float32],
    crops: NDArray[np.int64],
    warps: NDArray[np.float32],
    masks: NDArray[np.uint8] | None,
    interp: str,
    views: NDArray[np.int64] | None,
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """Gain, crop and remap views of raw into (M, H, W[, C]) float32 (NaN: no data)."""

@final
class RectifyPlan:
    """Rectification prepared once per calibration (bilinear): gains, crops, warps, masks."""

    def __new__(
        cls,
        gains: NDArray[np.float32],
        crops: NDArray[np.int64],
        warps: NDArray[np.float32],
        masks: NDArray[np.uint8] | None,
        interp: str,
    ) -> RectifyPlan: ...
    def rectify(
        self,
        raw: NDArray[_Pixel],
        views: NDArray[np.int64] | None = None,
        out: NDArray[np.float32] | None = None,
    ) -> NDArray[np.float32]:
        """Rectify views of a C-contiguous (H, W[, C]) raw into (M, Hr, Wr[, C]) float32."""

    @property
    def n_views(self) -> int: ...
    @property
    def shape(self) -> tuple[int, int]: ...
    @property
    def raw_shape(self) -> tuple[int, int]: ...
    @property
    def gain_channels(self) -> int: ...
    @property
    def kept(self) -> int: ...
    @property
    def nbytes(self) -> int: ...

def rasterize(
    vertices: NDArray[np.float32],
    colours: NDArray[np.float32],
    faces: NDArray[np.int32],
    height: int,
    width: int,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.uint8]]:
    """Z-buffer (M, 3) projected vertices (x, y, z), (M, C) colours, (K, 3) faces."""

def nan_median(
    stack: NDArray[np.float32],
) -> tuple[NDArray[np.float32], NDArray[np.uint8] | NDArray[np.uint16]]:
    """Median over axis 0 of a C-contiguous (K, ...) float32 stack ignoring NaN, and counts."""

def triangulate(
    flows: NDArray[np.float32],
    offsets: NDArray[np.float64],
    reference: int,
    weights: NDArray[np.float32] | None,
    min_views: int,
    sigma_floor: float,
    cutoff: float,
    iterations: int,
) -> tuple[
    NDArray[np.float32],
    NDArray[np.float32],
    NDArray[np.float32],
    NDArray[np.float32],
    NDArray[np.uint8],
]:
    """Robust parallax of (N, H, W, 2) float32 flows: (s, confidence, residual, perp, n_used)."""

def invert_maps(
    warps: NDArray[np.float32],
    masks: NDArray[np.uint8] | None,
    crops: NDArray[np.int64],
    raw_height: int,
    raw_width: int,
) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
    """Inverse warp maps: (H_raw, W_raw, 2) rectified positions and (H_raw, W_raw) views."""

def place_samples(
    inv: NDArray[np.float32],
    view: NDArray[np.int32],
    offsets: NDArray[np.float64],
    parallax: NDArray[np.float32],
    iterations: int,
    tolerance: float,
) -> NDArray[np.float32]:
    """Reference-frame positions p with p + o_i s(p) = q of samples at q (NaN: dropped)."""

def shift_and_add(
    positions: NDArray[np.float32],
    values: NDArray[np.float32],
    weights: NDArray[np.float32] | None,
    fine_height: int,
    fine_width: int,
    factor: float,
    sigma: float,
    radius: int,
    iterations: int,
    huber: float,
    reject: float,
    sum_out: NDArray[np.float32] | None = None,
    wsum_out: NDArray[np.float32] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Robust shift-and-add onto a fine grid: (sum (H, W, C), wsum (H, W)), written
    into sum_out / wsum_out when given."""

def shift_and_add_mean(
    positions: NDArray[np.float32],
    values: NDArray[np.float32],
    weights: NDArray[np.float32] | None,
    fine_height: int,
    fine_width: int,
    factor: float,
    sigma: float,
    radius: int,
    iterations: int,
    huber: float,
    reject: float,
    min_weight: float,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """shift_and_add's fused image: (sum / wsum where wsum >= min_weight, else 0;
    wsum; where the image has data)."""

def data_weights(wsum: NDArray[np.float32]) -> NDArray[np.float32]:
    """sqrt(clip(wsum / t, 0, 4)), t numpy's median of the positive weights (1 if none)."""

def btv_deblur(
    z: NDArray[np.float32],
    a: NDArray[np.float32],
    x0: NDArray[np.float32] | None,
    psf_sigma: float,
    lam: float,
    alpha: float,
    window: int,
    iterations: int,
    step: float,
    eps: float,
) -> NDArray[np.float32]:
    """Bilateral-TV deblurring of a (H, W, C) shift-and-add image with data weights a."""

def plane_sweep(
    views: NDArray[np.float32],
    offsets: NDArray[np.float64],
    reference: int,
    candidates: NDArray[np.float32],
    subsets: NDArray[np.uint8],
    trunc_colour: float,
    trunc_gradient: float,
    alpha: float,
    radius: int,
    eps: float,
    base: NDArray[np.float32] | None = None,
    active: NDArray[np.uint8] | None = None,
    cubic: bool = False,
) -> NDArray[np.float32]:
    """Plane sweep along the parallax lines: (H, W, S, 5) parallax, cost, curvature,
    second-best cost and cost at the candidate nearest 0 per pixel and view subset;
    candidates relative to ``base`` if given, only ``active`` pixels if given."""

def set_num_threads(n: int) -> None:
    """Set the number of threads lfcam's kernels run on (1 to 1024)."""

def get_num_threads() -> int:
    """The number of threads lfcam's kernels run on."""

def simd_info() -> dict[str, str]:
    """Which SIMD builds run: setting (LFCAM_SIMD), cpu, level, then one per kernel family."""

# Built with the cargo feature `test-hooks` only (not in release wheels), and not in
# `__all__`: `_raise_core_error(kind: str) -> NoReturn` and `_panic_for_test() -> NoReturn`.

def weighted_median_fill(
    values: NDArray[np.float32],
    weights: NDArray[np.float32],
    guide: NDArray[np.float32],
    todo: NDArray[np.uint8],
    radius: int,
    stride: int,
    sigma_colour: float,
    sigma_space: float,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Joint weighted median of ``values`` at the pixels where ``todo`` is non-zero."""

def fit_board_tilts(
    board: NDArray[np.int64],
    view: NDArray[np.int64],
    pos: NDArray[np.float64],
    parallax: NDArray[np.float64],
    weight: NDArray[np.float64],
    distances: NDArray[np.float64],
    z_b: float,
    reference: int,
    offsets: NDArray[np.float64],
    z_c: float,
    centre: tuple[float, float],
    gradient_prior: float,
    centres: NDArray[np.float64] | None = None,
    centres_weight: float = 0.0,
    fit_reference: bool = False,
    robust: bool = False,
) -> dict[str, Any]:
    """Joint fit of ``o_i``, ``Z_c`` and each board's tilt to parallax samples."""
