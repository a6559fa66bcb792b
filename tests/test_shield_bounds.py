"""The shield's declared bounds: the value, the ``--shield-bounds`` word, the faults beyond them, the warning at the
start of a run and the vehicle-steps beyond them that a run counts."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401
from envs.commands.evaluate import checked_shield_bounds, warn_beyond_bounds
from envs.evaluation.harness import run_episode
from envs.planners import DECLARED_BOUNDS, ShieldBounds, make_planner, parse_shield_bounds
from envs.planners.shield_bounds import EXCURSION_COLUMNS, exceeded, excursions
from envs.simulation.traffic import demand_scenario
from sb3_graph.commands import UserError

# The faults at the declared bounds (the issue's), and twice them.
AT_BOUNDS = {
    "position_sigma": 1.0,
    "position_bound": 3.0,
    "speed_sigma": 0.3,
    "speed_bound": 1.0,
    "loss": 0.05,
    "max_age": 1.0,
    "latency": 0.1,
    "lag": 0.3,
}
TWICE = {key: 2 * value for key, value in AT_BOUNDS.items()}


def test_the_words_none_declared_and_keys():
    assert parse_shield_bounds("none") == ShieldBounds() and ShieldBounds().exact
    assert parse_shield_bounds(None) == ShieldBounds()
    assert parse_shield_bounds("declared") == DECLARED_BOUNDS == ShieldBounds(3.0, 1.0, 1.0, 0.1, 0.3)
    assert parse_shield_bounds("declared,lag=0.5") == ShieldBounds(3.0, 1.0, 1.0, 0.1, 0.5)
    assert parse_shield_bounds("position=2, age=0.4") == ShieldBounds(position=2.0, age=0.4)
    assert parse_shield_bounds(DECLARED_BOUNDS.text()) == DECLARED_BOUNDS  # the report's text reads back


@pytest.mark.parametrize(
    "word, names",
    [
        ("position=-1", ["'position'", "[0, 1000]", "[m]"]),
        ("lag=nan", ["'lag'", "[0, 3600]"]),
        ("speed=fast", ["'speed'", "m/s"]),
        ("jitter=1", ["'jitter'", "position", "lag"]),
        ("position", ["KEY=VALUE"]),
        ("", ["empty"]),
    ],
)
def test_a_bad_word_is_one_line_naming_the_key_and_its_range(word, names):
    with pytest.raises(UserError) as error:
        checked_shield_bounds(word)
    text = str(error.value)
    assert "\n" not in text and text.startswith("--shield-bounds")
    assert all(name in text for name in names), text


def test_which_faults_exceed_the_bounds():
    assert exceeded(DECLARED_BOUNDS, AT_BOUNDS) == []
    assert exceeded(ShieldBounds(), None) == [] and exceeded(ShieldBounds(), {}) == []
    beyond = exceeded(DECLARED_BOUNDS, TWICE)
    assert [line.split()[0] for line in beyond] == ["position", "speed", "state", "latency", "lag"]
    assert "up to 6 m > 3 m" in beyond[0] and "up to 2 s > 1 s" in beyond[2]
    # an unbounded error exceeds any bound; the age of a held state counts only when messages are lost
    assert exceeded(ShieldBounds(position=50.0), {"position_sigma": 0.1}) == ["position error unbounded > 50 m"]
    assert exceeded(ShieldBounds(age=0.1, latency=0.1), {"latency": 0.1, "max_age": 5.0}) == []
    assert exceeded(ShieldBounds(age=0.1, latency=0.1), {"latency": 0.1, "loss": 0.01}) == [
        "state age up to 1 s > 0.1 s"
    ]


def test_the_warning_at_the_start_of_a_run(capsys):
    shielded = [("glide+shield", "Glide+shield")]
    assert warn_beyond_bounds(shielded, DECLARED_BOUNDS, {"faults": AT_BOUNDS}) is None
    assert warn_beyond_bounds([("glide", "Glide")], ShieldBounds(), {"faults": TWICE}) is None  # no shield
    line = warn_beyond_bounds(shielded, ShieldBounds(), {"faults": {"lag": 0.3}})
    err = capsys.readouterr().err
    assert line is not None and err == line + "\n" and "\n" not in line
    assert "--shield-bounds none" in line and "lag up to 0.3 s > 0 s" in line


def test_the_plus_shield_word_carries_the_bounds():
    shield = make_planner("glide+shield", shield_bounds=DECLARED_BOUNDS)
    assert shield.bounds == DECLARED_BOUNDS
    assert make_planner("fullthrottle+shield").bounds == ShieldBounds()


def test_excursions_of_one_scene():
    errors = (np.array([0.5, -3.5, 0.0, 0.0]), np.array([0.0, 0.0, 1.2, 0.0]), np.array([0.1, 0.1, 0.1, 1.2]))
    assert excursions(errors, DECLARED_BOUNDS).tolist() == [3, 1, 1, 1]
    assert excursions(errors, None).tolist() == [4, 2, 1, 4]  # the exact world: any error, any age
    assert excursions(None, None).tolist() == [0, 0, 0, 0]
    at_the_bound = (np.array([3.0, -3.0]), np.array([1.0, -1.0]), np.array([1.0, 0.0]))
    assert excursions(at_the_bound, DECLARED_BOUNDS).tolist() == [0, 0, 0, 0]


def _run(faults: dict, bounds: ShieldBounds | None) -> dict:
    scenario = demand_scenario("4way", 12.0, 3, 0.4)
    env = gym.make("CoopIntersection4Way-v0", config={"collision_handling": "remove", "faults": faults})
    _, facts = run_episode(env, make_planner("fullthrottle"), scenario, 12.0, seed=3, bounds=bounds)
    return facts


def test_a_run_counts_the_vehicle_steps_beyond_the_bounds():
    within = _run(AT_BOUNDS, DECLARED_BOUNDS)
    assert within["fault_excursions"] == 0  # the faults at the bounds stay within them
    beyond = _run(TWICE, DECLARED_BOUNDS)
    assert beyond["excursions_position"] > 0 and beyond["excursions_speed"] > 0
    assert beyond["fault_excursions"] >= max(beyond[k] for k in EXCURSION_COLUMNS[1:])
    exact = _run(AT_BOUNDS, None)  # declared nothing: every erroneous measurement is beyond
    assert exact["fault_excursions"] > beyond["fault_excursions"]
    assert "fault_excursions" not in _run({}, DECLARED_BOUNDS)  # no fault model: nothing to count
    assert math.isclose(within["return"], _run(AT_BOUNDS, ShieldBounds(position=1.0))["return"])  # counting only


def test_the_report_sums_the_excursions_per_planner():
    import pandas as pd

    from envs.evaluation.report import _excursion_table, add_fault_excursions

    runs = pd.DataFrame({
        "planner": ["A", "A", "B"], "fault_excursions": [3, 4, 0], "excursions_position": [3, 1, 0],
        "excursions_speed": [0, 3, 0], "excursions_age": [0, 1, 0],
    })  # fmt: skip
    summary = {"A": {"vehicles": 10, "collided": 2}, "B": {"vehicles": 8, "collided": 0}, "C": {"vehicles": 5}}
    add_fault_excursions(summary, runs)
    assert summary["A"]["fault_excursions"] == 7 and summary["A"]["excursions_age"] == 1
    assert summary["B"]["fault_excursions"] == 0 and "fault_excursions" not in summary["C"]
    table = _excursion_table(summary)
    assert "| A | 7 | 4 | 3 | 1 | 2 / 10 (20 %) |" in table and len(table) == 7  # title, header, rule, A, B
    assert _excursion_table({"A": {"vehicles": 1}}) == []  # no fault model, no table
