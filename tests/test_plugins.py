"""Domains plug in through entry points (sb3_graph/plugins.py); ``sb3_graph`` stands without them."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from checkout_entry_points import entry_point_tables, write_distribution

import sb3_graph.plugins as plugins
from sb3_graph.cli import COMMANDS, main

ROOT = Path(__file__).parents[1]
OWN = ("train", "tune", "tune-report", "export")
STUB_TABLES = {
    "sb3_graph.commands": {"stub": "stubdomain.plugin:COMMANDS"},
    "sb3_graph.tuning": {"stub": "stubdomain.plugin:TUNING"},
    "sb3_graph.gym_packages": {"stub": "stubdomain.registration"},
}


def _stub_domain(folder: Path, tables=None) -> Path:
    """A domain package ``stubdomain`` with one command, a tuning plug-in and a gym package, installed
    (as a ``.dist-info`` with its entry points) in ``folder``."""
    package = folder / "stubdomain"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "registration.py").write_text("REGISTERED = True  # a real domain registers its gym ids here\n")
    (package / "plugin.py").write_text(
        textwrap.dedent(
            """
            COMMANDS = {"hello": ("stubdomain.hello", "say hello (100 % stub)")}
            TUNING = {"StubEnv": ("stubdomain.plugin:evaluate", "none")}

            def evaluate(model, env_id, env_kwargs, episodes, seed):
                return {"flow": 1.0}
            """
        )
    )
    (package / "hello.py").write_text(
        textwrap.dedent(
            """
            from sb3_graph.commands import UserError

            def add_arguments(parser):
                parser.add_argument("--name", required=True)

            def run(args):
                if args.name == "bad":
                    raise UserError("--name: 'bad' is not a name (use letters)")
                print(f"hello {args.name}")
                return 0
            """
        )
    )
    return write_distribution(folder, "stubdomain", STUB_TABLES if tables is None else tables)


@pytest.fixture
def stub(tmp_path, monkeypatch):
    folder = _stub_domain(tmp_path / "site")
    monkeypatch.syspath_prepend(str(folder))
    monkeypatch.setattr(plugins, "SEARCH_PATH", [str(folder)])  # the stub domain only, no other installed
    for name in [m for m in sys.modules if m == "stubdomain" or m.startswith("stubdomain.")]:
        monkeypatch.delitem(sys.modules, name)
    return folder


def test_sb3_graph_names_no_domain_module():
    pattern = re.compile(r"""\benvs[./:][A-Za-z_]|["']envs["']|import envs\b|from envs\b""")
    hits = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in sorted((ROOT / "sb3_graph").rglob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not hits, hits


def test_a_stub_domain_adds_its_command_tuning_and_gym_package(stub, capsys):
    assert plugins.domain_commands() == {"hello": ("stubdomain.hello", "say hello (100 % stub)")}
    assert main(["hello", "--name", "ada"]) == 0
    assert capsys.readouterr().out == "hello ada\n"
    assert main(["hello", "--name", "bad"]) == 2  # the domain's UserError: one line, no traceback
    assert capsys.readouterr().err == "sb3-graph hello: error: --name: 'bad' is not a name (use letters)\n"
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in (*OWN, "hello")) and "evaluate" not in listed
    with pytest.raises(SystemExit) as stop:
        main(["evaluate"])  # the intersection domain is not installed here
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "unknown command 'evaluate'" in err and "pip install -e ." in err and err.count("\n") == 1

    from sb3_graph.commands.train import _import_packages
    from sb3_graph.commands.tune import _domain_default

    assert _domain_default("StubEnv-v0", 0) == "stubdomain.plugin:evaluate"
    assert _domain_default("StubEnv-v0", 1) == "none"
    assert _domain_default("GraphMaxNeighbour-v0", 0) == "sb3_graph.tuning.toy:evaluate_max_neighbour"
    assert plugins.gym_packages() == ["stubdomain.registration"]
    assert "stubdomain.registration" not in sys.modules
    _import_packages(None)  # train's default --gym-packages: the installed domains'
    assert sys.modules["stubdomain.registration"].REGISTERED


def test_a_package_command_keeps_its_name_and_a_broken_plugin_is_left_out(tmp_path, monkeypatch, capsys):
    tables = {"sb3_graph.commands": {"stub": "stubdomain.plugin:COMMANDS", "broken": "no_such_module:COMMANDS"}}
    folder = _stub_domain(tmp_path / "site", tables)
    (folder / "stubdomain" / "plugin.py").write_text('COMMANDS = {"export": ("stubdomain.hello", "x"), '
                                                     '"hello": ("stubdomain.hello", "say hello")}\n')  # fmt: skip
    monkeypatch.syspath_prepend(str(folder))
    monkeypatch.setattr(plugins, "SEARCH_PATH", [str(folder)])
    from sb3_graph.cli import all_commands

    table = all_commands()
    assert table["export"] == COMMANDS["export"] and table["hello"][0] == "stubdomain.hello"
    err = capsys.readouterr().err
    assert "plugin 'broken'" in err and "no_such_module" in err and err.count("\n") == 1


def test_sb3_graph_imports_and_lists_its_commands_without_the_domain(tmp_path):
    folder = _stub_domain(tmp_path / "site")
    code = textwrap.dedent(
        f"""
        import sys
        sys.modules["envs"] = None  # the intersection domain is not installed: importing it fails
        sys.path.insert(0, {str(folder)!r})
        import sb3_graph.plugins as plugins
        plugins.SEARCH_PATH = [{str(folder)!r}]
        import sb3_graph, sb3_graph.registry, sb3_graph.files.policy_files, sb3_graph.commands.tune
        import sb3_graph.commands.train, sb3_graph.commands.export
        from sb3_graph.cli import main
        try:
            main(["--help"])
        finally:
            loaded = [m for m in sys.modules if m == "envs" or m.startswith("envs.")]
            print("DOMAIN MODULES", [m for m in loaded if sys.modules[m] is not None])
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "DOMAIN MODULES []" in result.stdout
    listed = result.stdout
    assert all(name in listed for name in (*OWN, "hello"))
    assert not any(name in listed for name in ("evaluate", "sweep", "aggregate", "ind", "record", "serve"))


def test_the_repository_declares_the_intersection_domain(capsys):
    tables = entry_point_tables(ROOT / "pyproject.toml")
    assert tables == {
        "sb3_graph.commands": {"intersection": "envs.domain:COMMANDS"},
        "sb3_graph.tuning": {"intersection": "envs.domain:TUNING"},
        "sb3_graph.gym_packages": {"intersection": "envs"},
        "sb3_graph.experts": {"intersection": "envs.domain:EXPERTS"},
        "sb3_graph.planner_configs": {"intersection": "envs.domain:PLANNER_CONFIGS"},
    }
    from envs.domain import COMMANDS as DOMAIN

    assert set(DOMAIN) == {"evaluate", "sweep", "aggregate", "ind", "record", "serve", "reward-check"}
    assert not set(DOMAIN) & set(COMMANDS)
    assert plugins.gym_packages()[0] == "envs"  # tests see the checkout's entry points (conftest)
    with pytest.raises(SystemExit) as stop:
        main(["--help"])  # 95 % in a help text: argparse formats it
    assert stop.value.code == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in (*OWN, *DOMAIN))
