"""Planners as experts for behaviour cloning (envs.planners.expert) and `sb3-graph train --pretrain-from`."""

import json
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.vec_env import DummyVecEnv

import envs  # noqa: F401  (registers the environments)
from envs.planners import AIMPlanner, FIFOPlanner, make_planner
from envs.planners.expert import PlannerExpert
from sb3_graph.cli import main
from sb3_graph.plugins import expert_factory

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "CoopIntersection4Way-v0"
EMPTY = {"spawn_probability": 0.0, "initial_spawn_probability": 0.0}


def one_vehicle_env(**config):
    venv = DummyVecEnv([lambda: gym.make(ENV_ID, config={**EMPTY, **config})])
    venv.reset()
    base = venv.envs[0].unwrapped
    base.place_vehicles(["south->north"], arc=[30.0], speed=[6.0])
    return venv, base


@pytest.mark.parametrize(("spec", "planner"), [("aim", AIMPlanner), ("fifo", FIFOPlanner)])
def test_one_vehicle_expert_action_is_the_planners_command(spec, planner):
    venv, base = one_vehicle_env()
    expert = PlannerExpert(spec, venv)
    reference = planner()
    reference.reset()
    scene = base.scene()
    action = expert(None)
    assert action.shape == (1, base.action_space.shape[0])
    np.testing.assert_array_equal(action[0], base.accelerations_to_action(reference.act(scene)))
    assert np.all(action[0, 1:] == 0)


def test_residual_expert_action_reproduces_the_planners_command():
    venv, base = one_vehicle_env(residual_base="fullthrottle", residual_scale=2.0)
    expert = PlannerExpert("aim", venv)
    scene = base.scene()
    wanted = AIMPlanner().act(scene)
    action = expert(None)
    applied = np.clip(make_planner("fullthrottle").act(scene) + 2.0 * base.config["max_acceleration"] * action[0, :1],
                      -base.config["max_acceleration"], base.config["max_acceleration"])  # fmt: skip
    np.testing.assert_allclose(applied, wanted, atol=1e-9)
    assert not np.allclose(action[0, :1], base.accelerations_to_action(wanted)[:1])  # not the plain action


def test_the_domain_declares_its_expert():
    factory, _ = expert_factory(ENV_ID)
    assert factory == "envs.planners.expert:make_expert"
    assert expert_factory("GraphMaxNeighbour-v0")[0] == "sb3_graph.toy_envs:make_expert"
    assert expert_factory("Pendulum-v1") is None


def test_train_pretrain_from_aim_runs_end_to_end(tmp_path):
    out = tmp_path / "run"
    status = main(
        ["train", "--config", str(ROOT / "zoo_configs" / "td3.yml"), "--env", ENV_ID, "--out", str(out),
         "--n-timesteps", "40", "--eval-freq", "40", "--eval-episodes", "1", "--checkpoint-freq", "40",
         "--no-progress", "--pretrain-from", "aim", "--pretrain-transitions", "40", "--pretrain-steps", "8",
         "--hyperparams", "learning_starts:16", "batch_size:16", "buffer_size:500", "n_envs:2", "bc_coef:0.5",
         "--env-kwargs", json.dumps({"config": {"duration": 6.0}})]
    )  # fmt: skip
    assert status == 0
    record = json.loads((out / "run.json").read_text())
    assert record["pretrain"]["from"] == "aim" and record["pretrain"]["transitions"] == 40
    assert record["pretrain"]["gradient_steps"] == 8 and record["pretrain"]["critic_steps"] == 2
    assert record["num_timesteps"] == 40 and (out / "final_model.zip").is_file()


def test_the_shipped_advice_recipe_clones_trains_and_exports_end_to_end(tmp_path):
    """zoo_configs/td3_advice.yml (the shipped planner's recipe) for a few hundred steps: cloning glide,
    RL, then the export with the config's action type and features, which runs as an advice planner."""
    import yaml

    from envs.planners.priority import PriorityPlanner

    out = tmp_path / "run"
    status = main(
        ["train", "--config", str(ROOT / "zoo_configs" / "td3_advice.yml"), "--env", ENV_ID, "--out", str(out),
         "--n-timesteps", "200", "--eval-freq", "200", "--eval-episodes", "1", "--no-progress",
         "--hyperparams", "pretrain_transitions:40", "pretrain_steps:8", "learning_starts:64", "batch_size:16",
         "buffer_size:1000", "n_envs:2", "--env-kwargs", json.dumps({"config": {"duration": 6.0}})]
    )  # fmt: skip
    assert status == 0
    record = json.loads((out / "run.json").read_text())
    assert record["pretrain"]["from"] == "glide" and record["num_timesteps"] == 200
    config = yaml.safe_load((out / "config.yml").read_text())["env_kwargs"]["config"]
    header = {key: config[key] for key in ("action", "vertex_features", "edge_features")}
    target = tmp_path / "advice.safetensors"
    assert main(["export", str(out / "final_model.zip"), str(target), "--planner-config", json.dumps(header)]) == 0
    planner = make_planner(f"{target}+shield").planner
    assert isinstance(planner, PriorityPlanner) and planner.kind == "advice" and planner.scale == 64.0


