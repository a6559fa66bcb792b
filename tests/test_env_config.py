"""Configuration: defaults, merging, and clear errors for bad settings."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401
from envs.simulation.env import CoopIntersection3WayEnv, CoopIntersectionEnv


def test_defaults_and_merge():
    env = gym.make(
        "CoopIntersection3Way-v0", config={"max_vehicles": 10, "reward": "paper", "reward_weights": {"idle": 0.5}}
    )
    cfg = env.unwrapped.config
    assert cfg["layout"] == "3way" and cfg["max_vehicles"] == 10
    assert cfg["reward_weights"] == {
        "velocity": 0.03,
        "action": 0.01,
        "idle": 0.5,
        "proximity": 0.2,
        "collision": 1.0,
    }
    assert env.observation_space["x"].shape == (10, 3) and env.action_space.shape == (10,)
    assert CoopIntersection3WayEnv.default_config()["policy_frequency"] == 5
    assert cfg["collision_handling"] == "terminate"  # training: a collision ends the episode


def test_configure_takes_effect_at_reset():
    env = gym.make("CoopIntersection4Way-v0").unwrapped
    env.configure({"max_vehicles": 5, "layout": "inD"})
    obs, _ = env.reset(seed=0)
    assert obs["x"].shape == (5, 3) and env.layout.name == "inD"


@pytest.mark.parametrize(
    "config, key",
    [
        ({"spawn_probabilty": 0.1}, "spawn_probabilty"),  # unknown (typo)
        ({"spawn_probability": -0.1}, "spawn_probability"),  # negative rate
        ({"spawn_probability": "high"}, "spawn_probability"),  # wrong type
        ({"initial_speed_range": [1.0, 0.6]}, "initial_speed_range"),  # min >= max
        ({"initial_speed_range": [0.6, 0.6]}, "initial_speed_range"),
        ({"reward_weights": {"velocity": "big"}}, "reward_weights"),  # weight not a number
        ({"reward_weights": {"speed": 1.0}}, "reward_weights"),  # unknown term
        ({"edge_features": [[]]}, "edge_features"),  # unhashable entries are a wrong value, not a TypeError
        ({"reward": []}, "reward"),
        ({"reward": "fast"}, "reward"),
        ({"residual_base": ["aim"]}, "residual_base"),
        ({"residual_scale": 3.0}, "residual_scale"),
        ({"spawn_queue": -1}, "spawn_queue"),
        ({"shield": "yes"}, "shield"),
        ({"max_vehicles": 0}, "max_vehicles"),
        ({"max_vehicles": 2.5}, "max_vehicles"),
        ({"max_acceleration": True}, "max_acceleration"),
        ({"duration": float("nan")}, "duration"),
        ({"layout": "roundabout"}, "layout"),
        ({"policy_frequency": 4}, "simulation_frequency"),  # 15 is not a multiple of 4
        ({"collision_handling": "ignore"}, "collision_handling"),
        ({"collision_handling": None}, "collision_handling"),
        ({"s_scale": 1e300}, "s_scale"),  # observation scales: the float32 features would overflow
        ({"d_max": 1e300}, "d_max"),
        ({"s_ref": 1e300}, "s_ref"),
    ],
)
def test_bad_settings_raise_value_error_naming_the_key(config, key):
    with pytest.raises(ValueError, match=key):
        gym.make("CoopIntersection4Way-v0", config=config)
    env = CoopIntersectionEnv()
    with pytest.raises(ValueError, match=key):
        env.configure(config)
    assert env.config["max_vehicles"] == 64  # a rejected configure changes nothing


def test_error_lists_what_is_allowed():
    with pytest.raises(ValueError, match=r"a number in \[0, 1\]"):
        CoopIntersectionEnv(config={"spawn_probability": 2})
    with pytest.raises(ValueError, match="allowed keys"):
        CoopIntersectionEnv(config={"colour": "red"})


def test_spawn_probability_range_draws_per_episode():
    from envs.simulation.env import CoopIntersectionEnv

    env = CoopIntersectionEnv(config={"spawn_probability_range": [0.01, 0.06]})
    drawn = set()
    for seed in range(5):
        env.reset(seed=seed)
        assert 0.01 <= env.traffic.spawn_probability <= 0.06
        drawn.add(env.traffic.spawn_probability)
    assert len(drawn) == 5
    with pytest.raises(ValueError, match="spawn_probability_range"):
        CoopIntersectionEnv(config={"spawn_probability_range": [0.5, 1.5]})


@pytest.mark.parametrize("config", [[("max_vehicles", 8)], "max_vehicles=8", 0])
def test_a_config_that_is_not_a_dict_names_config(config):
    with pytest.raises(ValueError, match="config must be a dict"):
        CoopIntersectionEnv(config=config)
    with pytest.raises(ValueError, match="config must be a dict"):
        CoopIntersectionEnv().configure(config)


def test_numpy_booleans_are_booleans():
    env = CoopIntersectionEnv(config={"shield": np.bool_(True), "render_agent": np.bool_(False)})
    assert env.config["shield"] is True and env.config["render_agent"] is False  # stored as Python booleans


def test_an_unknown_render_mode_names_it_without_gymnasiums_warning():
    import warnings

    from envs.evaluation.harness import env_config

    with pytest.raises(ValueError, match=r"render_mode must be None or one of \['human', 'rgb_array'\], got 'video'"):
        CoopIntersectionEnv(render_mode="video")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(ValueError, match="render_mode"):
            env_config("CoopIntersection4Way-v0", {"render_mode": "video"})
    assert not caught, [str(w.message) for w in caught]


def test_observation_scales_at_their_bounds_give_finite_observations():
    from envs.simulation.config import MAX_D_MAX, MAX_S_REF, MAX_S_SCALE

    env = CoopIntersectionEnv(config={"s_scale": MAX_S_SCALE, "s_ref": MAX_S_REF, "d_max": MAX_D_MAX})
    obs, _ = env.reset(seed=0)
    for _ in range(10):
        obs, *_ = env.step(np.ones(env.action_space.shape, np.float32))
    assert all(np.isfinite(value).all() for value in obs.values())
