"""``sb3-graph tune`` behind the shield (issue #23): the weights' centres, --tune-config, the shielded and
residual trial, the objectives on task metrics, --init-weights, every --algo."""

import argparse

import numpy as np
import optuna
import pytest
import torch as th
import yaml
from optuna.trial import TrialState

from envs.simulation.rewards import PAPER_REWARD_WEIGHTS, TASK_REWARD_WEIGHTS
from sb3_graph.cli import main
from sb3_graph.commands import UserError
from sb3_graph.commands import tune as commands
from sb3_graph.registry import ALGORITHMS
from sb3_graph.tuning.objectives import DELAY, FLOW, make_objective
from sb3_graph.tuning.runner import TrialSettings, run_trial
from sb3_graph.tuning.search_space import entry_with_params, parse_config_space, split_params

th.set_num_threads(1)
optuna.logging.set_verbosity(optuna.logging.WARNING)
INTERSECTION = "CoopIntersection4Way-v0"
TOY = "GraphMaxNeighbour-v0"
TINY = {
    "n_timesteps": 200,
    "policy": "GraphPolicy",
    "learning_starts": 50,
    "batch_size": 16,
    "buffer_size": 500,
    "train_freq": 4,
    "policy_kwargs": "dict(encoder_dim=8, conv_dims=[8])",
}
SMALL = {"duration": 10.0, "max_vehicles": 16, "max_edges": 192}
SHIELDED = {**SMALL, "shield": True, "residual_base": "fullthrottle", "residual_scale": 1.0}


def write_config(tmp_path, config=None, entry=TINY, name="c.yml"):
    path = tmp_path / name
    entries = {INTERSECTION: {**entry, "env_kwargs": {"config": dict(config or {})}}, TOY: dict(entry)}
    path.write_text(yaml.safe_dump(entries))
    return path


def parse(path, *extra, env=INTERSECTION):
    parser = argparse.ArgumentParser()
    commands.add_arguments(parser)
    return parser.parse_args(["--config", str(path), "--env", env, "--study-name", "s", *extra])


# ---------------------------------------------------------------- the search space
def test_weight_centres_are_the_weights_of_the_preset_the_config_selects(tmp_path):
    task, _ = commands.prepare(parse(write_config(tmp_path, SMALL)))
    assert task.weight_defaults == TASK_REWARD_WEIGHTS  # the default reward: the task preset's weights
    paper, attrs = commands.prepare(parse(write_config(tmp_path, {**SMALL, "reward": "paper"})))
    assert paper.weight_defaults == PAPER_REWARD_WEIGHTS  # Table I only for reward: paper
    assert attrs["reward"] == "paper" and attrs["weight_centres"] == PAPER_REWARD_WEIGHTS
    own = write_config(tmp_path, {**SMALL, "reward_weights": {"delay": 0.3}})
    assert commands.prepare(parse(own))[0].weight_defaults == {**TASK_REWARD_WEIGHTS, "delay": 0.3}
    chosen, _ = commands.prepare(parse(own, "--weights", "throughput", "delay"))
    assert chosen.weight_defaults == {"throughput": 0.2, "delay": 0.3}
    with pytest.raises(UserError, match=r"unknown reward terms \['velocity'\]; the terms of reward 'task': "):
        commands.prepare(parse(own, "--weights", "velocity"))
    zero = write_config(tmp_path, {**SMALL, "reward_weights": {"shield": 0.0}})
    with pytest.raises(UserError, match=r"\['shield'\] weigh \[0.0\] of reward 'task': a log range needs"):
        commands.prepare(parse(zero, "--weights", "shield"))


