"""Sphinx configuration of chunkdic's documentation (``make -C docs html``)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))
sys.path.insert(0, str(HERE.parent))  # validation.record, read by the validation tables

import chunkdic  # noqa: E402

project = "chunkdic"
author = "the chunkdic developers"
copyright = "2026, the chunkdic developers"
release = version = chunkdic.__version__

extensions = [
    "myst_parser",
    "numpydoc",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx_gallery.gen_gallery",
    "chunkdic_docs",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "tools", "examples/README.txt", "**/README.md", "gallery/*.ipynb",
                    "gallery/*.py", "gallery/*.zip", "gallery/*.json", "gallery/*.md5"]
templates_path = ["_templates"]

# MyST: $...$ and $$...$$ maths, ::: fences, anchors for headings up to level 3
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# the API pages: one page per public name (docs/api.rst is written from chunkdic/__init__.pyi)
autosummary_generate = True
autodoc_typehints = "none"  # numpydoc's parameter lists say the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False

sphinx_gallery_conf = {
    "examples_dirs": "examples",
    "gallery_dirs": "gallery",
    "filename_pattern": r"/plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "matplotlib_animations": False,
    "within_subsection_order": "FileNameSortKey",
    # the examples write their scans under one temporary directory each, removed after the example
    "reset_modules": ("matplotlib",),
    "abort_on_example_error": True,
    "show_memory": False,
}

html_theme = "pydata_sphinx_theme"
html_title = f"chunkdic {version}"
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "secondary_sidebar_items": ["page-toc"],
    "footer_start": ["copyright"],
    "footer_end": [],
}
html_static_path: list[str] = []
html_show_sourcelink = False

# the examples run on the embedded scheduler with at most the machine's cores
os.environ.setdefault("MPLBACKEND", "Agg")
