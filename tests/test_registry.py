"""Every registered algorithm: trained briefly on the intersection, exported as a weights-only file,
loaded as a planner, it acts as its own ``model.predict(obs, deterministic=True)``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import envs  # noqa: F401  (registers the environments)
import sb3_graph
from envs.planners.gnn import GNNPlanner
from envs.simulation.graph import build_observation
from sb3_graph.cli import main
from sb3_graph.files.policy_files import POLICY_REGISTRY, load_policy
from sb3_graph.registry import ALGORITHMS, algorithm_entry, entry_of_policy

torch.set_num_threads(1)

ENV_ID = "CoopIntersection4Way-v0"
SMALL = dict(encoder_dim=8, conv_dims=[8, 8])
# Tiny runs: a few hundred steps, a handful of gradient steps each.
RUNS = {
    "td3": dict(learning_starts=100, batch_size=16, buffer_size=300, train_freq=20, gradient_steps=2),
    "ddpg": dict(learning_starts=100, batch_size=16, buffer_size=300, train_freq=20, gradient_steps=2),
    "sac": dict(learning_starts=100, batch_size=16, buffer_size=300, train_freq=20, gradient_steps=2),
    "tqc": dict(learning_starts=100, batch_size=16, buffer_size=300, train_freq=20, gradient_steps=2),
    "crossq": dict(learning_starts=100, batch_size=16, buffer_size=300, train_freq=20, gradient_steps=2),
    "ppo": dict(n_steps=100, batch_size=50, n_epochs=1),
    "a2c": dict(n_steps=20),
}
STEPS = 300


@pytest.fixture(scope="module")
def scenes():
    """Scenes of a short run of the environment with a few to a dozen vehicles."""
    env = gym.make(ENV_ID)
    env.reset(seed=3)
    found = []
    for step in range(120):
        env.step(np.full(env.action_space.shape, 0.3, dtype=np.float32))
        scene = env.unwrapped.scene()
        if step % 6 == 0 and scene.num_vehicles:
            found.append(scene)
    env.close()
    assert len(found) >= 10 and max(scene.num_vehicles for scene in found) >= 5
    return found


def test_every_algorithm_has_one_entry():
    assert set(RUNS) == set(ALGORITHMS)
    for algo, entry in ALGORITHMS.items():
        algorithm = entry.load_class()
        assert algorithm is getattr(sb3_graph, entry.name)
        assert algorithm.policy_aliases["GraphPolicy"] is entry.policy_class()
        assert algorithm.graph_buffer_class.__name__ == entry.buffer.rpartition(":")[2]
        assert POLICY_REGISTRY[entry.name]  # every algorithm exports
        assert algorithm_entry(entry.name) is algorithm_entry(algo) is entry
    with pytest.raises(KeyError, match="known: td3"):
        algorithm_entry("dqn")


@pytest.mark.parametrize("algo", list(RUNS))
def test_trained_model_exported_acts_as_its_predict(algo, scenes, tmp_path, capsys):
    entry = ALGORITHMS[algo]
    policy_kwargs = dict(SMALL, n_quantiles=5) if algo == "tqc" else dict(SMALL)
    model = entry.load_class()(
        "GraphPolicy", gym.make(ENV_ID), seed=0, policy_kwargs=policy_kwargs, device="cpu", **RUNS[algo]
    )
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(STEPS)
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters())), "no gradient step ran"
    model.save(tmp_path / "model.zip")
    out = tmp_path / "planner.safetensors"
    assert main(["export", str(tmp_path / "model.zip"), str(out)]) == 0
    # DDPG's zip cannot be told from TD3's (same policy class, same fields): it exports as TD3, same actions.
    written = "TD3" if algo == "ddpg" else entry.name
    assert f"export: {written} " in capsys.readouterr().out
    assert load_policy(out).description.algorithm == written

    planner = GNNPlanner(out)
    assert entry_of_policy(planner.model) is not None and planner._graph_actor  # the direct graph path
    for scene in scenes:
        n = scene.num_vehicles
        obs = build_observation(scene, model.observation_space)
        expected = model.predict(obs, deterministic=True)[0][:n]
        np.testing.assert_allclose(planner.vertex_actions(scene), expected, rtol=0, atol=1e-6)
        np.testing.assert_allclose(planner.predict(obs)[:n], expected, rtol=0, atol=1e-6)
        acc = np.clip(np.asarray(expected, dtype=float) * scene.a_max, scene.a_min, scene.a_max)
        np.testing.assert_allclose(planner.act(scene), acc, rtol=0, atol=1e-5)
    batched = planner.act_many(scenes[:4])
    for scene, answer in zip(scenes[:4], batched, strict=True):
        np.testing.assert_allclose(answer, planner.act(scene), rtol=1e-5, atol=1e-5)
    # A stochastic policy's deterministic action is its mean, squashed (SAC family) or clipped (PPO, A2C).
    if algo in ("sac", "tqc", "crossq", "ppo", "a2c"):
        obs = build_observation(scenes[-1], model.observation_space)
        samples = np.stack([model.predict(obs, deterministic=False)[0] for _ in range(3)])
        assert not np.allclose(samples[0], samples[1])
