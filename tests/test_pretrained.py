"""The GNN planners shipped with the package load (weights only) and act on every layout: the default
(an advice policy over glide, trained behind the shield), the residual policy that was the default
before it, and the paper's planner retrained under the fair physics."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml

import envs  # noqa: F401 - registers the environments
from envs.commands.evaluate import DEFAULT_MODEL, PAPER_MODEL, RESIDUAL_MODEL
from envs.planners import make_planner
from envs.planners.glide import GUARDED, GlideParams, GlidePlanner
from envs.planners.gnn import planner_config_of
from envs.planners.priority import PriorityPlanner
from envs.planners.residual import ResidualPlanner
from envs.simulation.config import action_config
from sb3_graph import TD3
from sb3_graph.files.policy_files import read_weights_file

SHIPPED_ZIP = PAPER_MODEL.with_suffix(".zip")


@pytest.mark.parametrize("model", [DEFAULT_MODEL, RESIDUAL_MODEL, PAPER_MODEL], ids=["default", "residual", "paper"])
def test_shipped_model_comes_with_its_run_record(model):
    folder = model.parent
    assert model.is_file() and model.suffix == ".safetensors"
    config = yaml.safe_load((folder / "config.yml").read_text())
    assert config["policy"] == "sb3_graph.GraphPolicy" and config["n_timesteps"] > 0
    assert (folder / "run.json").is_file() and (folder / "README.md").is_file()
    assert "/" not in (folder / "run.json").read_text().split('"command": "')[1].split()[0]  # no machine path


def test_default_model_is_the_advice_policy_of_its_training_config():
    """The header carries what the environment did around the policy in training (its config.yml):
    the action type and scale, and the features, so that `--planner FILE` builds the same planner."""
    config = yaml.safe_load((DEFAULT_MODEL.parent / "config.yml").read_text())["env_kwargs"]["config"]
    header = planner_config_of(DEFAULT_MODEL)
    assert config["shield"] is True and action_config(config["action"])["type"] == "advice"
    assert action_config(header["action"]) == action_config(config["action"])  # glide's version named: first_phase
    assert header["action"]["glide"] == "first_phase"
    for key in ("vertex_features", "edge_features"):
        assert header[key] == config[key], key


def test_the_first_advice_policy_runs_over_the_glide_it_was_trained_over():
    """A policy file whose header names no glide version was trained before glide had versions: it runs
    over glide as first shipped."""
    old = DEFAULT_MODEL.parent.parent / "coop_4way_advice_guarded" / "best_model.safetensors"
    assert "glide" not in planner_config_of(old)["action"]
    planner = make_planner(str(old))
    assert isinstance(planner, PriorityPlanner) and planner.scheduler.params == GUARDED
    assert make_planner(str(DEFAULT_MODEL)).scheduler.params == GlideParams()


@pytest.mark.parametrize("env_id", ["CoopIntersection4Way-v0", "CoopIntersection3Way-v0", "CoopIntersectionInD-v0"])
def test_default_model_moves_glides_windows_on_every_layout(env_id):
    """The shipped scores run over glide: some vehicle's window differs from glide's own, and without its
    critic gate the commands differ from glide's somewhere; every command is a valid acceleration. Behind
    its gate (the shipped setting) it plans as glide wherever the gate stays shut."""
    planner = make_planner(str(DEFAULT_MODEL))
    assert isinstance(planner, PriorityPlanner) and planner.kind == "advice" and planner.scale == 64.0
    assert planner.critic_gate == 0.2
    planner.critic_gate = 0.0  # the gate opens wherever the critics see any gain
    glide = GlidePlanner()
    env = gym.make(env_id, config={"spawn_probability": 0.07})
    env.reset(seed=0)
    moved = differs = 0
    for _ in range(100):
        scene = env.unwrapped.scene()
        scores = np.asarray(planner.scores.act(scene), float) / scene.a_max
        moved += int(np.sum(np.abs(scores) > 0.05))
        acc = planner.act(scene)
        differs += int(np.sum(acc != glide.act(scene)))
        n = scene.num_vehicles
        assert acc.shape == (n,) and np.isfinite(acc).all()
        assert np.all(acc >= scene.a_min) and np.all(acc <= scene.a_max)
        _, _, terminated, truncated, _ = env.step(np.append(acc / scene.a_max, np.zeros(env.action_space.shape[0] - n)))
        if terminated or truncated:
            env.reset()
            planner.reset()
            glide.reset()
    assert moved > 0 and differs > 0 and planner.stats()["gate_open_steps"] > 0


def test_default_models_gate_opens_in_dense_traffic_and_is_glide_where_shut():
    planner, glide = make_planner(str(DEFAULT_MODEL)), GlidePlanner()
    env = gym.make("CoopIntersection4Way-v0", config={"spawn_probability": 0.14, "shield": True})
    env.reset(seed=0)
    shut_differs = 0
    for _ in range(200):
        scene = env.unwrapped.scene()
        acc, own = planner.act(scene), glide.act(scene)
        if planner.gate_open_steps == 0:  # shut so far: glide's own windows, glide's commands (held advice after)
            shut_differs += int(np.sum(acc != own))
        n = scene.num_vehicles
        env.step(np.append(acc / scene.a_max, np.zeros(env.action_space.shape[0] - n)).astype(np.float32))
    stats = planner.stats()
    assert stats["gate_steps"] == 200 and 0 < stats["gate_open_steps"] < 200
    assert shut_differs == 0


def test_residual_model_is_the_residual_policy_of_its_training_config():
    """The former default's header carries its residual base and features (its config.yml)."""
    config = yaml.safe_load((RESIDUAL_MODEL.parent / "config.yml").read_text())["env_kwargs"]["config"]
    header = planner_config_of(RESIDUAL_MODEL)
    assert config["shield"] is True
    for key in ("residual_base", "residual_scale", "vertex_features", "edge_features"):
        assert header[key] == config[key], key


