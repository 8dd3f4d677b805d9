"""Sphinx configuration of the agsf-torch documentation site (`bash scripts/docs.sh` builds it into docs/_build/html).

The pages are Markdown (MyST); the API reference is autodoc + napoleon over the package's docstrings, which are
reST-flavoured Google style (``Args:``/``Returns:`` sections, ``double-backtick`` literals, :func:/:class:/:mod:
roles, ``.. math::``), so they render as written.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's packages, also when the editable install is missing

project = "agsf-torch"
author = "agsf-torch contributors"
copyright = "agsf-torch contributors"
release = "0.1.0"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

# MyST: $…$ / $$…$$ maths, ::: fences for directives, and anchors for headings (links to sections of other pages)
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

# autodoc + napoleon: Google-style sections, members in source order, type hints in the signature
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# `Attributes:` sections as :ivar: fields, not attribute entries: a NamedTuple's or dataclass's fields are then
# described in its docstring once, not a second time next to autodoc's entry for the same attribute
napoleon_use_ivar = True
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_preserve_defaults = True

html_theme = "furo"
html_title = "agsf-torch"
html_static_path: list[str] = []
