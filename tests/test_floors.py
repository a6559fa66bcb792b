"""``envs/`` flows one way (DESIGN.md, "Module map"): an import runs down the floors, never up, and what a
lower floor needs from a higher one it asks of :mod:`envs.simulation.hooks`."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from envs.simulation import hooks

ROOT = Path(__file__).resolve().parents[1]
# Rooms of envs/ and their floors: simulation at the bottom, commands on top.
FLOORS = {"simulation": 1, "planners": 2, "ind": 2, "evaluation": 3, "serve": 4, "commands": 5}


def _imported_modules(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every import in a file, function-local ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


def _upward_imports() -> list[str]:
    upward = []
    for room, floor in FLOORS.items():
        for path in sorted((ROOT / "envs" / room).rglob("*.py")):
            for line, module in _imported_modules(path):
                parts = module.split(".")
                if parts[0] == "envs" and len(parts) > 1 and FLOORS.get(parts[1], 0) > floor:
                    upward.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    return upward


def test_no_import_runs_up_a_floor():
    assert _upward_imports() == []


def test_the_check_sees_an_upward_import(tmp_path, monkeypatch):
    room = tmp_path / "envs" / "simulation"
    room.mkdir(parents=True)
    (room / "bad.py").write_text("def f():\n    from envs.planners.shield import Shield\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _upward_imports() == ["envs/simulation/bad.py:2 imports envs.planners.shield"]


def test_the_environment_module_loads_no_planner():
    code = "import sys, envs.simulation.env; print(sorted(m for m in sys.modules if m.startswith('envs.planners')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]"


def test_a_bare_environment_finds_the_planners_it_trains_with():
    # A fresh process: envs/__init__.py names envs.planners as the provider, imported on the first request.
    code = (
        "import envs.simulation.env as e, sys\n"
        "env = e.CoopIntersection4WayEnv(config={'shield': True, 'residual_base': 'fifo'})\n"
        "env.reset(seed=0)\n"
        "print(type(env.unwrapped._shield).__name__, type(env.unwrapped._base).__name__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.split() == ["Shield", "FIFOPlanner"]


def test_hooks_refuse_an_unknown_name():
    with pytest.raises(ValueError, match="hook 'shild' is not one of shield, residual_base, priority"):
        hooks.register("shild", object)


def test_a_hook_without_provider_names_what_to_import(monkeypatch):
    monkeypatch.setattr(hooks, "_MAKERS", {})
    monkeypatch.setattr(hooks, "_PROVIDERS", [])
    with pytest.raises(LookupError, match="nothing registered for 'priority': import envs.planners"):
        hooks.maker("priority")


def test_providers_fill_the_registry_on_the_first_request(tmp_path, monkeypatch):
    (tmp_path / "floors_provider.py").write_text(
        "from envs.simulation import hooks\n\n"
        "def scheduler():\n    return 'made'\n\n"
        "hooks.register('priority', scheduler)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(hooks, "_MAKERS", {})
    monkeypatch.setattr(hooks, "_PROVIDERS", [])
    hooks.add_provider("floors_provider")
    hooks.add_provider("floors_provider")  # named twice, imported once
    assert "floors_provider" not in sys.modules
    assert hooks.maker("priority")() == "made"
    assert hooks._PROVIDERS == ["floors_provider"]
    monkeypatch.delitem(sys.modules, "floors_provider")


def test_the_planners_register_what_the_environment_asks_for():
    import envs.planners
    from envs.planners.shield import training_shield
    from envs.serve.client import make_remote_planner

    assert hooks.maker("shield") is training_shield
    assert hooks.maker("residual_base") is envs.planners.make_residual_base
    assert hooks.maker("priority") is envs.planners.glide.glide_scheduler
    assert hooks.maker("remote_planner") is make_remote_planner
