"""rl-zoo3 style experiment entries: reading, checking, and turning them into SB3 objects."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.noise import NormalActionNoise

from sb3_graph.callbacks import InfoLoggerCallback, LinearScheduleCallback
from sb3_graph.files.experiment_files import (
    ExperimentError,
    build_algorithm_kwargs,
    build_callbacks,
    read_experiment,
    resolve_object,
)


def write(tmp_path, text):
    path = tmp_path / "exp.yml"
    path.write_text(text)
    return path


def test_read_entry_and_errors(tmp_path):
    path = write(tmp_path, "Env-v0:\n  n_timesteps: !!float 1e3\n  batch_size: 32\n")
    assert read_experiment(path, "Env-v0") == {"n_timesteps": 1000.0, "batch_size": 32}
    with pytest.raises(ExperimentError, match="no entry for env 'Other-v0'; entries: Env-v0"):
        read_experiment(path, "Other-v0")
    with pytest.raises(ExperimentError, match="does not exist"):
        read_experiment(tmp_path / "missing.yml", "Env-v0")
    with pytest.raises(ExperimentError, match="n_timesteps is required"):
        read_experiment(write(tmp_path, "Env-v0:\n  batch_size: 32\n"), "Env-v0")
    with pytest.raises(ExperimentError, match="normalize"):
        read_experiment(write(tmp_path, "Env-v0:\n  n_timesteps: 10\n  normalize: true\n"), "Env-v0")
    with pytest.raises(ExperimentError, match="not valid YAML"):
        read_experiment(write(tmp_path, "Env-v0: [unclosed\n"), "Env-v0")


def test_algorithm_kwargs_follow_rl_zoo3_conventions():
    entry = {
        "n_timesteps": 10,
        "n_envs": 2,
        "policy": "GraphPolicy",
        "env_kwargs": {"a": 1},
        "policy_kwargs": "dict(net_arch=[8], activation_fn=nn.Tanh)",
        "replay_buffer_class": "importlib.import_module('stable_baselines3.common.buffers').DictReplayBuffer",
        "learning_rate": "lin_0.001",
        "train_freq": [1, "episode"],
        "noise_type": "normal",
        "noise_std": 0.2,
        "gamma": 0.9,
    }
    kwargs = build_algorithm_kwargs(entry, action_dim=3)
    assert set(kwargs) == {
        "policy_kwargs", "replay_buffer_class", "learning_rate", "train_freq", "action_noise", "gamma"
    }
    assert kwargs["policy_kwargs"] == {"net_arch": [8], "activation_fn": th.nn.Tanh}
    assert kwargs["replay_buffer_class"].__name__ == "DictReplayBuffer"
    assert kwargs["learning_rate"](1.0) == pytest.approx(0.001)
    assert kwargs["learning_rate"](0.0) == pytest.approx(0.0)
    assert kwargs["train_freq"] == (1, "episode")
    assert isinstance(kwargs["action_noise"], NormalActionNoise)
    assert np.allclose(kwargs["action_noise"]._sigma, 0.2 * np.ones(3))


def test_bad_values_name_the_field():
    with pytest.raises(ExperimentError, match="noise_type must be one of"):
        build_algorithm_kwargs({"noise_type": "pink"}, 2)
    with pytest.raises(ExperimentError, match="learning_rate"):
        build_algorithm_kwargs({"learning_rate": "exp_0.1"}, 2)
    with pytest.raises(ExperimentError, match="policy_kwargs: cannot evaluate"):
        build_algorithm_kwargs({"policy_kwargs": "dict(a=open('x'))"}, 2)
    with pytest.raises(ExperimentError, match="cannot import 'sb3_graph.NoSuchThing'"):
        resolve_object("sb3_graph.NoSuchThing", "policy")


def test_callbacks_from_entry():
    callbacks = build_callbacks(
        {
            "callback": [
                {"sb3_graph.callbacks.LinearScheduleCallback": {"method": "set_p", "start": 0.0, "end": 1.0}},
                "sb3_graph.callbacks.InfoLoggerCallback",
            ]
        }
    )
    assert isinstance(callbacks[0], LinearScheduleCallback) and callbacks[0].method == "set_p"
    assert isinstance(callbacks[1], InfoLoggerCallback)
    with pytest.raises(ExperimentError, match="end_fraction"):
        build_callbacks({"callback": [{"sb3_graph.callbacks.LinearScheduleCallback": {
            "method": "m", "start": 0, "end": 1, "end_fraction": 2}}]})


def test_linear_schedule_values():
    callback = LinearScheduleCallback("set_p", start=0.01, end=0.05, end_fraction=0.5, total_timesteps=1000)
    assert callback.value_at(0) == pytest.approx(0.01)
    assert callback.value_at(250) == pytest.approx(0.03)
    assert callback.value_at(500) == pytest.approx(0.05)
    assert callback.value_at(900) == pytest.approx(0.05)


def test_info_logger_records_means_of_terms_and_event_counts():
    from stable_baselines3.common.logger import Logger

    callback = InfoLoggerCallback(keys=["reward_terms", "crossed", "num_vehicles"])
    logger = Logger(folder=None, output_formats=[])

    class Model:
        pass

    model = Model()
    model.logger = logger
    callback.model = model
    steps = [
        {"reward_terms": {"velocity": 1.0}, "crossed": np.array([3, 4]), "num_vehicles": 4},
        {"reward_terms": {"velocity": 0.0}, "crossed": np.array([], dtype=int), "num_vehicles": float("nan")},
    ]
    for info in steps:
        callback.locals = {"infos": [info]}
        callback._on_step()
    assert logger.name_to_value["info/reward_terms/velocity"] == pytest.approx(0.5)
    assert logger.name_to_value["info/crossed_count"] == pytest.approx(1.0)
    assert logger.name_to_value["info/num_vehicles"] == pytest.approx(4.0)  # NaN skipped


def test_info_logger_takes_0d_arrays_and_skips_strings():
    from stable_baselines3.common.logger import Logger

    callback = InfoLoggerCallback(keys=["speed", "label", "flag", "nothing", "terms"])
    logger = Logger(folder=None, output_formats=[])

    class Model:
        pass

    model = Model()
    model.logger = logger
    callback.model = model
    steps = [
        {"speed": np.array(2.0), "label": "left", "flag": True, "nothing": None, "terms": {"a": np.float32(1.0)}},
        {"speed": np.array(4.0), "label": np.array("right"), "flag": np.bool_(False), "terms": {"a": "n/a"}},
    ]
    for info in steps:
        callback.locals = {"infos": [info]}
        callback._on_step()
    assert logger.name_to_value["info/speed"] == pytest.approx(3.0)  # 0-d arrays are numbers
    assert logger.name_to_value["info/flag"] == pytest.approx(0.5)
    assert logger.name_to_value["info/terms/a"] == pytest.approx(1.0)
    assert not any("label" in key or "nothing" in key for key in logger.name_to_value)


@pytest.mark.parametrize("fixed", [True, False])
def test_validations_see_the_same_episodes(fixed, tmp_path):
    """A policy that does not change scores the same at every validation of FixedEpisodesEvalCallback; under
    SB3's EvalCallback (the oracle that the episodes do differ) the scores drift with the episodes."""
    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_graph import TD3
    from sb3_graph.callbacks import FixedEpisodesEvalCallback
    from sb3_graph.toy_envs import MaxNeighbourEnv

    eval_env = make_vec_env(MaxNeighbourEnv, n_envs=1, seed=7)
    common = dict(eval_freq=40, n_eval_episodes=3, deterministic=True, verbose=0, log_path=str(tmp_path))
    callback = FixedEpisodesEvalCallback(eval_env, seed=7, **common) if fixed else EvalCallback(eval_env, **common)
    model = TD3("GraphPolicy", MaxNeighbourEnv(), learning_starts=10_000, seed=0)  # no update: a fixed policy
    model.learn(160, callback=callback)
    rewards = callback.evaluations_results
    assert len(rewards) == 4
    same = all(np.array_equal(rewards[0], r) for r in rewards[1:])
    assert same == fixed, rewards
