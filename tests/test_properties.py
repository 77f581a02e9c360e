"""Property tests (hypothesis) over the public array functions and the core's kernels:
any shape (tiny and degenerate included), dtype, strides, NaN and inf either give a
correct result or an InputError naming the argument: never another exception, a
panic (an "internal error" LfcamError) or a crash."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import lfcam
import lfcam._lfcam as core
from lfcam.errors import InputError

SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)

DTYPES = st.sampled_from(
    [np.uint8, np.uint16, np.float32, np.float64, np.int32, np.int64, np.bool_, np.complex64]
)
SPECIAL = st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, -np.inf, 1e30, -1e-30, 255.0])


def _arrays(dtype: Any, shape: Any, allow_special: bool = True) -> st.SearchStrategy[np.ndarray]:
    dt = np.dtype(dtype)
    if dt.kind == "f" and allow_special:
        elements = st.one_of(st.floats(-2, 2, width=dt.itemsize * 8), SPECIAL)
        return hnp.arrays(dt, shape, elements=elements)
    return hnp.arrays(dt, shape)


@st.composite
def strided(draw: st.DrawFn, arr: np.ndarray) -> np.ndarray:
    """The array as given, or the same values in a non-contiguous or reversed view."""
    how = draw(st.sampled_from(["as is", "padded", "reversed", "fortran"]))
    if how == "padded" and arr.ndim >= 1:
        big = np.zeros((*arr.shape[:-1], arr.shape[-1] * 2), arr.dtype)
        big[..., ::2] = arr
        return big[..., ::2]
    if how == "reversed" and arr.ndim >= 1:
        return np.ascontiguousarray(arr[::-1])[::-1]
    if how == "fortran":
        return np.asfortranarray(arr)
    return arr


def _run(fn: Callable[..., Any], *args: Any, **kw: Any) -> Any:
    """fn's result, or None if it raised InputError; anything else fails the test."""
    try:
        return fn(*args, **kw)
    except InputError as e:
        msg = str(e)
    except lfcam.LfcamError as e:  # a panic or broken invariant in the core
        pytest.fail(f"{type(e).__name__}: {e}")
    assert msg, "an InputError without a message"
    assert "internal error" not in msg
    return None


shape2 = st.tuples(st.integers(0, 9), st.integers(0, 9))


@SETTINGS
@given(data=st.data(), dtype=DTYPES, shape=shape2, channels=st.sampled_from([None, 1, 2, 3, 4, 5]))
def test_crop_lenslets(
    data: st.DataObject, dtype: Any, shape: tuple[int, int], channels: Any
) -> None:
    full = shape if channels is None else (*shape, channels)
    raw = data.draw(strided(data.draw(_arrays(dtype, full))))
    n = data.draw(st.integers(0, 4))
    rects = data.draw(hnp.arrays(np.int64, (n, 4), elements=st.integers(-2, 11)))
    out = _run(lfcam.crop_lenslets, raw, rects)
    if out is None:
        return
    for i, (x0, y0, w, h) in enumerate(rects.tolist()):
        np.testing.assert_array_equal(out[i], raw[y0 : y0 + h, x0 : x0 + w])


@SETTINGS
@given(data=st.data(), h=st.integers(0, 7), w=st.integers(0, 7), c=st.sampled_from([None, 1, 3, 5]))
def test_remap_bilinear_identity_and_hostile_maps(
    data: st.DataObject, h: int, w: int, c: Any
) -> None:
    shape = (h, w) if c is None else (h, w, c)
    src = data.draw(strided(data.draw(_arrays(np.float32, shape))))
    # An identity map samples every pixel exactly; a hostile one must not crash.
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    ident = np.dstack([xx, yy])
    out = _run(lfcam.remap_bilinear, src, ident)
    if out is not None and np.isfinite(src).all():  # inf * a zero weight is NaN
        np.testing.assert_array_equal(out, np.asarray(src, np.float32))
    hm, wm = data.draw(st.integers(0, 5)), data.draw(st.integers(0, 5))
    bad = data.draw(_arrays(np.float32, (hm, wm, data.draw(st.sampled_from([1, 2, 3])))))
    out = _run(lfcam.remap_bilinear, src, data.draw(strided(bad)))
    if out is not None:
        assert out.shape[:2] == (hm, wm)
        assert out.dtype == np.float32


@SETTINGS
@given(data=st.data(), k=st.integers(0, 6), rest=st.lists(st.integers(0, 5), max_size=3))
def test_nan_median_matches_numpy(data: st.DataObject, k: int, rest: list[int]) -> None:
    stack = data.draw(strided(data.draw(_arrays(np.float32, (k, *rest)))))
    got = _run(lfcam.nan_median, stack)
    if got is None:
        return
    med, count = got
    with np.errstate(all="ignore"):
        finite = np.isfinite(stack) | np.isinf(stack)  # NaN is what is ignored
        assert np.array_equal(count, (~np.isnan(stack)).sum(axis=0))
        have = finite.any(axis=0)
        if have.any():
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                want = np.nanmedian(stack.astype(np.float64), axis=0)
            np.testing.assert_allclose(med[have], want[have], rtol=1e-6, atol=0)
        assert np.isnan(med[~have]).all()