def test_tune_config_samples_the_residual_scale_within_what_the_env_accepts(tmp_path):
    path = write_config(tmp_path, SHIELDED)
    settings, attrs = commands.prepare(parse(path, "--tune-config", "residual_scale:0.25:2"))
    assert settings.config_space == {"residual_scale": (0.25, 2.0, False)}
    assert attrs["config_space"] == {"residual_scale": [0.25, 2.0, False]}
    assert parse_config_space(["residual_scale:0.1:2:log"]) == {"residual_scale": (0.1, 2.0, True)}
    for spec, message in [
        ("residual_scale:0.5:3", r"--tune-config residual_scale: 3 is refused by .*a number in \(0, 2\]"),
        ("residual_base:0:1", "'residual_base' is not a number of"),
        ("residual_scale:2:1", "expected finite LOW < HIGH"),
        ("residual_scale:0.5", "expected KEY:LOW:HIGH"),
        ("reward_weights:0:1", "tuned by --weights"),
    ]:
        with pytest.raises(UserError, match=message):
            commands.prepare(parse(path, "--tune-config", spec))
    # the parameter goes into the env's config, next to the weights
    params = {"weight.delay": 0.2, "config.residual_scale": 1.5}
    entry = entry_with_params({"env_kwargs": {"config": dict(SHIELDED)}}, params)
    assert entry["env_kwargs"]["config"] == {**SHIELDED, "residual_scale": 1.5, "reward_weights": {"delay": 0.2}}
    assert split_params(params) == ({"delay": 0.2}, {})


def test_the_shipped_shield_configs_tune_behind_the_shield_and_can_fine_tune_the_shipped_planner():
    from envs.evaluation.tuning import TUNING_PRESET

    shield, _ = commands.prepare(parse("zoo_configs/td3_shield.yml", "--timesteps", "3000"))
    config = shield.entry["env_kwargs"]["config"]
    assert config["shield"] is True and {key: config[key] for key in TUNING_PRESET} == TUNING_PRESET
    assert shield.weight_defaults == TASK_REWARD_WEIGHTS and shield.init_weights is None
    planner = "envs/pretrained/coop_4way_fair/best_model.safetensors"  # trained on 64 vehicles, tuned on 16
    extra = ["--timesteps", "3000", "--tune-config", "residual_scale:0.25:2", "--init-weights", planner]
    residual, attrs = commands.prepare(parse("zoo_configs/td3_residual.yml", *extra))
    assert residual.entry["env_kwargs"]["config"]["residual_base"] == "fullthrottle"
    assert residual.config_space == {"residual_scale": (0.25, 2.0, False)} and str(residual.init_weights) == planner
    assert attrs["init_weights"] == planner


# ---------------------------------------------------------------- a trial behind the shield
def test_a_shielded_trial_trains_behind_the_shield_and_scores_the_shielded_planner_on_task_metrics(monkeypatch):
    import stable_baselines3.common.env_util as env_util

    from envs.evaluation import tuning
    from envs.planners.residual import ResidualPlanner
    from envs.planners.shield import Shield

    made, planners, seen = [], [], []
    make_vec_env = env_util.make_vec_env
    monkeypatch.setattr(env_util, "make_vec_env", lambda *a, **k: made.append(make_vec_env(*a, **k)) or made[-1])
    trial_planner = tuning.trial_planner
    monkeypatch.setattr(tuning, "trial_planner", lambda *a: planners.append(trial_planner(*a)) or planners[-1])

    def evaluator(model, **kwargs):  # the domain's evaluator, on a short validation episode
        seen.append(kwargs["env_kwargs"])
        return tuning.evaluate_model(model, duration=10.0, **kwargs)

    settings = TrialSettings(
        env_id=INTERSECTION,
        entry={**TINY, "env_kwargs": {"config": dict(SHIELDED)}},
        timesteps=200,
        objective=make_objective("flow-delay", max_collision_rate=1.0),
        evaluator=evaluator,
        weight_defaults={"throughput": 0.2, "delay": 0.1},
        config_space={"residual_scale": (0.25, 2.0, False)},
        evaluations=1,
        eval_episodes=1,
    )
    study = optuna.create_study(direction="maximize")
    study.optimize(lambda t: run_trial(t, settings), n_trials=1)
    (trial,) = study.trials
    assert trial.state == TrialState.COMPLETE, trial.user_attrs
    (config,) = made[0].get_attr("config")  # the training env
    assert config["shield"] is True and config["residual_base"] == "fullthrottle"
    assert config["residual_scale"] == trial.params["config.residual_scale"]
    assert config["reward_weights"]["delay"] == trial.params["weight.delay"]
    # the validation ran the planner that the config describes: residual on full throttle, behind the shield
    (planner,) = planners
    assert isinstance(planner, Shield) and isinstance(planner.planner, ResidualPlanner)
    assert planner.planner.scale == trial.params["config.residual_scale"]
    assert seen[0]["config"]["shield"] is True
    # the objective is the task metrics', never the training reward
    assert trial.value == pytest.approx(trial.user_attrs[FLOW] - 0.01 * trial.user_attrs[DELAY])
    assert 0 <= trial.user_attrs["shield_intervention_rate"] <= 1
    assert trial.system_attrs["constraints:collision_rate"] == pytest.approx(trial.user_attrs["collision_rate"] - 1.0)


