"""Sphinx configuration: the Markdown pages of docs/ (MyST) and reference pages generated from the
package's docstrings (autodoc). Build: ``bash scripts/build_docs.sh`` (HTML in docs/_build/html)."""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.abspath(".."))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

project = "torchir"
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.viewcode"]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "results"]  # results/: benchmark runs, rendered into measured.md
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
napoleon_use_ivar = True  # "Attributes:" as fields: a NamedTuple's fields are not documented twice
myst_heading_anchors = 3
html_theme = "alabaster"
autodoc_inherit_docstrings = False  # Lightning's own docstrings are not ours to render
suppress_warnings = ["myst.xref_missing"]  # the link back to ../README.md lies outside the site


def _write_results_page(app) -> None:
    """docs/measured.md from the benchmark runs kept in docs/results/ (torchir.bench.pages)."""
    from pathlib import Path

    from torchir.bench.pages import results_page

    here = Path(app.srcdir)
    page = results_page(here / "results")
    target = here / "measured.md"
    if not target.exists() or target.read_text() != page:  # unchanged: no rebuild of the page
        target.write_text(page)


def setup(app) -> None:
    app.connect("builder-inited", _write_results_page)
