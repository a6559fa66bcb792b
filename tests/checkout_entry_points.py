"""The checkout's own entry points (``pyproject.toml``) as an installed distribution, for the tests.

An editable install writes its entry points when it is installed; a checkout whose
``pyproject.toml`` declares newer ones than the installed copy would run its tests against the
old ones. :func:`install` writes the checkout's entry points into a stub ``.dist-info`` and puts it
first on ``sys.path`` (and on ``PYTHONPATH`` for the commands that tests start), so the tests see
the checkout's domain plug-ins (sb3_graph/plugins.py), whatever is installed.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

_TABLE = re.compile(r'^\[project\.entry-points\."([^"]+)"\]\s*$')
_ENTRY = re.compile(r'^([A-Za-z0-9_.-]+)\s*=\s*"([^"]+)"\s*(#.*)?$')


def entry_point_tables(pyproject: Path) -> dict[str, dict[str, str]]:
    """``group -> {name: value}`` of the ``[project.entry-points."group"]`` tables of a pyproject file."""
    tables: dict[str, dict[str, str]] = {}
    group = None
    for line in pyproject.read_text().splitlines():
        line = line.strip()
        if line.startswith("["):
            match = _TABLE.match(line)
            group = match.group(1) if match else None
            if group:
                tables.setdefault(group, {})
        elif group and (match := _ENTRY.match(line)):
            tables[group][match.group(1)] = match.group(2)
    return tables


def write_distribution(folder: Path, name: str, tables: dict[str, dict[str, str]]) -> Path:
    """A minimal installed distribution ``name`` with these entry points, in ``folder``."""
    info = folder / f"{name}-0.0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.0.0\n")
    text = "".join(
        f"[{group}]\n" + "".join(f"{key} = {value}\n" for key, value in entries.items()) + "\n"
        for group, entries in tables.items()
    )
    (info / "entry_points.txt").write_text(text)
    return folder


def install(root: Path, folder: Path) -> None:
    """Put the checkout's entry points first on ``sys.path`` and ``PYTHONPATH``."""
    write_distribution(folder, "sb3_graph_checkout", entry_point_tables(root / "pyproject.toml"))
    sys.path.insert(0, str(folder))
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(folder), str(root), os.environ.get("PYTHONPATH")]))
