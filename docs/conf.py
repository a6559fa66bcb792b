"""Sphinx configuration of the sb3-graph documentation.

Build it with ``pip install -e ".[docs]"`` and ``sphinx-build -W -b html docs docs/_build/html``: the docs extra
alone is enough. Two kinds of pages are written at every build from the code on disk (``docs/_ext/site_pages.py``),
so that they cannot drift from it:

- the API reference, one page per package group, in ``docs/_api/``;
- the environment reference's tables (environments, observation, action types, reward terms, every
  ``default_config()`` key), in ``docs/_generated/``.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "docs" / "_ext"))

import site_pages  # noqa: E402

project = "sb3-graph"
author = "sb3-graph contributors"
copyright = "sb3-graph contributors"
release = "0.1.0"

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
# _generated/ holds tables that pages include; results/ the summary file of the results tables
exclude_patterns = ["_build", "README.md", "_generated", "results", "_ext"]
myst_heading_anchors = 3
html_theme = "furo"
html_title = "sb3-graph"
html_static_path: list[str] = []

autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
autodoc_inherit_docstrings = False  # torch's and SB3's docstrings belong to their own docs
autodoc_member_order = "bysource"
# The optional extras' packages: the site builds from the docs extra alone, without the server stack
# (serve; its frames' codec msgspec is in the docs extra), the cluster executors (cluster, ray),
# PostgreSQL (postgres), rl-zoo3 (zoo) or video (video).
autodoc_mock_imports = [
    "fastapi",
    "pydantic",
    "starlette",
    "uvicorn",
    "httptools",
    "uvloop",
    "websockets",
    "dask",
    "distributed",
    "ray",
    "psycopg2",
    "rl_zoo3",
    "tensorboard",
    "imageio_ffmpeg",
]
napoleon_google_docstring = False


def write_generated_pages(app) -> None:
    """Write the API pages and the environment reference's tables (see the module docstring).

    :param app: the Sphinx application
    """
    site_pages.write_api_pages(Path(app.srcdir))
    site_pages.write_environment_tables(Path(app.srcdir))


def setup(app) -> None:
    app.connect("builder-inited", write_generated_pages)
