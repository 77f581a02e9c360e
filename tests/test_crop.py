"""crop_lenslets against numpy slicing, and every kind of bad input."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

import lfcam
import lfcam.errors
import lfcam.kernels.crop
from lfcam import _lfcam

DTYPES = [np.uint8, np.uint16, np.float32]
CHANNELS = [None, 3, 4]  # None: mono (H, W)


def make_raw(h: int, w: int, channels: int | None, dtype: type, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (h, w) if channels is None else (h, w, channels)
    if np.dtype(dtype).kind == "f":
        return rng.random(shape, dtype=np.float32)
    return rng.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True, dtype=dtype)


def grid_rects(rows: int, cols: int, vw: int, vh: int, x0: int = 0, y0: int = 0) -> np.ndarray:
    return np.array(
        [[x0 + c * vw, y0 + r * vh, vw, vh] for r in range(rows) for c in range(cols)],
        dtype=np.int64,
    )


def reference(raw: np.ndarray, rects: np.ndarray) -> np.ndarray:
    return np.stack([raw[y : y + h, x : x + w] for x, y, w, h in rects])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("channels", CHANNELS)
@pytest.mark.parametrize(
    ("grid", "view"),
    [((3, 4), (48, 36)), ((1, 1), (5, 3)), ((2, 2), (1, 1)), ((3, 4), (160, 120))],
)
def test_equals_numpy_slicing(
    dtype: type, channels: int | None, grid: tuple[int, int], view: tuple[int, int]
) -> None:
    (rows, cols), (vw, vh) = grid, view
    raw = make_raw(rows * vh + 7, cols * vw + 5, channels, dtype)
    rects = grid_rects(rows, cols, vw, vh, x0=2, y0=3)
    views = lfcam.crop_lenslets(raw, rects)
    want = reference(raw, rects)
    assert views.dtype == raw.dtype
    assert views.shape == want.shape
    assert views.flags.c_contiguous
    assert np.array_equal(views, want)


def test_large_frame_parallel_path() -> None:
    # 12 views of 480x360 RGB: ~6 MB of output, well above the serial threshold.
    raw = make_raw(1080, 1920, 3, np.uint8)
    rects = grid_rects(3, 4, 480, 360)
    assert np.array_equal(lfcam.crop_lenslets(raw, rects), reference(raw, rects))


def test_overlapping_and_repeated_rects() -> None:
    raw = make_raw(50, 60, None, np.uint16)
    rects = np.array([[0, 0, 20, 10], [5, 3, 20, 10], [5, 3, 20, 10], [40, 40, 20, 10]])
    assert np.array_equal(lfcam.crop_lenslets(raw, rects), reference(raw, rects))


@pytest.mark.parametrize(
    "make_view",
    [
        pytest.param(lambda a: a.transpose(1, 0, 2), id="transposed"),
        pytest.param(lambda a: a[::2, ::3], id="strided"),
        pytest.param(lambda a: a[:, :, ::-1], id="reversed-channels"),
        pytest.param(lambda a: np.asfortranarray(a), id="fortran"),
        pytest.param(lambda a: a[5:, 7:], id="offset-rows"),
    ],
)
def test_non_contiguous_input(make_view) -> None:  # type: ignore[no-untyped-def]
    base = make_raw(120, 150, 3, np.float32)
    raw = make_view(base)
    rects = grid_rects(2, 2, 20, 15, x0=1, y0=2)
    views = lfcam.crop_lenslets(raw, rects)
    assert np.array_equal(views, reference(raw, rects))


def test_array_likes_are_accepted() -> None:
    raw = [[1, 2, 3], [4, 5, 6]]
    views = lfcam.crop_lenslets(np.array(raw, dtype=np.uint8), [(1, 0, 2, 2)])
    assert views.tolist() == [[[2, 3], [5, 6]]]
    rects32 = np.array([[0, 0, 2, 1]], dtype=np.uint32)
    assert lfcam.crop_lenslets(np.array(raw, dtype=np.uint16), rects32).tolist() == [[[1, 2]]]


def test_input_is_not_modified_and_output_is_a_new_array() -> None:
    raw = make_raw(30, 40, None, np.uint8)
    before = raw.copy()
    views = lfcam.crop_lenslets(raw, [[0, 0, 40, 30]])
    views[...] = 0
    assert np.array_equal(raw, before)
    assert not np.shares_memory(views, raw)


@pytest.mark.parametrize(
    ("bad", "needle"),
    [
        ([1900, 10, 100, 100], "(1900, 10, 100, 100) lies outside the 1920x1080 frame"),
        ([-1, 0, 100, 100], "lies outside the 1920x1080 frame"),
        ([0, 981, 100, 100], "lies outside the 1920x1080 frame"),
        ([2**62, 2**62, 100, 100], "lies outside"),
        ([0, 0, 100, 101], "differs from that of rects[0], (100, 100)"),
        ([0, 0, 0, 0], "at least 1"),
    ],
)
def test_bad_rectangle_raises_input_error_naming_its_index(bad: list[int], needle: str) -> None:
    raw = np.zeros((1080, 1920), np.uint8)
    rects = [[0, 0, 100, 100], [100, 0, 100, 100], bad]
    with pytest.raises(lfcam.InputError) as info:
        lfcam.crop_lenslets(raw, rects)
    assert isinstance(info.value, ValueError)
    message = str(info.value)
    assert message.startswith("rects[2]: ")
    assert needle in message


@pytest.mark.parametrize("dtype", [np.float64, np.int32, np.bool_, np.int8, np.complex64])
def test_wrong_dtype_names_raw(dtype: type) -> None:
    raw = np.zeros((10, 10), dtype=dtype)
    with pytest.raises(lfcam.InputError, match=r"^raw: dtype .* is not supported"):
        lfcam.crop_lenslets(raw, [[0, 0, 2, 2]])
    # The bindings check again, for callers of the private module.
    with pytest.raises(lfcam.InputError, match=r"^raw: dtype .* is not supported"):
        _lfcam.crop_lenslets(raw, np.array([[0, 0, 2, 2]], dtype=np.int64))


@pytest.mark.parametrize("shape", [(10,), (2, 10, 10, 3), ()])
def test_wrong_ndim_names_raw(shape: tuple[int, ...]) -> None:
    with pytest.raises(lfcam.InputError, match=r"^raw: expected a \(H, W\) or \(H, W, C\) image"):
        lfcam.crop_lenslets(np.zeros(shape, np.uint8), [[0, 0, 1, 1]])
    with pytest.raises(lfcam.InputError, match=r"^raw: expected a 2-D"):
        _lfcam.crop_lenslets(np.zeros(shape, np.uint8), np.array([[0, 0, 1, 1]]))


def test_empty_raw_names_raw() -> None:
    with pytest.raises(lfcam.InputError, match=r"^raw: image is empty"):
        lfcam.crop_lenslets(np.zeros((0, 10), np.uint8), [[0, 0, 1, 1]])
    with pytest.raises(lfcam.InputError, match=r"^raw: image is empty"):
        _lfcam.crop_lenslets(np.zeros((4, 4, 0), np.uint8), np.array([[0, 0, 1, 1]]))


@pytest.mark.parametrize(
    ("rects", "needle"),
    [
        ([0, 0, 2, 2], "expected shape (N, 4), got (4,)"),
        ([[0, 0, 2]], "expected shape (N, 4), got (1, 3)"),
        ([[0.0, 0.0, 2.0, 2.0]], "expected integers"),
        ([[True, False, True, True]], "expected integers"),
        (np.full((1, 4), 2**63, dtype=np.uint64), "do not fit in int64"),
    ],
)
def test_bad_rects_array_names_rects(rects: object, needle: str) -> None:
    with pytest.raises(lfcam.InputError, match=r"^rects: ") as info:
        lfcam.crop_lenslets(np.zeros((8, 8), np.uint8), rects)
    assert needle in str(info.value)


def test_no_rects_names_rects() -> None:
    with pytest.raises(lfcam.InputError, match=r"^rects: at least one rectangle"):
        lfcam.crop_lenslets(np.zeros((8, 8), np.uint8), np.zeros((0, 4), np.int64))


def test_bindings_check_their_own_arguments() -> None:
    raw = np.zeros((8, 8), np.uint8)
    with pytest.raises(lfcam.InputError, match=r"^raw: expected a numpy.ndarray, got list"):
        _lfcam.crop_lenslets([[1]], np.array([[0, 0, 1, 1]]))
    with pytest.raises(lfcam.InputError, match=r"^rects: expected dtype int64, got int32"):
        _lfcam.crop_lenslets(raw, np.array([[0, 0, 1, 1]], dtype=np.int32))
    with pytest.raises(lfcam.InputError, match=r"^raw: must be C-contiguous"):
        _lfcam.crop_lenslets(raw[:, ::2], np.array([[0, 0, 1, 1]]))
    with pytest.raises(lfcam.InputError, match=r"^raw: must be C-contiguous"):
        _lfcam.crop_lenslets(
            np.asfortranarray(np.zeros((8, 6), np.uint8)), np.array([[0, 0, 1, 1]])
        )
    with pytest.raises(lfcam.InputError, match=r"^rects: must be C-contiguous"):
        _lfcam.crop_lenslets(raw, np.zeros((4, 2), np.int64).T)


def test_unallocatable_output_raises_memory_error() -> None:
    # 100 000 full-frame views of 1920x1080 RGB: ~620 GB.
    raw = np.zeros((1080, 1920, 3), np.uint8)
    rects = np.tile(np.array([0, 0, 1920, 1080], np.int64), (100_000, 1))
    with pytest.raises(MemoryError):
        lfcam.crop_lenslets(raw, rects)


@pytest.mark.parametrize("module", [lfcam.kernels.crop, lfcam.errors])
def test_docstring_examples(module: object) -> None:
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)  # type: ignore[arg-type]
    assert result.attempted > 0
    assert result.failed == 0
