"""Reward terms (paper, "Reward Engineering") on hand-built cases, through the environment."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.rewards import DEFAULT_REWARD_WEIGHTS, REWARD_TERMS, reward_terms, velocity_reward
from envs.scene import STOP_SPEED


def _empty_env(**config):
    cfg = {"spawn_probability": 0.0, "initial_spawn_probability": 0.0, "max_vehicles": 8, "max_speed": 30.0}
    cfg.update(config)
    env = gym.make("CoopIntersection4Way-v0", config=cfg).unwrapped
    env.reset(seed=0)
    return env


def test_velocity_reward_is_the_papers_piecewise_function():
    r = np.array([0.0, 0.4, 0.8, 0.9, 1.0, 1.1, 1.2, 1.5])
    expected = [0.0, 0.5, 1.0, 1.0, 1.0, 0.5, 0.0, -1.5]
    np.testing.assert_allclose(velocity_reward(r), expected)


def test_all_standing_gives_the_idle_penalty():
    env = _empty_env()
    env.place_vehicles(["south->north", "west->east"], [20.0, 20.0], [0.0, 0.0], [0, 1])
    _, reward, terminated, _, info = env.step(env.accelerations_to_action(np.array([-5.0, -5.0])))
    terms = info["reward_terms"]
    assert terms["idle"] == -1.0 and terms["velocity"] == 0.0
    assert terms["action"] == pytest.approx(-1.0)
    assert not terminated
    assert reward == pytest.approx(sum(DEFAULT_REWARD_WEIGHTS[k] * terms[k] for k in REWARD_TERMS))
    assert reward == pytest.approx(-0.01 - 0.01)
    # One vehicle moving: no idle penalty.
    env.sim.speed[0] = 5.0
    _, _, _, _, info = env.step(env.accelerations_to_action(np.array([0.0, -5.0])))
    assert info["reward_terms"]["idle"] == 0.0


def test_no_idle_penalty_without_vehicles():
    env = _empty_env()
    _, reward, _, _, info = env.step(env.action_space.sample())
    assert info["reward_terms"] == dict.fromkeys(REWARD_TERMS, 0.0) and reward == 0.0


def test_collision_gives_the_penalty_and_ends_the_episode():
    env = _empty_env()
    lay = env.layout
    sn, we = lay.route_id("south->north"), lay.route_id("west->east")
    mid = (lay.entry_arc + lay.exit_arc) / 2
    env.place_vehicles([sn, we], [mid[sn], mid[we]], [3.0, 3.0], [4, 9])
    _, reward, terminated, truncated, info = env.step(env.accelerations_to_action(np.zeros(2)))
    assert terminated and not truncated
    assert info["reward_terms"]["collision"] == -1.0
    assert info["collisions"].tolist() == [[4, 9]] and info["collided"].tolist() == [4, 9]
    assert reward <= -1.0  # the collision weight is 1


def test_speed_above_the_limit_lowers_the_velocity_term():
    # The governor keeps vehicles of the environment at or below the limit; the term itself still
    # follows the paper above it.
    ratios = np.array([0.5, 0.9, 1.1, 1.3])
    values = [
        reward_terms(np.array([r * 8.0]), np.array([8.0]), np.zeros(1), 5.0, np.full(1, np.inf), False)["velocity"]
        for r in ratios
    ]
    np.testing.assert_allclose(values, [1.25 * 0.5, 1.0, 6.0 - 5.0 * 1.1, 6.0 - 5.0 * 1.3])


def test_velocity_term_in_the_environment():
    env = _empty_env()
    r = env.layout.route_id("south->north")
    limit = env.layout.speed_limit[r, 0]
    values = []
    for k, ratio in enumerate([0.5, 0.9, 1.3]):
        env.reset()
        env.place_vehicles([r], [10.0], [ratio * limit], [k])
        _, _, _, _, info = env.step(env.accelerations_to_action(np.zeros(1)))
        values.append(info["reward_terms"]["velocity"])
    # 1.3x the limit: the governor brings the vehicle down to the limit within the step.
    np.testing.assert_allclose(values, [1.25 * 0.5, 1.0, 1.0])


def test_proximity_penalty_from_the_mahalanobis_distance():
    env = _empty_env()
    r = env.layout.route_id("west->east")
    env.place_vehicles([r, r], [30.0, 36.0], [5.0, 5.0], [0, 1])  # 6 m apart in line: d = 6 / 2.5
    _, _, _, _, info = env.step(env.accelerations_to_action(np.zeros(2)))
    assert info["reward_terms"]["proximity"] == pytest.approx(-(1 - (6.0 / 2.5) / 3.0))
    far = reward_terms(np.ones(2), np.ones(2), np.zeros(2), 5.0, np.array([3.5, 9.0]), False)
    assert far["proximity"] == 0.0


def test_weights_come_from_the_config():
    env = _empty_env(reward_weights={"idle": 2.0})
    assert env.config["reward_weights"]["velocity"] == DEFAULT_REWARD_WEIGHTS["velocity"]
    env.place_vehicles([0], [20.0], [0.0])
    _, reward, _, _, info = env.step(env.accelerations_to_action(np.zeros(1)))
    assert info["reward_weighted"]["idle"] == -2.0
    assert reward == pytest.approx(-2.0)
    assert STOP_SPEED > 0
