"""The documentation: every ```python block of README.md and docs/**/*.md runs as written (SB3's
doctest habit), and the Sphinx site builds with warnings as errors, without the packages that only the other
extras install, when Sphinx is installed (``pip install -e ".[docs]"``; CI installs it)."""

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
    pages = sorted(p for p in (ROOT / "docs").rglob("*.md") if not {"_build", "_api", "_generated"} & set(p.parts))
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


#: What the test extra installs and the docs extra does not: the site must build without it (``.ci/run`` also builds
#: it in a fresh venv with the docs extra alone).
NOT_IN_DOCS_EXTRA = (
    "fastapi", "pydantic", "starlette", "uvicorn", "httptools", "uvloop", "websockets", "dask",
    "distributed", "ray", "psycopg2", "rl_zoo3", "tensorboard", "trustme", "hypothesis", "imageio_ffmpeg",
)  # fmt: skip
def _shadow(folder: Path) -> Path:
    """A folder of stand-ins that fail to import, one per package of :data:`NOT_IN_DOCS_EXTRA`: first on
    ``PYTHONPATH``, it makes a process see those packages as absent, as in a venv with the docs extra alone."""
    folder.mkdir()
    for name in NOT_IN_DOCS_EXTRA:
        text = f"raise ModuleNotFoundError('No module named {name} (not in the docs extra)', name={name!r})\n"
        (folder / f"{name}.py").write_text(text)
    return folder


def test_docs_build_strict_without_the_other_extras(tmp_path):
    # The site builds with every warning an error (a missing page, a broken cross-reference, a
    # docstring that is not valid reStructuredText, a module that autodoc cannot import) when only the docs
    # extra is installed. The dummy builder reads and resolves every page as the HTML one does, without writing HTML.
    pytest.importorskip("sphinx")
    pytest.importorskip("myst_parser")
    pytest.importorskip("furo")
    shadow = _shadow(tmp_path / "absent")
    env = {**os.environ, "PYTHONPATH": f"{shadow}{os.pathsep}{ROOT}", "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "dummy"]
    done = subprocess.run(
        [*command, str(ROOT / "docs"), str(tmp_path / "out")], capture_output=True, text=True, env=env, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr[-4000:]


def test_the_stand_ins_make_a_package_absent(tmp_path):
    # The build above proves something only if the stand-ins really hide the packages in its process.
    shadow = _shadow(tmp_path / "absent")
    env = {**os.environ, "PYTHONPATH": str(shadow)}
    done = subprocess.run([sys.executable, "-c", "import pydantic"], capture_output=True, text=True, env=env)
    assert done.returncode != 0 and "not in the docs extra" in done.stderr


def test_every_config_key_is_in_the_environment_reference():
    # The environment reference's table is written from default_config() and its docstring: a new key
    # without a line in the docstring would show an empty meaning.
    sys.path.insert(0, str(ROOT / "docs" / "_ext"))
    import site_pages

    from envs.simulation.env import CoopIntersectionEnv

    table = site_pages.config_table().splitlines()[2:]
    keys = list(CoopIntersectionEnv.default_config())
    assert [row.split("|")[1].strip() for row in table] == [f"`{key}`" for key in keys]
    assert all(row.split("|")[4].strip() for row in table), [row for row in table if not row.split("|")[4].strip()]
    assert "| `delay` | 0.1 | 0 |" in site_pages.reward_table()


def test_the_api_reference_is_grouped_by_package():
    sys.path.insert(0, str(ROOT / "docs" / "_ext"))
    import site_pages

    pages = site_pages.api_pages()
    assert 8 <= len(pages) <= 16  # a page per package, not one per module
    assert site_pages.api_group("sb3_graph.td3.policies") == "sb3_graph.algorithms"
    assert site_pages.api_group("sb3_graph.common.layers.layouts") == "sb3_graph.common"
    assert site_pages.api_group("envs.serve.app") == "envs.serve" and site_pages.api_group("envs.domain") == "envs"
    documented = [line.split()[-1] for text in pages.values() for line in text.splitlines() if "automodule" in line]
    assert sorted(documented) == site_pages.api_modules()  # every module once


def test_the_command_line_reference_has_every_command():
    # Written from the parsers: every command of the package and of the domain, with its flags as --help shows them.
    sys.path.insert(0, str(ROOT / "docs" / "_ext"))
    import site_pages

    page = site_pages.cli_reference()
    for name in site_pages.command_table():
        assert f"## `sb3-graph {name}`" in page and f"usage: sb3-graph {name} " in page
    assert "--scenario-dir" in page and "--token-file" in page
    assert "{include} _generated/cli.md" in (ROOT / "docs" / "cli.md").read_text()


def test_the_examples_page_has_every_example():
    sys.path.insert(0, str(ROOT / "docs" / "_ext"))
    import site_pages

    page = site_pages.examples_page()
    for path in (ROOT / "examples").glob("*.py"):
        assert f"## `examples/{path.name}`" in page and path.read_text().rstrip() in page


def test_citation_and_changelog():
    yaml = pytest.importorskip("yaml")
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert citation["cff-version"] == "1.2.0" and citation["title"] and citation["authors"]
    import sb3_graph

    assert str(citation["version"]) == sb3_graph.__version__
    paper = citation["references"][0]
    assert [a["family-names"] for a in paper["authors"]] == ["Klimke", "Völz", "Buchholz"] and paper["year"] == 2022
    assert f"## {sb3_graph.__version__}" in (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")


def test_the_tested_versions_table_lists_what_the_script_prints():
    # The versions are those of the machine that ran the figures; the rows are the script's, so that rerunning it
    # rewrites the table rather than a hand-kept copy.
    sys.path.insert(0, str(ROOT / "scripts"))
    import tested_versions

    install = (ROOT / "docs" / "install.md").read_text(encoding="utf-8")
    rows = [line.split("|")[1].strip() for line in tested_versions.table().splitlines()[2:]]
    page = [line.split("|")[1].strip() for line in install.split("## Tested versions")[1].splitlines() if "|" in line]
    assert page[2:] == rows


def test_the_hand_written_scenario_of_the_guide_is_valid():
    # "Your own scenarios" shows a scenario file that a user copies: it must load, and every route the page's
    # table lists is one of its layout's.
    import json

    from envs.simulation.layouts import LAYOUT_NAMES, build_layout
    from envs.simulation.traffic import Scenario

    page = (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8")
    block = re.search(r"^```json\n(.*?)^```", page, re.DOTALL | re.MULTILINE).group(1)
    scenario = Scenario.from_dict(json.loads(block), "docs/scenarios.md")
    scenario.validate("docs/scenarios.md")
    assert scenario.num_vehicles == 3 and scenario.human.tolist() == [False, False, True]
    sys.path.insert(0, str(ROOT / "docs" / "_ext"))
    import site_pages

    table = site_pages.routes_table()
    for name in LAYOUT_NAMES:
        assert all(f"| `{route}` |" in table for route in build_layout(name).route_names)


#: the pages that keep the record of what was measured, with dates and the machine's load; every other page is a guide
RESEARCH_PAGES = ("experiments.md", "speed.md")


def test_guides_say_no_today_and_no_load_average():
    # A guide states what holds, with its command; a figure that depends on the day or on the machine's load
    # belongs to the experiments or speed page, which say when and under what load they measured it.
    found = []
    for path in markdown_files():
        if path.name in RESEARCH_PAGES:
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"\btoday\b|load average", line, re.IGNORECASE):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:80]}")
    assert found == [], "\n".join(found)
