"""nan_median against numpy.nanmedian, and bad inputs."""

from __future__ import annotations

import doctest
import warnings

import numpy as np
import pytest

import lfcam
import lfcam.kernels.stats
from lfcam import _lfcam

RNG = np.random.default_rng(7)


def numpy_reference(stack: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "All-NaN slice encountered"
        return np.nanmedian(stack, axis=axis), (~np.isnan(stack)).sum(axis=axis)


def random_stack(shape: tuple[int, ...], nan_fraction: float = 0.3) -> np.ndarray:
    stack = RNG.normal(0, 100, shape).astype(np.float32)
    # Ties and repeated values, as maps of whole pixels have.
    stack[RNG.random(shape) < 0.2] = 3.0
    stack[RNG.random(shape) < nan_fraction] = np.nan
    return stack


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5, 8, 31, 32, 33, 100, 256, 700])
def test_equals_numpy_nanmedian(k: int) -> None:
    stack = random_stack((k, 37, 23, 2))
    stack[:, 0, 0, :] = np.nan  # all-NaN columns
    stack[:, 1, 1, 0] = np.nan
    stack[0, 1, 1, 0] = 5.0  # a single value
    median, count = lfcam.nan_median(stack)
    want, want_count = numpy_reference(stack)
    assert median.dtype == np.float32
    assert median.shape == count.shape == (37, 23, 2)
    assert count.dtype == (np.uint8 if k <= 255 else np.uint16)
    np.testing.assert_array_equal(median, want)  # exactly, NaN where all are NaN
    np.testing.assert_array_equal(count, want_count)
    assert np.isnan(median[0, 0]).all()
    assert median[1, 1, 0] == 5.0


@pytest.mark.parametrize("axis", [0, 1, 2, -1, -3])
def test_axis(axis: int) -> None:
    stack = random_stack((6, 7, 8))
    median, count = lfcam.nan_median(stack, axis=axis)
    want, want_count = numpy_reference(stack, axis)
    np.testing.assert_array_equal(median, want)
    np.testing.assert_array_equal(count, want_count)


def test_one_dimensional_stack_and_infinities() -> None:
    median, count = lfcam.nan_median(np.array([np.inf, 1.0, np.nan, -2.0], np.float32))
    assert median.shape == ()
    assert count.shape == ()
    assert median == 1.0
    assert count == 3
    median, count = lfcam.nan_median(np.array([[np.inf, np.inf], [1.0, -np.inf]], np.float32))
    np.testing.assert_array_equal(median, [np.inf, np.nan])  # (inf + -inf) / 2, as numpy
    np.testing.assert_array_equal(count, [2, 2])


def test_large_stack_parallel_path() -> None:
    # Five captures of a 1350 x 2000 warp map, as in calibration.
    stack = random_stack((5, 1350, 2000, 2), nan_fraction=0.1)
    median, count = lfcam.nan_median(stack)
    want, want_count = numpy_reference(stack)
    np.testing.assert_array_equal(median, want)
    np.testing.assert_array_equal(count, want_count)


def test_non_contiguous_and_input_untouched() -> None:
    base = random_stack((4, 30, 40))
    view = base[:, ::2, ::-1]
    before = base.copy()
    median, _ = lfcam.nan_median(view)
    np.testing.assert_array_equal(median, numpy_reference(view)[0])
    np.testing.assert_array_equal(base, before)


@pytest.mark.parametrize(
    ("stack", "axis", "needle"),
    [
        (np.zeros((3, 4)), 0, r"^stack: expected float32, got dtype float64"),
        (np.zeros((3, 4), np.int32), 0, r"^stack: expected float32, got dtype int32"),
        (np.float32(1.0), 0, r"^stack: expected at least 1 dimension"),
        (np.zeros((0, 4), np.float32), 0, r"^stack: has no values along axis 0 \(K = 0\)"),
        (np.zeros((3, 4), np.float32), 2, r"^axis: 2 is out of range for a 2-D stack"),
        (np.zeros((3, 4), np.float32), 1.0, r"^axis: expected an integer"),
        (np.zeros((3, 4), np.float32), True, r"^axis: expected an integer"),
    ],
)
def test_bad_inputs_name_the_argument(stack: np.ndarray, axis: object, needle: str) -> None:
    with pytest.raises(lfcam.InputError, match=needle):
        lfcam.nan_median(stack, axis=axis)  # type: ignore[arg-type]


def test_too_many_values_and_bindings_checks() -> None:
    big = np.zeros((65536, 1), np.float32)
    with pytest.raises(lfcam.InputError, match=r"^stack: K = 65536 values per element"):
        lfcam.nan_median(big)
    with pytest.raises(lfcam.InputError, match=r"^stack: K = 65536 values per element"):
        _lfcam.nan_median(big)
    with pytest.raises(lfcam.InputError, match=r"^stack: must be C-contiguous"):
        _lfcam.nan_median(np.zeros((4, 6), np.float32)[:, ::2])
    with pytest.raises(lfcam.InputError, match=r"^stack: expected dtype float32, got float64"):
        _lfcam.nan_median(np.zeros((4, 6)))
    with pytest.raises(lfcam.InputError, match=r"^stack: has no values along axis 0"):
        _lfcam.nan_median(np.zeros((0, 6), np.float32))


def test_docstring_examples() -> None:
    result = doctest.testmod(lfcam.kernels.stats, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0
