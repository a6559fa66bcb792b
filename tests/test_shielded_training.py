"""Training behind the shield, residual policies and the warm-up of their actor (issue #22)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import run_episode
from envs.planners import AIMPlanner, make_planner
from envs.planners.adversarial import FullThrottle
from envs.planners.base import Planner
from envs.planners.gnn import check_planner_config
from envs.planners.residual import ResidualPlanner
from envs.planners.shield import Shield
from envs.simulation.traffic import generate_scenario
from sb3_graph import TD3
from sb3_graph.callbacks import ActorWarmupCallback

SMALL = {"max_vehicles": 12, "max_edges": 200, "duration": 20.0, "spawn_probability": 0.07}
TINY_NET = {"encoder_dim": 8, "conv_dims": (8,)}


class _Recorder(gym.Wrapper):
    """Keeps every action the agent proposed and the info the step returned."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.steps: list[tuple[np.ndarray, dict]] = []

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps.append((np.array(action, dtype=np.float32), info))
        return obs, reward, terminated, truncated, info


class _Zero(Planner):
    def __init__(self) -> None:
        super().__init__("zero")

    def act(self, scene):
        return np.zeros(scene.num_vehicles)


def test_the_shielded_env_executes_the_shields_command_and_charges_the_override():
    env = gym.make("CoopIntersection4Way-v0", config={**SMALL, "shield": True}).unwrapped
    env.reset(seed=3)
    overridden = 0
    for _ in range(60):
        scene = env.scene()
        n = scene.num_vehicles
        action = np.ones(env.action_space.shape, np.float32)  # always full throttle: the shield must brake some
        expected = Shield(FullThrottle()).check(scene, np.full(n, scene.a_max))
        _, _, terminated, _, info = env.step(action)
        executed = info["executed_action"]
        np.testing.assert_allclose(executed[:n], expected / scene.a_max, atol=1e-6)
        assert np.all(executed[n:] == 0)
        gap = float(np.abs(1.0 - executed[:n]).sum())
        assert info["reward_terms"]["shield"] == pytest.approx(-gap)
        assert info["shield_overridden"] == int((np.abs(expected - scene.a_max) > 1e-9).sum())
        overridden += info["shield_overridden"]
        assert not terminated and info["collisions"].size == 0
    assert overridden > 0


def test_the_replay_buffer_holds_the_executed_actions_of_a_shielded_env():
    env = _Recorder(gym.make("CoopIntersection4Way-v0", config={**SMALL, "shield": True}))
    model = TD3("GraphPolicy", env, learning_starts=10_000, buffer_size=500, policy_kwargs=TINY_NET, seed=0)
    stored: list[np.ndarray] = []
    add = model.replay_buffer.add

    def recording_add(obs, next_obs, action, reward, done, infos):
        stored.append(np.array(action, copy=True))
        return add(obs, next_obs, action, reward, done, infos)

    model.replay_buffer.add = recording_add
    model.learn(80)
    assert len(stored) == len(env.steps) == 80
    differs = 0
    for buffer_action, (proposal, info) in zip(stored, env.steps):
        np.testing.assert_array_equal(buffer_action[0], info["executed_action"])
        differs += int(not np.allclose(buffer_action[0], proposal))
    assert differs > 0  # the shield changed some of the random proposals, and those changes were stored


def test_a_clipped_residual_correction_is_stored_as_proposed_where_the_shield_keeps_it():
    # Over full throttle every positive correction clips to +5 m/s^2; stored clipped (0), the critic
    # would never see one and would extrapolate into them.
    config = {**SMALL, "shield": True, "residual_base": "fullthrottle", "residual_scale": 2.0}
    env = gym.make("CoopIntersection4Way-v0", config=config).unwrapped
    env.reset(seed=3)
    kept = overridden = 0
    for _ in range(60):
        scene = env.scene()
        n = scene.num_vehicles
        expected = Shield(FullThrottle()).check(scene, np.full(n, scene.a_max))
        action = np.full(env.action_space.shape, 0.7, np.float32)
        _, _, _, _, info = env.step(action)
        executed = info["executed_action"][:n]
        changed = np.abs(expected - scene.a_max) > 1e-9
        np.testing.assert_allclose(executed[~changed], 0.7, atol=1e-6)
        shielded = (expected[changed] - scene.a_max) / (2.0 * scene.a_max)
        np.testing.assert_allclose(executed[changed], shielded, atol=1e-6)
        assert info["reward_terms"]["shield"] == pytest.approx(-np.abs(expected - scene.a_max).sum() / scene.a_max)
        kept += int((~changed).sum())
        overridden += int(changed.sum())
    assert kept > 0 and overridden > 0


def test_a_residual_planner_with_a_zero_correction_is_its_base_planner():
    env = gym.make("CoopIntersection4Way-v0", config={"collision_handling": "remove"})
    env.reset(seed=0)
    scenario = generate_scenario(env.unwrapped.layout, 30.0, np.random.default_rng(5))
    base, _ = run_episode(env, AIMPlanner(), scenario, 30.0, seed=1)
    residual, _ = run_episode(env, ResidualPlanner(AIMPlanner(), _Zero(), 2.0), scenario, 30.0, seed=1)
    assert len(base) > 5
    assert base.equals(residual)


