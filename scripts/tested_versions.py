"""Print the install page's table of tested versions (docs/install.md, "Tested versions") from the installed packages.

    python scripts/tested_versions.py

A package that is not installed shows ``-``.
"""

from __future__ import annotations

import platform
from importlib import metadata

#: rows of the table: label -> the distributions whose versions it lists
ROWS: dict[str, tuple[str, ...]] = {
    "torch": ("torch",),
    "stable-baselines3, sb3-contrib": ("stable-baselines3", "sb3-contrib"),
    "torch-geometric": ("torch-geometric",),
    "gymnasium": ("gymnasium",),
    "highway-env": ("highway-env",),
    "optuna": ("optuna",),
    "numba": ("numba",),
    "numpy": ("numpy",),
    "fastapi, uvicorn (the `serve` extra)": ("fastapi", "uvicorn"),
    "msgspec, websockets (the `serve` extra)": ("msgspec", "websockets"),
    "sphinx, myst-parser, furo (the `docs` extra)": ("sphinx", "myst-parser", "furo"),
}


def version(name: str) -> str:
    """The installed version of one distribution, ``-`` when it is absent."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "-"


def table() -> str:
    """The Markdown table: Python first, then every row of :data:`ROWS`."""
    lines = ["| package | version |", "|---|---|", f"| Python | {platform.python_version()} |"]
    for label, names in ROWS.items():
        versions = [version(name) for name in names]
        shown = versions[0] if len(set(versions)) == 1 else ", ".join(versions)
        lines.append(f"| {label} | {shown} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