@pytest.mark.parametrize("env_id", ["CoopIntersection4Way-v0", "CoopIntersection3Way-v0", "CoopIntersectionInD-v0"])
def test_residual_model_acts_on_every_layout_and_corrects_its_base(env_id):
    planner = make_planner(str(RESIDUAL_MODEL))
    assert isinstance(planner, ResidualPlanner) and planner.base.name == "FullThrottle"
    env = gym.make(env_id, config={"spawn_probability": 0.07})
    env.reset(seed=0)
    corrected = 0
    for _ in range(100):
        scene = env.unwrapped.scene()
        acc = planner.act(scene)
        n = scene.num_vehicles
        assert acc.shape == (n,) and np.isfinite(acc).all()
        assert np.all(acc >= scene.a_min) and np.all(acc <= scene.a_max)
        corrected += int(np.sum(acc < scene.a_max - 1e-6))  # a trained correction, not the base alone
        _, _, terminated, truncated, _ = env.step(np.append(acc / scene.a_max, np.zeros(env.action_space.shape[0] - n)))
        if terminated or truncated:
            env.reset()
    assert corrected > 0


def test_shipped_weights_are_the_zip_policy():
    """The paper planner's weights-only file is `sb3-graph export` of its zip: the same tensors."""
    description, state = read_weights_file(PAPER_MODEL)
    assert (description.algorithm, description.policy_class) == ("TD3", "GraphPolicy")
    policy = TD3.load(SHIPPED_ZIP, device="cpu").policy  # our own shipped file: trusted here
    reference = policy.state_dict()
    assert set(state) == set(reference)
    for key, value in reference.items():
        assert th.equal(state[key], value), key


@pytest.mark.parametrize("env_id", ["CoopIntersection4Way-v0", "CoopIntersection3Way-v0", "CoopIntersectionInD-v0"])
def test_paper_model_acts_on_every_layout(env_id):
    model = TD3.load(SHIPPED_ZIP, device="cpu")
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    planner = make_planner(str(PAPER_MODEL))
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
    """experiments/weight_study/seeds (issue #23): each file has the shipped planner's architecture, and
    fine-tuning moved its weights (a copy of the shipped file would pass a load check too)."""
    from pathlib import Path

    _, shipped = read_weights_file(PAPER_MODEL)
    root = Path(__file__).parents[1] / "experiments" / "weight_study" / "seeds"
    files = sorted(root.glob("*/seed_*/best_model.safetensors"))
    assert [f.relative_to(root).as_posix() for f in files] == [
        f"{s}/seed_{k}/best_model.safetensors" for s in ("default", "tuned") for k in range(3)
    ]
    for file in files:
        description, state = read_weights_file(file)
        assert (description.algorithm, description.policy_class) == ("TD3", "GraphPolicy")
        assert {k: v.shape for k, v in state.items()} == {k: v.shape for k, v in shipped.items()}
        assert any(not th.equal(state[k], shipped[k]) for k in shipped if k.startswith("actor.")), file
