"""The gym environments: checkers, seeding, scenario replay, actions, info, rendering."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import envs
from envs.simulation.graph import build_observation
from envs.simulation.traffic import Scenario, generate_scenario

torch.set_num_threads(1)

INFO_KEYS = {"reward_terms", "reward_weighted", "entered", "crossed", "removed", "stopped", "collisions",
             "vehicles", "time", "num_vehicles", "waiting", "collided"}  # fmt: skip


@pytest.mark.parametrize("env_id", list(envs.ENV_IDS))
def test_gymnasium_and_sb3_checkers(env_id):
    env = gym.make(env_id, config={"max_vehicles": 16, "max_edges": 64})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gym_check_env(env.unwrapped)
        sb3_check_env(env.unwrapped, warn=False)


def _rule(obs: dict, n_slots: int) -> np.ndarray:
    # A deterministic planner of the observation: brake when close, otherwise track 80 % of the limit.
    x = obs["x"]
    action = np.clip(2.0 * (0.8 - x[:, 1]) - 3.0 * x[:, 2], -1, 1).astype(np.float32)
    return action[:n_slots]


def _rollout(env, steps, reset_kwargs):
    obs, info = env.reset(**reset_kwargs)
    trace = [env.unwrapped.scene()]
    infos = [info]
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(_rule(obs, env.action_space.shape[0]))
        trace.append(env.unwrapped.scene())
        infos.append(info)
        if terminated or truncated:
            break
    return trace, infos


def _same(a, b):
    assert len(a) == len(b)
    for sa, sb in zip(a, b):
        assert np.array_equal(sa.vehicle_id, sb.vehicle_id)
        assert np.array_equal(sa.position, sb.position) and np.array_equal(sa.speed, sb.speed)


def test_reset_seed_is_reproducible():
    env = gym.make("CoopIntersection4Way-v0", config={"spawn_probability": 0.3})
    a, _ = _rollout(env, 60, {"seed": 11})
    b, _ = _rollout(env, 60, {"seed": 11})
    c, _ = _rollout(env, 60, {"seed": 12})
    _same(a, b)
    assert not all(np.array_equal(x.vehicle_id, y.vehicle_id) for x, y in zip(a, c))


@pytest.mark.parametrize("env_id", ["CoopIntersection4Way-v0", "CoopIntersectionInD-v0"])
def test_scenario_file_replays_the_same_trajectories(tmp_path, env_id):
    config = {"collision_handling": "remove"}  # a collision of the simple rule must not end the replay early
    env = gym.make(env_id, config=config)
    scenario = generate_scenario(env.unwrapped.config["layout"], 20.0, 4, rate_range=(0.4, 0.4))
    path = scenario.save(tmp_path / "scenario.json")
    a, infos = _rollout(env, 500, {"options": {"scenario": scenario}})
    env.reset(seed=999)  # training traffic in between must not matter
    b, _ = _rollout(gym.make(env_id, config=config), 500, {"seed": 3, "options": {"scenario": str(path)}})
    _same(a, b)
    assert infos[-1]["time"] == pytest.approx(20.0)  # truncated at the scenario's duration
    entered = np.concatenate([i["entered"] for i in infos])
    assert set(entered.tolist()) <= set(scenario.vehicle_id.tolist()) and entered.size > 5
    for i in infos:
        for vid, meta in i["vehicles"].items():
            k = int(np.flatnonzero(scenario.vehicle_id == vid)[0])
            assert meta["route"] == scenario.route[k] and meta["time"] >= scenario.time[k] - 0.2


def test_scenario_for_another_layout_is_an_error():
    env = gym.make("CoopIntersection3Way-v0")
    with pytest.raises(ValueError, match="layout"):
        env.reset(options={"scenario": generate_scenario("4way", 10.0, 0)})
    with pytest.raises(ValueError, match="unknown keys"):
        env.reset(options={"scenery": None})


def test_step_info_and_observation_contract():
    # The two directions of the major road do not conflict: no collision, vehicles come and go.
    scenario = Scenario(
        layout="3way", duration=30.0, seed=None, vehicle_id=range(12), time=[i * 1.5 for i in range(12)],
        route=("west->east", "east->west") * 6, speed=[8.0] * 12, length=[5.0] * 12, width=[2.0] * 12,
    )  # fmt: skip
    env = gym.make("CoopIntersection3Way-v0")
    obs, info = env.reset(options={"scenario": scenario})
    assert INFO_KEYS <= set(info)
    seen_entered, seen_removed, seen_crossed = set(info["entered"].tolist()), set(), set()
    for _ in range(150):
        scene = env.unwrapped.scene()
        action = env.unwrapped.accelerations_to_action(np.full(scene.num_vehicles, 1.0))
        obs, reward, terminated, truncated, info = env.step(action)
        assert INFO_KEYS <= set(info)
        assert reward == pytest.approx(sum(info["reward_weighted"].values()))
        scene = env.unwrapped.scene()
        expected = build_observation(scene, env.observation_space)
        assert all(np.array_equal(obs[k], expected[k]) for k in obs)
        assert int(obs["node_mask"].sum()) == scene.num_vehicles == info["num_vehicles"]
        assert set(info["vehicles"]) == set(info["entered"].tolist())
        seen_entered |= set(info["entered"].tolist())
        seen_removed |= set(info["removed"].tolist())
        seen_crossed |= set(info["crossed"].tolist())
        if terminated or truncated:
            break
    assert seen_removed and seen_removed <= seen_crossed <= seen_entered


def test_padded_action_slots_are_ignored():
    env = gym.make("CoopIntersection4Way-v0")
    env.reset(seed=4)
    n = env.unwrapped.scene().num_vehicles
    a = np.zeros(env.action_space.shape, np.float32)
    b = a.copy()
    b[n:] = 1.0
    env.step(a)
    s1 = env.unwrapped.scene()
    env.reset(seed=4)
    env.step(b)
    s2 = env.unwrapped.scene()
    assert np.array_equal(s1.position, s2.position)
    with pytest.raises(ValueError, match="accelerations"):
        env.unwrapped.accelerations_to_action(np.zeros(n + 1))
    act = env.unwrapped.accelerations_to_action(np.full(s2.num_vehicles, 10.0))
    assert (
        act.dtype == np.float32
        and (act[: s2.num_vehicles] == 1.0).all()
        and (act[s2.num_vehicles :] == 0).all()
    )


def test_capacity_is_never_exceeded():
    env = gym.make("CoopIntersectionInD-v0", config={"max_vehicles": 3, "spawn_probability": 1.0})
    env.reset(seed=0)
    for _ in range(40):
        _, _, terminated, truncated, info = env.step(np.zeros(3, np.float32))
        assert info["num_vehicles"] <= 3
        if terminated or truncated:
            env.reset()


def test_set_spawn_probability():
    env = gym.make("CoopIntersection4Way-v0", config={"initial_spawn_probability": 0.0})
    env.reset(seed=0)
    env.unwrapped.set_spawn_probability(0.0)
    for _ in range(20):
        _, _, _, _, info = env.step(np.zeros(64, np.float32))
        assert info["entered"].size == 0
    env.unwrapped.set_spawn_probability(1.0)
    _, _, _, _, info = env.step(np.zeros(64, np.float32))
    assert info["entered"].size == 4
    with pytest.raises(ValueError, match="spawn_probability"):
        env.unwrapped.set_spawn_probability(1.5)


def test_rgb_array_rendering():
    env = gym.make(
        "CoopIntersectionInD-v0", render_mode="rgb_array", config={"screen_width": 200, "screen_height": 160}
    )
    env.reset(seed=0)
    env.step(np.zeros(64, np.float32))
    image = env.render()
    assert image.shape == (160, 200, 3) and image.dtype == np.uint8 and image.std() > 0
    env.close()


def test_scenario_objects_and_paths_are_accepted(tmp_path):
    scenario = generate_scenario("4way", 5.0, 1)
    env = gym.make("CoopIntersection4Way-v0")
    with pytest.raises(ValueError, match="cannot read"):
        env.reset(options={"scenario": tmp_path / "nope.json"})
    with pytest.raises(ValueError, match="'scenario' must be"):
        env.reset(options={"scenario": 3})
    env.reset(options={"scenario": Scenario.from_dict(scenario.to_dict())})


def test_human_rendering_runs_headless(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = gym.make(
        "CoopIntersection3Way-v0", render_mode="human", config={"screen_width": 120, "screen_height": 100}
    )
    env.reset(seed=0)
    assert env.unwrapped.config["offscreen_rendering"] is False
    env.step(np.zeros(64, np.float32))
    assert (
        env.unwrapped.viewer is not None
        and len(env.unwrapped.road.vehicles) == env.unwrapped.scene().num_vehicles
    )
    env.close()


@pytest.mark.parametrize("handling", ["terminate", "remove"])
def test_collision_handling(handling):
    """A hand-built crash at the centre of the 4-way next to a bystander on the major road: under
    "terminate" the episode ends with the pair in place; under "remove" the pair is reported once,
    leaves the scene, and the episode goes on with the bystander."""
    config = {"spawn_probability": 0.0, "initial_spawn_probability": 0.0, "collision_handling": handling}
    env = gym.make("CoopIntersection4Way-v0", config=config)
    env.reset(seed=0)
    base = env.unwrapped
    lay = base.layout
    sn, we, ew = (lay.route_id(r) for r in ("south->north", "west->east", "east->west"))
    mid = (lay.entry_arc + lay.exit_arc) / 2
    base.place_vehicles([sn, we, ew], [mid[sn], mid[we], 20.0], [3.0, 3.0, 8.0], [4, 9, 7])
    _, reward, terminated, truncated, info = env.step(base.accelerations_to_action(np.zeros(3)))
    assert info["collisions"].tolist() == [[4, 9]] and info["collided"].tolist() == [4, 9]
    assert info["reward_weighted"]["collision"] == -base.config["reward_weights"]["collision"] and reward < 0
    ids = base.scene().vehicle_id.tolist()
    if handling == "terminate":
        assert terminated and not truncated
        assert sorted(ids) == [4, 7, 9]
        return
    assert not terminated and not truncated
    assert ids == [7] and info["num_vehicles"] == 1
    assert sorted(info["removed"].tolist()) == [4, 9]
    for _ in range(20):  # the run goes on without reporting the pair again
        _, _, terminated, truncated, info = env.step(base.accelerations_to_action(np.zeros(1)))
        assert not terminated and info["collisions"].size == 0 and info["collided"].size == 0
    assert base.scene().vehicle_id.tolist() == [7] and base.sim.time == pytest.approx(21 * base.sim.dt)
