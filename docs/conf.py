"""Sphinx configuration of the sb3-graph documentation.

Build it with ``pip install -e ".[docs]"`` and ``sphinx-build -W -b html docs docs/_build/html``.
The API reference is one page per public module of ``sb3_graph`` and ``envs``, written into
``docs/_api/`` at every build from the packages on disk, so that a module that moves or appears
is documented without editing this file.
"""

from __future__ import annotations

import pkgutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

project = "sb3-graph"
author = "sb3-graph contributors"
release = "0.1.0"

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "README.md"]
myst_heading_anchors = 3
html_theme = "alabaster"
html_static_path: list[str] = []

autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
autodoc_inherit_docstrings = False  # torch's and SB3's docstrings belong to their own docs
autodoc_member_order = "bysource"
napoleon_google_docstring = False

#: Packages whose modules the API reference documents, and module names it leaves out: the command
#: line (documented by ``sb3-graph COMMAND --help``) and private modules (compiled kernels).
API_PACKAGES = ("sb3_graph", "envs")
API_SKIP = ("commands", "cli")


def api_modules() -> list[str]:
    """Every public module of :data:`API_PACKAGES`, found on disk without importing it.

    :return: dotted module names, sorted
    """
    names = []
    for package in API_PACKAGES:
        names.append(package)
        for info in pkgutil.walk_packages([str(ROOT / package)], prefix=f"{package}."):
            parts = info.name.split(".")
            if any(part.startswith("_") or part in API_SKIP for part in parts[1:]):
                continue
            names.append(info.name)
    return sorted(names)


def write_api_pages(app) -> None:
    """Write ``docs/_api/<module>.rst`` for every module of :func:`api_modules`, removing stale ones.

    :param app: the Sphinx application
    """
    out = Path(app.srcdir) / "_api"
    out.mkdir(exist_ok=True)
    wanted = {
        f"{name}.rst": f"``{name}``\n{'=' * (len(name) + 4)}\n\n.. automodule:: {name}\n" for name in api_modules()
    }
    for stale in out.glob("*.rst"):
        if stale.name not in wanted:
            stale.unlink()
    for file, text in wanted.items():
        path = out / file
        if not path.exists() or path.read_text() != text:
            path.write_text(text)


def setup(app) -> None:
    app.connect("builder-inited", write_api_pages)
