"""Sphinx configuration: the user docs (Markdown, through MyST) and the API reference built
from the docstrings. Build with ``python -m sphinx -W -b html docs docs/_build/html``."""

import prdp_fem

project = "prdp_fem"
release = version = prdp_fem.__version__
extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.mathjax", "myst_parser"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath"]
autodoc_member_order = "bysource"
autodoc_typehints = "none"          # the signatures show the types; long unions clutter the text
autodoc_default_options = {"members": True, "show-inheritance": False}
napoleon_numpy_docstring = True
napoleon_google_docstring = False
napoleon_use_ivar = True  # a NamedTuple's fields are documented once, as its members
html_theme = "alabaster"
html_title = "prdp_fem"
