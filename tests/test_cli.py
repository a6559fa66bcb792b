"""The ``sb3-graph`` command line: every command's ``--help`` works, ``--version`` answers."""

import subprocess
import sys
from pathlib import Path

import pytest

import sb3_graph
from sb3_graph.cli import all_commands, main

ROOT = Path(__file__).resolve().parents[1]
# The package's commands and the intersection domain's (its entry points: tests/conftest.py loads the checkout's).
COMMANDS = all_commands()


@pytest.mark.parametrize("command", [[]] + [[name] for name in COMMANDS], ids=["sb3-graph", *COMMANDS])
def test_help_of_every_command_exits_0(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: sb3-graph")
    if not command:  # the top-level help lists every command with its one-line help
        assert all(name in out for name in COMMANDS) and "95 % intervals" in out


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0 and capsys.readouterr().out.strip() == f"sb3-graph {sb3_graph.__version__}"


def test_console_help_exits_0_in_a_fresh_process():
    result = subprocess.run(
        [sys.executable, "-m", "sb3_graph.cli", "--help"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr


def test_import_sb3_graph_registers_the_toy_env():
    code = "import gymnasium as gym, sb3_graph; env = gym.make('GraphMaxNeighbour-v0'); env.reset(seed=0)"
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


def test_top_level_help_imports_no_command_module_nor_torch():
    # The fast start (benchmarks/bench_cli_start.py times it): listing the commands loads none of them.
    code = (
        "import sys\n"
        "from sb3_graph.cli import all_commands, main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "modules = {module for module, _ in all_commands().values()}\n"
        "print(sorted(m for m in modules | {'torch', 'stable_baselines3', 'torch_geometric', 'highway_env'} "
        "if m in sys.modules))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_package_names_load_on_first_use():
    code = (
        "import sys, sb3_graph\nassert 'torch' not in sys.modules\n"
        "print(sb3_graph.TD3.__module__, len(sb3_graph.POLICY_CLASSES))"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["sb3_graph.td3.td3", "5"]


# What a command's --help must not import: the network stack, highway-env, the evaluation harness, pandas.
HEAVY = ("torch", "stable_baselines3", "torch_geometric", "highway_env", "envs.evaluation.harness", "numba", "pandas")


def test_no_command_help_imports_the_heavy_modules():
    # Each command's parser in one fresh process per command: a module that imports torch, highway-env or the
    # harness at parser time makes that command's --help (and every argparse error of it) take seconds.
    code = (
        "import sys\nfrom sb3_graph.cli import main\ntry:\n    main([sys.argv[1], '--help'])\nexcept SystemExit:\n"
        f"    pass\nprint([m for m in {HEAVY!r} if m in sys.modules])\n"
    )
    for command in COMMANDS:
        result = subprocess.run(
            [sys.executable, "-c", code, command], cwd=ROOT, capture_output=True, text=True, timeout=120
        )
        assert result.returncode == 0, result.stderr
        assert result.stdout.strip().splitlines()[-1] == "[]", (command, result.stdout[-300:])


@pytest.mark.parametrize("command", ["export", "evaluate", "train"])
def test_an_unknown_flag_names_the_command_and_its_help(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--no-such-flag", "1"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sb3-graph {command}: error:") and f"(see sb3-graph {command} --help)" in err, err
    assert err.count("\n") == 1


@pytest.mark.parametrize(
    "word, hint",
    [
        ("glid", "did you mean 'glide'?"),
        ("aim+shiled", "did you mean 'aim+shield'?"),
        ("FullThrotle+shield", "did you mean 'fullthrottle+shield'?"),
        ("runs/missing/best_model.safetensors", "file not found"),
        ("missing.zip+shield", "file not found"),
    ],
)
def test_a_near_miss_planner_word_gets_a_suggestion(word, hint, tmp_path, capsys):
    assert main(["evaluate", "--planner", word, "--out", str(tmp_path / "r"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sb3-graph evaluate: error: --planner:") and hint in err and err.count("\n") == 1, err
    assert "Traceback" not in err and not (tmp_path / "r").exists()


def test_an_unknown_planner_word_gets_no_wrong_suggestion(tmp_path, capsys):
    assert main(["evaluate", "--planner", "banana", "--out", str(tmp_path / "r"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "is unknown" in err and "did you mean" not in err and "glide" in err  # the accepted words are listed
