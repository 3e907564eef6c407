"""Sphinx configuration of mi_tetvr's documentation site.

Build: ``python -m sphinx -W -b html docs docs/_build/html`` (warnings are errors).
"""
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(DOCS.parent))

import mi_tetvr  # noqa: E402

project = "mi_tetvr"
author = "The mi_tetvr developers"
copyright = "2026, the mi_tetvr developers"
release = version = mi_tetvr.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinxarg.ext",
    "mitsuba_plugins",
    "tutorials",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "images/README.md"]
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

html_theme = "furo"
html_title = f"mi_tetvr {release}"

# autodoc: the public API, numpy-style docstrings, in source order
autodoc_member_order = "bysource"
autodoc_default_options = {"show-inheritance": False}
autodoc_typehints = "description"
napoleon_google_docstring = False
napoleon_numpy_docstring = True
# a class's Attributes section as fields of the class, not as attributes autodoc documents again
napoleon_use_ivar = True
# the renderer's modules need a Mitsuba variant (set before autodoc imports them)
import mitsuba as mi  # noqa: E402
mi.set_variant("llvm_ad_rgb")
