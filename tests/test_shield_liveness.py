"""The shield keeps the intersection draining, and the watchdog sees a run that stands still."""

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

import envs  # noqa: F401
from envs.evaluation.harness import evaluation_env_kwargs, run_episode
from envs.evaluation.metrics import STANDSTILL_LIMIT, run_metrics, standstill
from envs.planners.hostile import BoxParker, LineHolder
from envs.planners.shield import Shield
from envs.simulation.traffic import generate_scenario

ENVS = {"4way": "CoopIntersection4Way-v0", "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}


def test_standstill_measures_the_longest_wait_without_a_crossing():
    vehicles = pd.DataFrame(
        {
            "first_seen": [0.0, 1.0, 5.0, 50.0],
            "scheduled": [0.0, 1.0, 5.0, 50.0],
            "crossed": [10.0, 12.0, np.nan, np.nan],
            "removed": [np.nan, np.nan, np.nan, 55.0],
        }
    )
    longest, last = standstill(vehicles, 100.0)
    assert last == 12.0
    assert longest == pytest.approx(100.0 - 12.0)  # vehicle 2 waits from 5 s on, nobody crosses after 12 s
    longest, _ = standstill(vehicles.drop(index=2), 100.0)
    assert longest == pytest.approx(10.0)  # the first 10 s: vehicle 0 waits; vehicle 3 left at 55 s
    assert standstill(vehicles.iloc[:0], 100.0)[0] == 0.0  # nobody waits: no standstill


def _box_run(layout: str, seed: int, monkeypatch=None):
    if monkeypatch is not None:  # the shield without its liveness rules
        monkeypatch.setattr(Shield, "_committed_and_braked", lambda self, s, p, acc, f: np.zeros(len(acc), bool))
        monkeypatch.setattr(Shield, "_parked_past_the_line", lambda self, s, p, acc: np.zeros(len(acc), bool))
    env = gym.make(ENVS[layout], **evaluation_env_kwargs(None))
    shield = Shield(BoxParker())
    vehicles, _ = run_episode(env, shield, generate_scenario(layout, 60.0, seed), 60.0, seed=seed)
    return run_metrics(vehicles, 60.0), shield


@pytest.mark.parametrize("layout, seed", [("4way", 8383), ("4way", 9494), ("3way", 8383), ("inD", 8383)])
def test_a_planner_that_brakes_every_vehicle_inside_the_box_cannot_stall_it(layout, seed):
    row, shield = _box_run(layout, seed)
    assert row["collided"] == 0 and shield.unresolved == 0
    assert not row["stuck"] and row["longest_standstill_s"] < 20.0
    assert row["crossed"] >= 15 and row["last_crossing_s"] > 55.0


def test_without_the_liveness_rules_the_same_planner_stalls_the_box(monkeypatch):
    row, _ = _box_run("4way", 8383, monkeypatch)
    assert row["stuck"] and row["crossed"] == 0  # what the rules prevent


def test_a_planner_that_holds_every_vehicle_before_the_line_is_seen_by_the_watchdog():
    # Where the guarantee stops: before the line, the planner decides (and the fallback would hold them too).
    env = gym.make(ENVS["4way"], **evaluation_env_kwargs(None))
    vehicles, _ = run_episode(env, Shield(LineHolder()), generate_scenario("4way", 60.0, 8383), 60.0, seed=8383)
    row = run_metrics(vehicles, 60.0)
    assert row["stuck"] and row["longest_standstill_s"] >= STANDSTILL_LIMIT and row["collided"] == 0
