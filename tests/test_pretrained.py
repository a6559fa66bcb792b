"""The GNN planner shipped with the package loads (weights only) and acts on every layout."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml

import envs  # noqa: F401 - registers the environments
from envs.commands.evaluate import DEFAULT_MODEL
from envs.planners import make_planner
from sb3_graph import TD3
from sb3_graph.weights import read_weights_file

SHIPPED_ZIP = DEFAULT_MODEL.with_suffix(".zip")


def test_shipped_model_comes_with_its_run_record():
    folder = DEFAULT_MODEL.parent
    assert DEFAULT_MODEL.is_file() and DEFAULT_MODEL.suffix == ".safetensors"
    config = yaml.safe_load((folder / "config.yml").read_text())
    assert config["policy"] == "sb3_graph.GraphPolicy" and config["n_timesteps"] > 0
    assert (folder / "run.json").is_file() and (folder / "README.md").is_file()
    assert "/" not in (folder / "run.json").read_text().split('"command": "')[1].split()[0]  # no machine path


def test_shipped_weights_are_the_zip_policy():
    """The weights-only file is `sb3-graph export` of the shipped zip: the same tensors."""
    description, state = read_weights_file(DEFAULT_MODEL)
    assert (description.algorithm, description.policy_class) == ("TD3", "GraphPolicy")
    policy = TD3.load(SHIPPED_ZIP, device="cpu").policy  # our own shipped file: trusted here
    reference = policy.state_dict()
    assert set(state) == set(reference)
    for key, value in reference.items():
        assert th.equal(state[key], value), key


@pytest.mark.parametrize("env_id", ["CoopIntersection4Way-v0", "CoopIntersection3Way-v0", "CoopIntersectionInD-v0"])
def test_shipped_model_acts_on_every_layout(env_id):
    model = TD3.load(SHIPPED_ZIP, device="cpu")
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


def test_the_weight_studys_six_planners_are_fine_tunings_of_the_shipped_one():
    """examples/weight_study/seeds (issue #23): each file has the shipped planner's architecture, and
    fine-tuning moved its weights (a copy of the shipped file would pass a load check too)."""
    from pathlib import Path

    _, shipped = read_weights_file(DEFAULT_MODEL)
    root = Path(__file__).parents[1] / "examples" / "weight_study" / "seeds"
    files = sorted(root.glob("*/seed_*/best_model.safetensors"))
    assert [f.relative_to(root).as_posix() for f in files] == [
        f"{s}/seed_{k}/best_model.safetensors" for s in ("default", "tuned") for k in range(3)
    ]
    for file in files:
        description, state = read_weights_file(file)
        assert (description.algorithm, description.policy_class) == ("TD3", "GraphPolicy")
        assert {k: v.shape for k, v in state.items()} == {k: v.shape for k, v in shipped.items()}
        assert any(not th.equal(state[k], shipped[k]) for k in shipped if k.startswith("actor.")), file
