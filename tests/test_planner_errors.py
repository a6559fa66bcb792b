"""Invalid planner outputs are planner errors: never clipped silently, never a numpy traceback."""

import json

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

import envs  # noqa: F401
from envs.evaluation.harness import evaluate, evaluation_env_kwargs, generate_scenarios, run_episode
from envs.planners.base import Planner
from envs.planners.errors import PlannerError, checked_accelerations
from envs.planners.shield import Shield
from envs.simulation.traffic import Scenario
from sb3_graph.cli import main

ENV = "CoopIntersection4Way-v0"

BAD_OUTPUTS = {
    "nan": lambda n: np.full(n, np.nan),
    "inf": lambda n: np.full(n, np.inf),
    "-inf": lambda n: np.full(n, -np.inf),
    "1e9": lambda n: np.full(n, 1e9),
    "-1e9": lambda n: np.full(n, -1e9),
    "strings": lambda n: ["1.0"] * n,
    "column": lambda n: np.zeros((n, 1)),
    "too short": lambda n: np.zeros(max(n - 1, 0)),
    "too long": lambda n: np.zeros(n + 1),
    "bool": lambda n: np.ones(n, bool),
    "none": lambda n: None,
}


class Bad(Planner):
    """Answers one of :data:`BAD_OUTPUTS` from its second scene with vehicles on, full throttle before."""

    def __init__(self, kind: str) -> None:
        super().__init__(f"Bad[{kind}]")
        self.kind = kind
        self.calls = 0

    def act(self, scene):
        self.calls += scene.num_vehicles > 0
        if self.calls < 2:
            return np.full(scene.num_vehicles, scene.a_max)
        return BAD_OUTPUTS[self.kind](scene.num_vehicles)


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scenarios")
    return generate_scenarios(folder, 1, 30.0, 3, "4way")[0]


@pytest.fixture(scope="module")
def env():
    return gym.make(ENV, **evaluation_env_kwargs(None))


def _scene(env, scenario):
    env.reset(seed=0, options={"scenario": Scenario.load(scenario)})
    for _ in range(200):
        scene = env.unwrapped.scene()
        if scene.num_vehicles >= 2:
            return scene
        env.step(env.unwrapped.accelerations_to_action(np.zeros(scene.num_vehicles)))
    raise AssertionError("no vehicles")


@pytest.mark.parametrize("kind", sorted(BAD_OUTPUTS))
def test_each_invalid_output_is_a_planner_error_naming_planner_step_and_value(env, scenario, kind):
    scene = _scene(env, scenario)
    with pytest.raises(PlannerError) as caught:
        checked_accelerations(BAD_OUTPUTS[kind](scene.num_vehicles), scene, "Hostile")
    line = caught.value.line("scenario_000.json")
    assert line.startswith("planner error: Hostile, scenario scenario_000.json, step ") and "\n" not in line
    if kind in ("nan", "inf", "-inf", "1e9", "-1e9"):
        assert repr(float(BAD_OUTPUTS[kind](1)[0])) in line and "vehicle" in line
    else:
        assert "expected a float array of shape" in line


def test_valid_outputs_pass_and_values_within_the_tolerance_are_clipped(env, scenario):
    scene = _scene(env, scenario)
    n = scene.num_vehicles
    for output in (np.zeros(n, np.float32), np.ones(n, np.int64), [0.5] * n, np.full(n, scene.a_max + 5e-5)):
        acc = checked_accelerations(output, scene, "Honest")
        assert acc.dtype == np.float64 and acc.shape == (n,) and (acc <= scene.a_max).all()


@pytest.mark.parametrize("kind", ["nan", "1e9", "strings", "column", "too short"])
def test_without_the_shield_the_run_fails_with_one_line(env, scenario, kind):
    with pytest.raises(PlannerError, match=rf"^planner error: Bad\[{kind}\], step \d+"):
        run_episode(env, Bad(kind), Scenario.load(scenario), 30.0, seed=0)


@pytest.mark.parametrize("kind", ["nan", "inf", "-1e9", "strings", "column", "too long"])
def test_behind_the_shield_the_fallback_takes_over_and_every_such_step_counts(env, scenario, kind):
    planner = Bad(kind)
    shield = Shield(planner)
    vehicles, facts = run_episode(env, shield, Scenario.load(scenario), 30.0, seed=0)
    bad_steps = planner.calls - 1
    assert bad_steps > 10 and shield.planner_errors == bad_steps
    assert shield.interventions >= bad_steps
    assert shield.error_lines and shield.error_lines[0].startswith(f"planner error: Bad[{kind}]")
    assert int(vehicles["collided"].sum()) == 0


def test_evaluate_keeps_the_other_planners_and_marks_the_failed_runs(scenario):
    runs, vehicles = evaluate(
        [("pr", "PR"), ("envs.planners.hostile:NaNPlanner", "NaN"), ("envs.planners.hostile:NaNPlanner+shield", "S")],
        [scenario], ENV, 30.0, progress=False,
    )  # fmt: skip
    runs = runs.set_index("planner")
    assert bool(runs.loc["NaN", "failed"]) and not bool(runs.loc["PR", "failed"]) and not bool(runs.loc["S", "failed"])
    assert runs.loc["NaN", "planner_error"].startswith("planner error: NaN, scenario scenario_000.json, step ")
    assert runs.loc["S", "planner_errors"] > 0 and runs.loc["PR", "crossed"] > 0
    assert runs.loc["S", "crossed"] > 0 and runs.loc["S", "collided"] == 0  # one NaN a step: the rest drive
    assert set(vehicles["planner"]) == {"PR", "S"}


def test_the_command_writes_the_report_and_exits_non_zero(tmp_path, scenario, capsys):
    out = tmp_path / "report"
    code = main(
        ["evaluate", "--planner", "pr", "--planner", "envs.planners.hostile:NaNPlanner",
         "--planner", "envs.planners.hostile:NaNPlanner+shield", "--scenario-dir", str(scenario.parent),
         "--duration", "30", "--out", str(out), "--no-progress"]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert code == 1
    assert "planner error: NaNPlanner, scenario scenario_000.json, step" in text and "Traceback" not in text
    assert "planner errors" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["NaNPlanner"]["failed_runs"] == 1 and summary["NaNPlanner"]["runs"] == 0
    assert summary["PR"]["runs"] == 1 and summary["PR"]["flow_rate"]["median"] > 0
    shielded = summary["NaNPlanner+shield"]
    assert shielded["planner_errors"] > 0 and shielded["shield_unresolved"] == 0 and shielded["stuck_runs"] == 0
    assert len(pd.read_csv(out / "metrics.csv")) == 3
    assert "## Planner errors" in (out / "report.md").read_text()


def test_a_report_whose_every_run_failed_still_names_the_errors(tmp_path, scenario, capsys):
    out = tmp_path / "report"
    code = main(["evaluate", "--planner", "envs.planners.hostile:NaNPlanner", "--scenario-dir", str(scenario.parent),
                 "--duration", "10", "--out", str(out), "--no-progress"])  # fmt: skip
    assert code == 1 and "Traceback" not in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["NaNPlanner"]["failed_runs"] == 1
    assert "## Planner errors" in (out / "report.md").read_text()
