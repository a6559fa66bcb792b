"""The strong baselines on hand-built scenes in the real simulation: PR's stop point, AIM's
reservations, the actuated signal, and no collisions on busy scenarios for every baseline."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.planners import PriorityRulesPlanner

EMPTY = {"spawn_probability": 0.0, "initial_spawn_probability": 0.0}


def empty_env(layout_id: str = "CoopIntersection4Way-v0"):
    env = gym.make(layout_id, config=dict(EMPTY))
    env.reset(seed=0)
    return env


def drive(env, planner, steps: int, record=None) -> None:
    """Run ``planner`` for ``steps`` policy steps; ``record(scene)`` sees every scene before a step."""
    base = env.unwrapped
    for _ in range(steps):
        scene = base.scene()
        if record is not None:
            record(scene)
        env.step(base.accelerations_to_action(planner.act(scene)))


def test_pr_leader_stops_at_its_stop_line():
    """A yielding leader comes to rest within 1 m of its stop line (not the jam distance before it),
    its follower the jam distance behind it, and both stay at rest."""
    env = empty_env()
    base = env.unwrapped
    base.place_vehicles(["south->north", "south->west", "west->east"], arc=[30.0, 5.0, 20.0], speed=[10.0, 10.0, 8.0])
    planner = PriorityRulesPlanner()
    planner.blocked = lambda scene: np.ones(scene.num_vehicles, bool)  # everyone yields, forever
    drive(env, planner, 150)
    scene = base.scene()
    leaders = scene.leader < 0
    assert np.all(scene.speed < 0.05)
    assert np.all((scene.dist_to_entry[leaders] >= 0.0) & (scene.dist_to_entry[leaders] <= 1.0))
    follower = np.flatnonzero(~leaders)
    assert scene.gap[follower] == pytest.approx(planner.idm.jam_distance, abs=0.5)
