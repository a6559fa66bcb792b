"""How the project's modules import each other (DESIGN.md, "Rooms sit on floors"): no circle of imports, and few
function-local imports of the project's own modules outside the command modules.

A function-local import is how a command keeps its ``--help`` fast (the network code loads when it runs), so the
command modules (``*/commands/*`` and ``cli.py``) may hold them. Elsewhere one mostly dodges an upward import, a
sign that something lives in the wrong room: their number may not grow above :data:`LOCAL_IMPORTS_GOAL`.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sb3_graph", "envs")
#: the most function-local imports of the project's own modules that the modules outside the commands may hold
LOCAL_IMPORTS_GOAL = 40


def module_name(path: Path, root: Path = ROOT) -> str:
    """``sb3_graph/common/cloning.py`` -> ``sb3_graph.common.cloning``, ``envs/__init__.py`` -> ``envs``."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Every module of :data:`PACKAGES` under ``root``: dotted name -> file."""
    return {module_name(p, root): p for package in PACKAGES for p in sorted((root / package).rglob("*.py"))}


def own_imports(path: Path, known: dict[str, Path], root: Path = ROOT) -> list[tuple[int, str, bool]]:
    """The project's modules that one file imports: ``(line, module, inside a function)``; ``from a.b import c``
    counts as ``a.b.c`` where that is a module, else as ``a.b``.

    :param path: a module's file
    :param known: :func:`modules`
    """
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []

    def visit(node: ast.AST, local: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = local or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:  # relative: from the file's package up
                    up = package.split(".")[: len(package.split(".")) - (child.level - 1)]
                    base = ".".join([*up, base] if base else up)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in child.names]
            for target in dict.fromkeys(targets):
                if target.split(".")[0] in PACKAGES:
                    found.append((child.lineno, target, local))
            visit(child, inside)

    visit(ast.parse(path.read_text(encoding="utf-8")), False)
    return found


def is_command_module(path: Path, root: Path = ROOT) -> bool:
    parts = path.relative_to(root).parts
    return "commands" in parts[:-1] or path.name == "cli.py"


def local_imports(root: Path = ROOT) -> list[str]:
    """Every function-local import of the project's own modules outside the command modules, as ``file:line``."""
    known = modules(root)
    return [
        f"{path.relative_to(root)}:{line} {target}"
        for path in known.values()
        if not is_command_module(path, root)
        for line, target, local in own_imports(path, known, root)
        if local
    ]


def circles(root: Path = ROOT) -> list[list[str]]:
    """The circles of imports between modules (function-local imports included): each strongly connected group of
    more than one module, sorted. A package's ``__init__`` that re-exports its own modules is no circle with them."""
    known = modules(root)
    edges = {name: set() for name in known}
    for name, path in known.items():
        for _, target, _ in own_imports(path, known, root):
            while target not in known and "." in target:
                target = target.rpartition(".")[0]
            if target in known and target != name and not target.startswith(f"{name}."):
                edges[name].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def connect(node: str) -> None:  # Tarjan's strongly connected components
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in sorted(edges[node]):
            if other not in index:
                connect(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(edges):
        if node not in index:
            connect(node)
    return sorted(groups)


def test_no_circle_of_imports():
    assert circles() == []


def test_few_function_local_imports_outside_the_commands():
    found = local_imports()
    assert len(found) <= LOCAL_IMPORTS_GOAL, "\n".join(found)


def test_the_checks_see_a_circle_and_a_local_import(tmp_path):
    room = tmp_path / "sb3_graph"
    (room / "commands").mkdir(parents=True)
    (room / "__init__.py").write_text("")
    (room / "commands" / "__init__.py").write_text("")
    (room / "commands" / "train.py").write_text("def run():\n    from sb3_graph.tuning import pretrain\n")
    (room / "tuning").mkdir()
    (room / "tuning" / "__init__.py").write_text("")
    (room / "tuning" / "pretrain.py").write_text("def clone():\n    from sb3_graph.commands.train import run\n")
    assert circles(tmp_path) == [["sb3_graph.commands.train", "sb3_graph.tuning.pretrain"]]
    assert local_imports(tmp_path) == ["sb3_graph/tuning/pretrain.py:2 sb3_graph.commands.train"]