def test_a_zero_residual_actor_behind_the_shield_scores_as_its_base_behind_the_shield():
    import gymnasium as gym

    import envs  # noqa: F401
    from envs.evaluation.tuning import evaluate_model, evaluate_planner
    from envs.planners.adversarial import FullThrottle
    from envs.planners.shield import Shield
    from sb3_graph import TD3

    kwargs = {"config": {**SHIELDED, "duration": 20.0}}
    model = TD3("GraphPolicy", gym.make(INTERSECTION, **kwargs), policy_kwargs={"encoder_dim": 8, "conv_dims": [8]})
    with th.no_grad():
        model.policy.actor.head.weight.zero_()
        model.policy.actor.head.bias.zero_()  # tanh(0): no correction
    metrics = evaluate_model(model, INTERSECTION, kwargs, episodes=1, seed=5, duration=20.0)
    base = evaluate_planner(Shield(FullThrottle()), INTERSECTION, {"config": SMALL}, episodes=1, seed=5, duration=20.0)
    assert metrics == pytest.approx(base, nan_ok=True)
    assert metrics["vehicles"] > 0 and "shield_intervention_rate" in metrics
    bare = evaluate_planner(FullThrottle(), INTERSECTION, {"config": SMALL}, episodes=1, seed=5, duration=20.0)
    assert bare["collision_rate"] > metrics["collision_rate"]  # the shield made the difference
    plain = evaluate_model(model, INTERSECTION, {"config": SMALL}, episodes=1, seed=5, duration=20.0)
    assert "shield_intervention_rate" not in plain  # not shielded, not residual: the actor's zero command


# ---------------------------------------------------------------- --init-weights
def tiny_policy_file(tmp_path, encoder_dim=8, name="init.safetensors"):
    import gymnasium as gym

    import sb3_graph.toy_envs  # noqa: F401
    from sb3_graph import TD3
    from sb3_graph.files.policy_files import save_policy

    env = gym.make(TOY)
    model = TD3("GraphPolicy", env, policy_kwargs={"encoder_dim": encoder_dim, "conv_dims": [8]}, seed=1)
    return save_policy(model.policy, tmp_path / name, "TD3"), model


