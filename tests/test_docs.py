"""The documentation: every ```python block of README.md and docs/**/*.md runs as written (SB3's
doctest habit), and the Sphinx site builds with warnings as errors when Sphinx is installed
(``pip install -e ".[docs]"``; CI installs it)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
# A fence opens with ```python (nothing else on the line but spaces) and closes with ```.
_FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.DOTALL | re.MULTILINE)


def markdown_files() -> list[Path]:
    """The README and every Markdown page of the docs, generated folders left out.

    :return: paths, README first
    """
    pages = sorted(p for p in (ROOT / "docs").rglob("*.md") if not {"_build", "_api"} & set(p.parts))
    return [ROOT / "README.md", *pages]


def python_blocks(path: Path) -> list[tuple[int, str]]:
    """The ```python blocks of one Markdown file.

    :param path: a Markdown file
    :return: (line of the opening fence, code) per block, in file order
    """
    text = path.read_text(encoding="utf-8")
    return [(text.count("\n", 0, m.start()) + 1, m.group(1)) for m in _FENCE.finditer(text)]


BLOCKS = [(path, line, code) for path in markdown_files() for line, code in python_blocks(path)]


def test_blocks_are_found(tmp_path):
    # The extraction itself: a fence of another language is not a python block, and the README has
    # python blocks (its library snippet).
    sample = tmp_path / "sample.md"
    sample.write_text("```python\nx = 1\n```\n\n```bash\nls\n```\n\n```python\ny = 2\n```\n")
    assert python_blocks(sample) == [(1, "x = 1\n"), (9, "y = 2\n")]
    assert any(path.name == "README.md" for path, _, _ in BLOCKS)


@pytest.mark.parametrize(
    "path,line,code", BLOCKS, ids=[f"{p.relative_to(ROOT)}:{line}" for p, line, _ in BLOCKS]
)
def test_python_block_runs(path, line, code, tmp_path, monkeypatch):
    # Each block runs on its own, in a fresh namespace and an empty working folder: what it writes
    # lands there, and it reaches shipped files through the packages, not through the working folder.
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYTHONPATH", str(ROOT))  # a command that a block starts runs this checkout too
    threads = torch.get_num_threads()
    try:
        # Blank lines in front: a traceback names the Markdown file and its own line.
        exec(compile("\n" * line + code, str(path), "exec"), {"__name__": "__docs__"})
    finally:
        torch.set_num_threads(threads)


def test_docs_build_strict(tmp_path):
    # The site builds with every warning an error (a missing page, a broken cross-reference, a
    # docstring that is not valid reStructuredText). The dummy builder reads and resolves every page
    # as the HTML one does, without writing HTML.
    pytest.importorskip("sphinx")
    pytest.importorskip("myst_parser")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "dummy"]
    done = subprocess.run(
        [*command, str(ROOT / "docs"), str(tmp_path / "out")], capture_output=True, text=True, env=env, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr[-4000:]
