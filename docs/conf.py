"""Sphinx configuration of the flyvpr documentation.

Build with ``make docs`` (warnings are errors).  Why this tool chain: the docstrings are
numpydoc, the house style of scientific Python, so Sphinx + numpydoc renders them as written
(scikit-learn uses the same stack); MyST lets the guide pages be plain Markdown that reads well
unbuilt too; sphinx-argparse generates the command-line reference from the real parser
(``flyvpr.cli.build_parser``), so it cannot drift from the program.
"""

from __future__ import annotations

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
# Document the checkout next to this folder, whatever flyvpr the environment has installed.
sys.path.insert(0, str(DOCS.parent / "src"))
sys.path.insert(0, str(DOCS))

from api_pages import write_api_pages  # noqa: E402

import flyvpr  # noqa: E402

project = "flyvpr"
author = "the flyvpr authors"
copyright = "flyvpr authors; Nordland frames: NRK (CC BY)"
release = flyvpr.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinxarg.ext",
    "docstrings",  # docs/docstrings.py: two docstring fixes and short cross-references
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "README.md"]
templates_path = []

# -- every warning is an error (``-W``), and every reference must resolve (``-n``) --------------
nitpicky = True
# No intersphinx: the build must not need the network, so names from other projects stay text.
nitpick_ignore_regex = [
    (r"py:.*", r"(dataclasses|numpy|np|scipy|torch|joblib|matplotlib|pathlib|argparse)\..*"),
    # Private modules and helpers (``flyvpr._validation...``, ``_jit``) are not documented.
    (r"py:.*", r"(flyvpr(\.\w+)*\.)?_[a-z]\w*(\.\w+)*"),
]

# Text keeps "--" and quotes as typed: prose names options such as --jobs.
smartquotes = False

# -- MyST ----------------------------------------------------------------------------------------
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

# -- the API pages are written from the package on every build (see api_pages.py) ---------------
write_api_pages(DOCS / "api")

# -- autodoc + numpydoc --------------------------------------------------------------------------
autodoc_typehints = "none"  # types are written in the numpydoc Parameters sections
autodoc_member_order = "bysource"

numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# -- HTML ----------------------------------------------------------------------------------------
html_theme = "furo"
html_title = f"flyvpr {release}"
html_static_path = ["_static"]
html_last_updated_fmt = None
