"""The exception family, and the mapping of each core error variant onto it."""

from __future__ import annotations

from typing import Any

import pytest

import lfcam
from lfcam import _lfcam


def _hook(name: str) -> Any:
    """A private test hook of the extension, or a skip: release builds leave them out
    (cargo feature ``test-hooks``, which ``.ci/run`` turns on)."""
    hook = getattr(_lfcam, name, None)
    if hook is None:
        pytest.skip(f"the extension is built without the test-hooks feature ({name})")
    return hook


def test_hierarchy() -> None:
    assert issubclass(lfcam.LfcamError, Exception)
    assert issubclass(lfcam.InputError, lfcam.LfcamError)
    assert issubclass(lfcam.InputError, ValueError)
    assert issubclass(lfcam.CalibrationError, lfcam.LfcamError)
    assert not issubclass(lfcam.CalibrationError, ValueError)
    assert issubclass(lfcam.NumericalError, lfcam.LfcamError)
    assert issubclass(lfcam.NumericalError, ArithmeticError)
    assert lfcam.errors.InputError is lfcam.InputError


@pytest.mark.parametrize(
    ("variant", "cls", "message"),
    [
        ("InvalidArgument", lfcam.InputError, "arg: test InvalidArgument"),
        ("InvalidItem", lfcam.InputError, "arg[7]: test InvalidItem"),
        ("Numerical", lfcam.NumericalError, "test Numerical"),
        (
            "Internal",
            lfcam.LfcamError,
            "internal error in _raise_core_error: test Internal; please report this",
        ),
    ],
)
def test_each_core_variant_maps_to_its_class(variant: str, cls: type, message: str) -> None:
    raise_core_error = _hook("_raise_core_error")
    with pytest.raises(lfcam.LfcamError) as info:
        raise_core_error(variant)
    assert type(info.value) is cls
    assert str(info.value) == message


def test_internal_error_does_not_blame_the_input() -> None:
    # A broken invariant of the core is lfcam's bug: the base class, which neither
    # `except InputError` nor `except ValueError` catches.
    raise_core_error = _hook("_raise_core_error")
    with pytest.raises(lfcam.LfcamError) as info:
        raise_core_error("Internal")
    assert not isinstance(info.value, (lfcam.InputError, ValueError))


def test_unknown_variant_is_an_input_error() -> None:
    raise_core_error = _hook("_raise_core_error")
    with pytest.raises(lfcam.InputError, match=r"^kind: unknown core error variant"):
        raise_core_error("NoSuchVariant")


def test_panic_becomes_lfcam_error() -> None:
    panic_for_test = _hook("_panic_for_test")
    with pytest.raises(Exception) as info:  # noqa: PT011 - the class is asserted below
        panic_for_test()
    assert type(info.value) is lfcam.LfcamError
    assert str(info.value) == (
        "internal error in _panic_for_test: deliberate panic for testing; please report this"
    )
    # pyo3's PanicException derives from BaseException only; ours must not be one.
    assert "PanicException" not in type(info.value).__name__


def test_extension_still_works_after_a_panic() -> None:
    panic_for_test = _hook("_panic_for_test")
    with pytest.raises(lfcam.LfcamError):
        panic_for_test()
    import numpy as np

    views = lfcam.crop_lenslets(np.arange(12, dtype=np.uint8).reshape(3, 4), [[1, 1, 2, 2]])
    assert views.tolist() == [[[5, 6], [9, 10]]]
