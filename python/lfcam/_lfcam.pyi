"""Type stub of the Rust extension module (rust/lfcam-py). Checked by mypy.stubtest."""

from typing import Final, NoReturn, TypeVar

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "__version__",
    "_panic_for_test",
    "_raise_core_error",
    "crop_lenslets",
    "get_num_threads",
    "set_num_threads",
]

_Pixel = TypeVar("_Pixel", np.uint8, np.uint16, np.float32)

__version__: Final[str]

def crop_lenslets(raw: NDArray[_Pixel], rects: NDArray[np.int64]) -> NDArray[_Pixel]:
    """Crop (N, 4) int64 rects (x0, y0, w, h) out of a C-contiguous (H, W[, C]) raw."""

def set_num_threads(n: int) -> None:
    """Set the number of threads lfcam's kernels run on (1 to 1024)."""

def get_num_threads() -> int:
    """The number of threads lfcam's kernels run on."""

def _raise_core_error(kind: str) -> NoReturn:
    """Test hook: raise the exception a core error variant maps to."""

def _panic_for_test() -> NoReturn:
    """Test hook: panic inside the panic guard (raises LfcamError)."""