def test_the_residual_env_with_a_zero_action_drives_as_its_base_planner():
    config = {**SMALL, "collision_handling": "remove"}
    plain = gym.make("CoopIntersection4Way-v0", config=config).unwrapped
    residual = gym.make("CoopIntersection4Way-v0", config={**config, "residual_base": "aim"}).unwrapped
    plain.reset(seed=4)
    residual.reset(seed=4)
    aim = AIMPlanner()
    aim.reset(4)
    for _ in range(50):
        plain.step(plain.accelerations_to_action(aim.act(plain.scene())))
        residual.step(np.zeros(residual.action_space.shape, np.float32))
        a, b = plain.scene(), residual.scene()
        np.testing.assert_array_equal(a.vehicle_id, b.vehicle_id)
        # The plain env receives AIM's command through the float32 action; the residual env uses it in float64.
        np.testing.assert_allclose(a.arc, b.arc, rtol=0, atol=1e-5)
        np.testing.assert_allclose(a.speed, b.speed, rtol=0, atol=1e-5)
    assert plain.scene().num_vehicles > 0


def test_a_policy_file_with_a_residual_config_becomes_a_residual_planner(tmp_path):
    from sb3_graph.files.policy_files import load_policy, save_policy

    shipped = "envs/pretrained/coop_4way_fair/best_model.safetensors"
    loaded = load_policy(shipped)
    path = tmp_path / "residual" / "best_model.safetensors"
    path.parent.mkdir()
    source = {**loaded.description.source, "planner": {"residual_base": "fullthrottle", "residual_scale": 1.5}}
    save_policy(loaded.policy, path, loaded.description.algorithm, source)
    planner = make_planner(str(path))
    assert isinstance(planner, ResidualPlanner) and isinstance(planner.base, FullThrottle)
    assert planner.scale == 1.5 and planner.name == "RL:residual"
    plain = make_planner(shipped)
    assert not isinstance(plain, ResidualPlanner)
    # The residual's command is the base's plus 1.5 times the policy's, clipped.
    env = gym.make("CoopIntersection4Way-v0")
    env.reset(seed=2)
    scene = env.unwrapped.scene()
    expected = np.clip(scene.a_max + 1.5 * plain.act(scene), scene.a_min, scene.a_max)
    np.testing.assert_allclose(planner.act(scene), expected)


@pytest.mark.parametrize(
    "config, field",
    [
        ({"residual_base": "warp"}, "residual_base"),
        ({"residual_base": "aim", "residual_scale": 3.0}, "residual_scale"),
        ({"residual_base": "aim", "residual_scale": "1"}, "residual_scale"),
        ({"base": "aim"}, "keys"),
    ],
)
def test_a_bad_planner_config_is_one_error_naming_the_field(config, field):
    with pytest.raises(ValueError, match=field):
        check_planner_config(config, "file.safetensors")


def test_the_actor_warmup_starts_at_zero_and_holds_the_actor_until_its_step():
    env = gym.make("CoopIntersection4Way-v0", config=SMALL)
    model = TD3("GraphPolicy", env, learning_starts=20, train_freq=1, policy_delay=1, policy_kwargs=TINY_NET, seed=0)
    trunk_before = [p.detach().clone() for p in model.actor.trunk.parameters()]
    warmup = ActorWarmupCallback(steps=60)
    model.learn(50, callback=warmup)
    assert warmup.frozen
    assert all(float(p.detach().abs().max()) == 0.0 for p in model.actor.head.parameters())
    assert all(float(p.detach().abs().max()) == 0.0 for p in model.actor_target.head.parameters())
    assert all(bool((a == b).all()) for a, b in zip(trunk_before, model.actor.trunk.parameters()))
    critic_before = [p.detach().clone() for p in model.critic.parameters()]
    model.learn(40, callback=warmup, reset_num_timesteps=False)
    assert not warmup.frozen
    assert any(float(p.detach().abs().max()) > 0.0 for p in model.actor.head.parameters())
    assert any(not bool((a == b).all()) for a, b in zip(critic_before, model.critic.parameters()))
    with pytest.raises(ValueError, match="steps"):
        ActorWarmupCallback(steps=-1)


def test_vertex_origin_names_each_vehicles_previous_slot():
    env = gym.make("CoopIntersection4Way-v0", config={**SMALL, "duration": 40.0, "shield": True}).unwrapped
    env.reset(seed=2)
    left = joined = shifted = 0
    for _ in range(150):
        before = env.scene().vehicle_id.copy()
        _, _, terminated, truncated, info = env.step(np.ones(env.action_space.shape, np.float32))
        after = env.scene().vehicle_id
        origin = info["vertex_origin"]
        assert origin.shape == after.shape
        known = origin >= 0
        np.testing.assert_array_equal(before[origin[known]], after[known])
        assert not np.isin(after[~known], before).any()
        left += before.size - int(known.sum())
        joined += int((~known).sum())
        shifted += int((origin[known] != np.flatnonzero(known)).sum())
        if terminated or truncated:
            break
    assert left > 0 and joined > 0 and shifted > 0
