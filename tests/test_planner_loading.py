"""User planners on the command line (``file.py:Class``, ``package.module:Class``), ``--shield``,
and the one-line errors for a missing file, a missing class and a class that is not a Planner."""

from __future__ import annotations

import json

import pytest

from envs.planners import check_planner_spec, make_planner, planner_name
from sb3_graph.cli import main

SMALL = ["--scenarios", "1", "--duration", "6", "--seed", "1", "--jobs", "1", "--no-progress"]

USER_PLANNER = """
import numpy as np
from envs.planners import Planner


class Creep(Planner):
    def __init__(self):
        super().__init__("Creep")

    def act(self, scene):
        return np.full(scene.num_vehicles, 0.5)


class NotAPlanner:
    pass
"""


@pytest.fixture
def user_file(tmp_path):
    path = tmp_path / "my_planner.py"
    path.write_text(USER_PLANNER)
    return path


def test_file_and_module_specs_build_planners(user_file):
    spec = f"{user_file}:Creep"
    assert check_planner_spec(spec) == spec
    planner = make_planner(spec)
    assert planner.name == "Creep" and planner_name(spec) == "Creep"
    assert make_planner("envs.planners.adversarial:RandomAccel").name == "RandomAccel"


def test_user_planner_runs_with_and_without_the_shield(tmp_path, user_file):
    out = tmp_path / "report"
    args = ["evaluate", "--planner", f"{user_file}:Creep", "--planner", "envs.planners.adversarial:FullThrottle"]
    assert main([*args, "--shield", "--out", str(out), *SMALL]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary) == ["Creep+shield", "FullThrottle+shield"]
    for entry in summary.values():
        assert 0.0 <= entry["shield_interventions"] <= 1.0
    assert summary["FullThrottle+shield"]["collision_rate"] == 0.0
    assert "Safety shield" in (out / "report.md").read_text()


@pytest.mark.parametrize(
    "spec, words",
    [
        ("{dir}/missing.py:Creep", ["missing.py", "does not exist"]),
        ("{file}:Nope", ["Nope", "no class"]),
        ("{file}:NotAPlanner", ["NotAPlanner", "not a subclass of envs.planners.Planner"]),
        ("envs.planners.nope:Creep", ["envs.planners.nope", "cannot be imported"]),
    ],
    ids=["missing-file", "missing-class", "not-a-planner", "missing-module"],
)
def test_bad_class_specs_are_one_line_errors(tmp_path, user_file, capsys, spec, words):
    spec = spec.format(dir=tmp_path, file=user_file)
    out = tmp_path / "r"
    assert main(["evaluate", "--planner", spec, "--out", str(out), *SMALL]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--planner" in err and "Traceback" not in err
    for word in words:
        assert word in err
    assert not out.exists()
