"""Reward terms on hand-built cases, through the environment: the paper's ("Reward Engineering",
``reward: paper``) and the task preset's (``reward: task``, the default)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.simulation.rewards import (
    PAPER_REWARD_WEIGHTS,
    PAPER_TERMS,
    REWARD_TERMS,
    TASK_REWARD_WEIGHTS,
    reward_terms,
    velocity_reward,
)
from envs.simulation.scene import STOP_SPEED


def _empty_env(**config):
    cfg = {
        "spawn_probability": 0.0,
        "initial_spawn_probability": 0.0,
        "max_vehicles": 8,
        "max_speed": 30.0,
        "reward": "paper",
    }
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
    assert reward == pytest.approx(sum(PAPER_REWARD_WEIGHTS[k] * terms[k] for k in PAPER_TERMS))
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
    assert env.config["reward_weights"]["velocity"] == PAPER_REWARD_WEIGHTS["velocity"]
    env.place_vehicles([0], [20.0], [0.0])
    _, reward, _, _, info = env.step(env.accelerations_to_action(np.zeros(1)))
    assert info["reward_weighted"]["idle"] == -2.0
    assert reward == pytest.approx(-2.0)
    assert STOP_SPEED > 0


# ---------------------------------------------------------------- the task preset


def _task_env(**config):
    return _empty_env(reward="task", **config)


def test_the_task_preset_is_the_default_and_a_preset_switch_replaces_the_weights():
    env = gym.make("CoopIntersection4Way-v0").unwrapped
    assert env.config["reward"] == "task" and env.config["reward_weights"] == TASK_REWARD_WEIGHTS
    env.configure({"reward": "paper"})
    assert env.config["reward_weights"] == PAPER_REWARD_WEIGHTS
    env.configure({"reward": "task", "reward_weights": {"stop": 1.0}})
    assert env.config["reward_weights"] == {**TASK_REWARD_WEIGHTS, "stop": 1.0}
    with pytest.raises(ValueError, match="reward"):
        env.configure({"reward": "fast"})


def test_a_vehicle_that_clears_the_box_earns_throughput():
    env = _task_env()
    lay = env.layout
    r = lay.route_id("west->east")
    limit = lay.speed_limit[r, 0]
    # Centre 1 m before the exit at the lane limit: it crosses within the 0.2 s step.
    env.place_vehicles([r], [lay.exit_arc[r] - 1.0], [limit], [3])
    _, reward, _, _, info = env.step(env.accelerations_to_action(np.zeros(1)))
    terms = info["reward_terms"]
    assert info["crossed"].tolist() == [3]
    assert terms["throughput"] == 1.0 and terms["stop"] == 0.0
    assert terms["delay"] == pytest.approx(0.0, abs=1e-9)  # at the limit: no delay
    assert reward == pytest.approx(TASK_REWARD_WEIGHTS["throughput"])


def test_delay_charges_slow_vehicles_and_a_new_stop_costs_once():
    env = _task_env()
    r = env.layout.route_id("south->north")
    limit = float(env.layout.speed_limit[r, 0])
    env.place_vehicles([r, r], [10.0, 40.0], [0.0, 0.5 * limit], [0, 1])
    _, reward, _, _, info = env.step(env.accelerations_to_action(np.array([-5.0, 0.0])))
    terms = info["reward_terms"]
    speed = env.scene().speed
    expected = -0.2 * ((1 - speed[0] / limit) + (1 - speed[1] / limit))
    assert terms["delay"] == pytest.approx(expected)
    assert terms["stop"] == -1.0  # vehicle 0 stands: its first stop
    assert reward == pytest.approx(TASK_REWARD_WEIGHTS["delay"] * expected - TASK_REWARD_WEIGHTS["stop"])
    _, _, _, _, info = env.step(env.accelerations_to_action(np.array([-5.0, 0.0])))
    assert info["reward_terms"]["stop"] == 0.0  # still standing: no second charge


def test_a_waiting_vehicle_outside_the_scene_costs_delay():
    env = _task_env(spawn_queue=5)
    r = env.layout.route_id("west->east")
    # A vehicle standing on the spawn point blocks the lane; a training spawn there must queue.
    env.place_vehicles([r], [3.0], [0.0], [10_000])
    env.traffic.spawn_probability = 1.0
    _, _, _, _, info = env.step(env.accelerations_to_action(np.array([-5.0])))
    waiting = info["waiting"]
    assert waiting >= 1
    speed = env.scene().speed
    limits = env.scene().speed_limit
    in_scene = float(np.maximum(0.0, 1 - speed / limits).sum())
    assert info["reward_terms"]["delay"] == pytest.approx(-0.2 * (in_scene + waiting))
    # Without the queue a blocked spawn is dropped: nobody waits.
    env = _task_env(spawn_queue=0)
    env.place_vehicles([r], [3.0], [0.0], [10_000])
    env.traffic.spawn_probability = 1.0
    _, _, _, _, info = env.step(env.accelerations_to_action(np.array([-5.0])))
    assert info["waiting"] == 0


def test_every_preset_weighs_only_known_terms():
    for weights in (PAPER_REWARD_WEIGHTS, TASK_REWARD_WEIGHTS):
        assert set(weights) <= set(REWARD_TERMS) and all(w > 0 for w in weights.values())