def test_train_pretrain_from_an_unknown_planner_is_one_line(tmp_path, capsys):
    status = main(
        ["train", "--config", str(ROOT / "zoo_configs" / "td3.yml"), "--env", ENV_ID, "--out", str(tmp_path / "r"),
         "--n-timesteps", "40", "--no-progress", "--pretrain-from", "nosuchplanner"]
    )  # fmt: skip
    assert status != 0
    assert "pretrain_from" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


PRIORITY = {"action": {"type": "priority"}}


def test_glide_expert_with_priority_scores_is_zero_and_drives_as_glide():
    venv, base = one_vehicle_env(**PRIORITY)
    reference, reference_base = one_vehicle_env()  # acceleration actions, glide's own command
    expert, glide = PlannerExpert("glide", venv), PlannerExpert("glide", reference)
    for _ in range(3):
        scores = expert(None)
        assert scores.shape == (1, base.action_space.shape[0]) and not scores.any()
        venv.step(scores)
        reference.step(glide(None))
    mine, theirs = base.scene(), reference_base.scene()
    assert mine.num_vehicles == theirs.num_vehicles == 1
    np.testing.assert_array_equal(mine.speed, theirs.speed)
    np.testing.assert_array_equal(mine.arc, theirs.arc)


def test_other_planners_are_refused_with_priority_scores_in_one_line():
    venv, _ = one_vehicle_env(**PRIORITY)
    for spec in ("aim", "fifo", "glide+shield"):  # glide+shield: only where the env shields
        message = re.escape(f"planner '{spec}' has no exact label for action type 'priority'")
        with pytest.raises(ValueError, match=message) as e:
            PlannerExpert(spec, venv)
        assert "\n" not in str(e.value)
    shielded, _ = one_vehicle_env(shield=True, **PRIORITY)
    assert not PlannerExpert("glide+shield", shielded)(None).any()


def test_advice_scores_take_glide_as_their_expert_and_refuse_others():
    venv, _ = one_vehicle_env(action={"type": "advice"})
    assert not PlannerExpert("glide", venv)(None).any()
    assert PlannerExpert("glide", venv).cache_key is None  # an exact label: nothing beyond the spec
    with pytest.raises(ValueError, match=re.escape("planner 'aim' has no exact label for action type 'advice'")):
        PlannerExpert("aim", venv)


def test_a_lookahead_class_labels_advice_over_its_own_glide_and_other_classes_are_refused():
    """Expert iteration's teacher: a class spec of a LookaheadPlanner (the search with the shipped student as its
    proposer) labels an advice environment over the same glide, as ``lookahead`` does; a class over another
    glide, or a class that is no search, is refused in one line."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "lookahead_variants.py"
    venv, base = one_vehicle_env(action={"type": "advice", "glide": "recipe"})
    expert = PlannerExpert(f"{script}:WithStudent", venv)
    assert expert.searches and expert.planners[0].proposer is not None
    assert "per_approach=False" in expert.cache_key  # the search's parameters key a label cache
    assert "per_approach=True" in PlannerExpert("lookahead", venv).cache_key
    scores = expert(None)
    assert scores.shape == (1, base.action_space.shape[0]) and np.all(np.abs(scores) <= 1.0)
    other, _ = one_vehicle_env(action={"type": "advice"})  # glide's own values, not the recipe
    with pytest.raises(ValueError, match="its glide is not the environment's") as error:
        PlannerExpert(f"{script}:WithStudent", other)
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="a class must be a LookaheadPlanner, got") as error:
        PlannerExpert(f"{Path(__file__).resolve().parent / 'serve_support.py'}:SlowPlanner", venv)
    assert "\n" not in str(error.value)