@SETTINGS
@given(
    data=st.data(),
    n=st.integers(0, 5),
    h=st.integers(0, 5),
    w=st.integers(0, 5),
    reference=st.integers(-1, 5),
)
def test_triangulate_never_crashes(
    data: st.DataObject, n: int, h: int, w: int, reference: int
) -> None:
    flows = data.draw(strided(data.draw(_arrays(np.float32, (n, h, w, 2)))))
    offsets = data.draw(_arrays(np.float64, (n, 2)))
    res = _run(lfcam.triangulate, flows, offsets, reference)
    if res is not None:
        assert res.parallax.shape == (h, w)


@SETTINGS
@given(
    data=st.data(),
    h=st.integers(0, 6),
    w=st.integers(0, 6),
    c=st.integers(0, 5),
    window=st.integers(0, 10),
    iterations=st.integers(0, 3),
)
def test_btv_deblur_any_size_and_window(
    data: st.DataObject, h: int, w: int, c: int, window: int, iterations: int
) -> None:
    finite = data.draw(st.booleans())
    z = data.draw(_arrays(np.float32, (h, w, c), allow_special=not finite))
    a = data.draw(hnp.arrays(np.float32, (h, w), elements=st.floats(0, 2, width=32)))
    out = _run(core.btv_deblur, z, a, None, 0.6, 0.015, 0.7, window, iterations, 0.02, 0.01)
    if out is not None:
        assert out.shape == z.shape
        if finite:
            assert np.isfinite(out).all()


@SETTINGS
@given(data=st.data(), h=st.integers(0, 6), w=st.integers(0, 6))
def test_data_weights_formula(data: st.DataObject, h: int, w: int) -> None:
    wsum = data.draw(_arrays(np.float32, (h, w)))
    got = _run(core.data_weights, wsum)
    if got is None or not np.isfinite(wsum).all():
        return
    pos = wsum[wsum > 0]
    t = np.median(pos) if pos.size else 1.0
    want = np.sqrt(np.clip(wsum / np.float32(t), 0, 4))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


@SETTINGS
@given(
    data=st.data(),
    m=st.integers(0, 20),
    c=st.integers(0, 4),
    hf=st.integers(0, 8),
    wf=st.integers(0, 8),
    radius=st.integers(0, 3),
)
def test_shift_and_add_never_crashes(
    data: st.DataObject, m: int, c: int, hf: int, wf: int, radius: int
) -> None:
    positions = data.draw(_arrays(np.float32, (m, 2)))
    values = data.draw(_arrays(np.float32, (m, c)))
    out = _run(
        core.shift_and_add, positions, values, None, hf, wf, 2.0, 0.4, radius, 1, 0.015, 0.15
    )
    if out is not None:
        total, wsum = out
        assert total.shape[:2] == wsum.shape == (hf, wf)


@SETTINGS
@given(
    data=st.data(),
    m=st.integers(0, 6),
    k=st.integers(0, 4),
    h=st.integers(0, 6),
    w=st.integers(0, 6),
)
def test_rasterize_never_crashes(data: st.DataObject, m: int, k: int, h: int, w: int) -> None:
    vertices = data.draw(_arrays(np.float32, (m, 3)))
    colours = data.draw(_arrays(np.float32, (m, 3)))
    faces = data.draw(hnp.arrays(np.int32, (k, 3), elements=st.integers(-1, 7)))
    out = _run(core.rasterize, vertices, colours, faces, h, w)
    if out is not None:
        assert out[0].shape[:2] == (h, w)


@SETTINGS
@given(data=st.data(), dtype=DTYPES, shape=st.tuples(st.integers(0, 6), st.integers(0, 6)))
def test_write_read_image_round_trip_or_refusal(
    data: st.DataObject, dtype: Any, shape: tuple[int, int], tmp_path_factory: Any
) -> None:
    img = data.draw(strided(data.draw(_arrays(dtype, shape))))
    ext = data.draw(st.sampled_from([".png", ".tif"]))
    path = tmp_path_factory.mktemp("img") / f"a{ext}"
    if _run(lfcam.io.write_image, path, img) is None and not path.exists():
        return
    back = _run(lfcam.read_image, path)
    if np.dtype(dtype) in (np.uint8, np.uint16, np.float32):
        assert back is not None
        assert back.dtype == img.dtype
        np.testing.assert_array_equal(back, img)
