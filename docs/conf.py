"""Sphinx configuration of lfcam's documentation site.

Build: ``pip install ".[docs]" && sphinx-build -W -b html docs docs/_build/html``
(MyST markdown pages, numpydoc API reference from the docstrings).
"""

from __future__ import annotations

import lfcam

project = "lfcam"
author = "lfcam contributors"
copyright = "lfcam contributors"
release = lfcam.__version__
version = release

extensions = [
    "myst_parser",
    "numpydoc",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

autosummary_generate = True
autodoc_typehints = "none"  # numpydoc's Parameters sections say the types
autodoc_default_options = {"members": False}
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_validation_checks: set[str] = set()

html_theme = "alabaster"
html_title = f"lfcam {release}"
html_static_path: list[str] = []
suppress_warnings = ["myst.header"]