def test_init_weights_fine_tunes_each_trial_from_the_file_tensors_only(tmp_path):
    import json

    from safetensors.torch import load_file, save_file

    from sb3_graph import TD3
    from sb3_graph.tuning.runner import load_init_weights

    path, source = tiny_policy_file(tmp_path)
    # a header that names classes to import: a tensors-only load never reads them
    hostile = tmp_path / "hostile.safetensors"
    header = {"format": "sb3-graph-policy", "version": 1, "algorithm": "TD3", "policy_class": "os:system",
              "policy_kwargs": {"activation_fn": {"class": "os.system"}}, "observation_space": {},
              "action_space": {}}  # fmt: skip
    save_file(load_file(str(path)), str(hostile), metadata={"sb3_graph": json.dumps(header)})
    fresh = TD3("GraphPolicy", source.env, policy_kwargs={"encoder_dim": 8, "conv_dims": [8]}, seed=2)
    load_init_weights(fresh, hostile)
    for key, tensor in source.policy.state_dict().items():
        assert th.equal(fresh.policy.state_dict()[key], tensor), key

    config = write_config(tmp_path, SMALL)
    storage = f"sqlite:///{tmp_path}/i.db"
    base = ["tune", "--config", str(config), "--env", TOY, "--storage", storage, "--tune-algo",
            "--timesteps", "100", "--eval-episodes", "1", "--n-trials", "1"]  # fmt: skip
    assert main([*base, "--study-name", "init", "--init-weights", str(path)]) == 0
    study = optuna.load_study(study_name="init", storage=storage)
    assert study.trials[0].state == TrialState.COMPLETE
    assert study.user_attrs["init_weights"] == str(path) and len(study.user_attrs["init_weights_sha256"]) == 64
    # a study is resumed with the same start only
    assert main([*base, "--study-name", "init"]) == 2


def test_init_weights_of_another_architecture_is_a_one_line_error(tmp_path, capsys):
    path, _ = tiny_policy_file(tmp_path, encoder_dim=16)
    config = write_config(tmp_path, SMALL)
    base = ["tune", "--config", str(config), "--env", TOY, "--study-name", "m", "--storage",
            f"sqlite:///{tmp_path}/m.db", "--tune-algo", "--timesteps", "100", "--n-trials", "1"]  # fmt: skip
    assert main([*base, "--init-weights", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "--init-weights: " in err and "a TD3 policy of another architecture than the GraphPolicy to train" in err
    assert "in the file, [8, 8] in the policy" in err  # the first tensor whose shape differs
    assert main([*base, "--init-weights", str(tmp_path / "none.safetensors")]) == 2
    assert "--init-weights: file not found" in capsys.readouterr().err
    (tmp_path / "junk.safetensors").write_bytes(b"not a file")
    assert main([*base, "--init-weights", str(tmp_path / "junk.safetensors")]) == 2
    assert "not a .safetensors policy file" in capsys.readouterr().err
    assert not (tmp_path / "m.db").exists()  # refused before any study was made


# ---------------------------------------------------------------- every algorithm
def test_every_registered_algorithm_can_be_tuned(tmp_path):
    parser = argparse.ArgumentParser()
    commands.add_arguments(parser)
    (algo,) = [action for action in parser._actions if action.dest == "algo"]
    assert list(algo.choices) == list(ALGORITHMS)
    # an on-policy one end to end (test_tuning.py runs SAC)
    entry = {"n_timesteps": 128, "policy": "GraphPolicy", "n_steps": 128, "batch_size": 16, "n_epochs": 1,
             "policy_kwargs": "dict(encoder_dim=8, conv_dims=[8])"}  # fmt: skip
    config = tmp_path / "ppo.yml"
    config.write_text(yaml.safe_dump({TOY: entry}))
    storage = f"sqlite:///{tmp_path}/ppo.db"
    assert main(["tune", "--config", str(config), "--env", TOY, "--study-name", "ppo", "--storage", storage,
                 "--algo", "ppo", "--tune-algo", "--timesteps", "128", "--eval-episodes", "1", "--n-trials", "1",
                 "--objective", "pareto"]) == 0  # fmt: skip
    (trial,) = optuna.load_study(study_name="ppo", storage=storage).trials
    assert trial.state == TrialState.COMPLETE and len(trial.values) == 3
    assert set(trial.params) == {f"algo.{key}" for key in ALGORITHMS["ppo"].tune_space}
    assert np.isfinite(trial.user_attrs[DELAY])
