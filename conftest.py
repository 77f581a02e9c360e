"""Doctests (`pytest --doctest-modules --pyargs lfcam`, `--doctest-glob "*.md" docs`):
examples may use ``lfcam`` and ``np`` without importing them, as the docstrings do."""

from __future__ import annotations

import numpy as np
import pytest

import lfcam


@pytest.fixture(autouse=True)
def _doctest_names(doctest_namespace: dict[str, object]) -> None:
    doctest_namespace["lfcam"] = lfcam
    doctest_namespace["np"] = np
