"""The GNN planner shipped with the package loads and acts on every layout."""

import gymnasium as gym
import numpy as np
import pytest
import yaml

import envs  # noqa: F401 - registers the environments
from envs.commands.evaluate import DEFAULT_MODEL
from envs.planners import make_planner
from sb3_graph import TD3


def test_shipped_model_comes_with_its_run_record():
    folder = DEFAULT_MODEL.parent
    assert DEFAULT_MODEL.is_file()
    config = yaml.safe_load((folder / "config.yml").read_text())
    assert config["policy"] == "sb3_graph.GraphPolicy" and config["n_timesteps"] > 0
    assert (folder / "run.json").is_file() and (folder / "README.md").is_file()


@pytest.mark.parametrize("env_id", ["CoopIntersection4Way-v0", "CoopIntersection3Way-v0", "CoopIntersectionInD-v0"])
def test_shipped_model_acts_on_every_layout(env_id):
    model = TD3.load(DEFAULT_MODEL, device="cpu")
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    planner = make_planner(str(DEFAULT_MODEL))
    for _ in range(20):
        n = int(obs["node_mask"].sum())
        action, _ = model.predict(obs, deterministic=True)
        assert np.isfinite(action).all() and np.all(np.abs(action) <= 1) and np.all(action[n:] == 0)
        scene = env.unwrapped.scene()
        acc = planner.act(scene)
        assert acc.shape == (n,) and np.isfinite(acc).all()
        np.testing.assert_allclose(acc, action[:n] * scene.a_max, atol=1e-5)  # same observation, same answer
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            obs, _ = env.reset()
