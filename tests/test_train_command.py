"""`sb3-graph train` and rl-zoo3 on zoo_configs/td3.yml: tiny runs that write models which load and act."""

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml
from stable_baselines3.common.env_util import make_vec_env

import envs  # noqa: F401 - registers the environments
from sb3_graph import TD3
from sb3_graph.callbacks import LinearScheduleCallback
from sb3_graph.cli import main

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "zoo_configs" / "td3.yml"
ENV_ID = "CoopIntersection4Way-v0"
TINY = ["--hyperparams", "learning_starts:64", "batch_size:16", "buffer_size:1000"]
SHORT_EPISODES = ["--env-kwargs", json.dumps({"config": {"duration": 8.0}})]


def train(out, *extra):
    return main(
        ["train", "--config", str(CONFIG), "--env", ENV_ID, "--out", str(out), "--eval-freq", "100",
         "--eval-episodes", "1", "--checkpoint-freq", "100", "--no-progress", *extra]
    )


def acts(model_path, algorithm=TD3):
    model = algorithm.load(model_path)
    env = gym.make(ENV_ID)
    obs, _ = env.reset(seed=3)
    action, _ = model.predict(obs, deterministic=True)
    n = int(obs["node_mask"].sum())
    assert n > 0 and np.isfinite(action).all() and np.all(np.abs(action) <= 1)
    assert np.all(action[n:] == 0)  # padded slots stay 0
    env.step(action)
    return model


def test_tiny_run_writes_loadable_models_and_resumes(tmp_path):
    out = tmp_path / "run"
    assert train(out, "--n-timesteps", "200", *TINY, *SHORT_EPISODES) == 0
    for name in ("config.yml", "run.json", "best_model.zip", "final_model.zip", "evaluations.npz"):
        assert (out / name).is_file(), name
    assert acts(out / "final_model.zip").num_timesteps == 200
    record = json.loads((out / "run.json").read_text())
    assert record["num_timesteps"] == 200 and record["env"] == ENV_ID and "torch" in record["versions"]
    assert (out / "checkpoints" / "model_replay_buffer_200_steps.pkl").is_file()
    assert (out / "checkpoints" / "model_100_steps.zip").is_file()  # periodic checkpoint
    assert any((out / "tb").rglob("events.out.tfevents.*"))  # TensorBoard is installed here: its logs

    # --resume continues the step count from the last checkpoint, with its replay buffer
    assert train(out, "--resume", "--n-timesteps", "300") == 0
    model = acts(out / "final_model.zip")
    assert model.num_timesteps == 300
    record = json.loads((out / "run.json").read_text())
    assert [s["steps_until"] for s in record["sessions"]] == [200, 300]
    buffers = sorted((out / "checkpoints").glob("model_replay_buffer_*_steps.pkl"))
    assert [b.name for b in buffers] == ["model_replay_buffer_300_steps.pkl"]  # only the newest kept
    model.load_replay_buffer(buffers[0])
    assert model.replay_buffer.size() == 300  # 200 from the first session, 100 from the resumed one


def test_existing_run_folder_is_refused_and_untouched(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert train(out, "--n-timesteps", "10") == 2
    assert "already holds files" in capsys.readouterr().err
    assert (out / "keep.txt").read_text() == "mine" and len(list(out.iterdir())) == 1


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--env", "NoSuchEnv-v0"], "no entry for env 'NoSuchEnv-v0'"),
        (["--hyperparams", "batch_size"], "expected KEY:VALUE"),
        (["--hyperparams", "noise_type:pink"], "noise_type must be one of"),
        (["--checkpoint-freq", "0"], "--checkpoint-freq must be at least 1, got 0"),
        (["--label-jobs", "0"], "--label-jobs must be at least 1, got 0"),
        (["--label-address", "tcp://127.0.0.1:1"], "--label-address needs --label-executor dask or ray"),
        (["--label-jobs", "2"], "the entry has no pretrain_from"),
    ],
)
def test_user_errors_are_one_line(tmp_path, capsys, extra, message):
    assert train(tmp_path / "run", "--n-timesteps", "10", *extra) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_periodic_checkpoint_holds_every_transition(tmp_path):
    from sb3_graph.commands.train import _make_checkpoint_callback

    env = make_vec_env(ENV_ID, n_envs=1, seed=0, env_kwargs={"config": {"duration": 8.0}})
    model = TD3("GraphPolicy", env, learning_starts=1000, buffer_size=1000, seed=0)
    model.learn(120, callback=_make_checkpoint_callback(50, tmp_path))
    assert sorted(p.name for p in tmp_path.glob("model_*_steps.zip")) == ["model_100_steps.zip", "model_50_steps.zip"]
    model.load_replay_buffer(tmp_path / "model_replay_buffer_100_steps.pkl")
    assert model.replay_buffer.size() == 100  # the transition of step 100 is in


def test_curriculum_raises_spawn_probability():
    env = make_vec_env(ENV_ID, n_envs=1, seed=0, env_kwargs={"config": {"duration": 8.0}})
    model = TD3("GraphPolicy", env, learning_starts=1000, buffer_size=1000, seed=0)
    callback = LinearScheduleCallback("set_spawn_probability", start=0.01, end=0.05, end_fraction=0.5,
                                      update_every=10)
    model.learn(100, callback=callback)
    assert env.get_attr("config")[0]["spawn_probability"] == pytest.approx(0.05)
    assert callback.value == pytest.approx(0.05)
    model.learn(100, callback=LinearScheduleCallback("set_spawn_probability", 0.01, 0.05, update_every=1000))
    assert env.get_attr("config")[0]["spawn_probability"] == pytest.approx(0.01)  # applied at training start


def test_rl_zoo3_runs_the_same_experiment_file(tmp_path):
    pytest.importorskip("rl_zoo3")
    command = [
        sys.executable, "-m", "rl_zoo3.train", "--algo", "td3", "--env", ENV_ID, "--gym-packages", "envs",
        "-conf", str(CONFIG), "-n", "120", "-params", "learning_starts:64", "batch_size:16", "buffer_size:1000",
        "--eval-freq", "-1", "-f", str(tmp_path), "--seed", "1", "--env-kwargs", "config:{'duration':8.0}",
        "--num-threads", "1",
    ]
    result = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    saved = list(tmp_path.glob(f"td3/{ENV_ID}_*/{ENV_ID}.zip"))
    assert len(saved) == 1
    model = acts(saved[0])
    assert type(model.replay_buffer).__name__ == "GraphReplayBuffer" or model.replay_buffer is None


def test_sigterm_saves_a_checkpoint_that_resumes(tmp_path):
    out = tmp_path / "run"
    command = [
        sys.executable, "-m", "sb3_graph.cli", "train", "--config", str(CONFIG), "--env", ENV_ID, "--out", str(out),
        "--n-timesteps", "100000", "--eval-freq", "100000", "--checkpoint-freq", "100000", "--no-progress", *TINY,
        *SHORT_EPISODES,
    ]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    record = out / "run.json"
    for _ in range(600):  # the record is written before training starts
        if record.is_file():
            break
        time.sleep(0.1)
    time.sleep(3.0)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130 and "continue with --resume" in err
    steps = json.loads(record.read_text())["num_timesteps"]
    assert 0 < steps < 100000
    assert (out / "checkpoints" / f"model_{steps}_steps.zip").is_file()
    assert (out / "checkpoints" / f"model_replay_buffer_{steps}_steps.pkl").is_file()
    assert train(out, "--resume", "--n-timesteps", str(steps + 20)) == 0
    assert TD3.load(out / "final_model.zip").num_timesteps == steps + 20


def test_ppo_run_from_its_zoo_config_resumes_as_ppo(tmp_path, capsys):
    import sb3_graph

    out = tmp_path / "ppo"
    config = ROOT / "zoo_configs" / "ppo.yml"
    tiny = ["--hyperparams", "n_envs:2", "n_steps:32", "batch_size:32", "n_epochs:1"]
    common = ["train", "--config", str(config), "--env", ENV_ID, "--out", str(out), "--eval-freq", "64",
              "--eval-episodes", "1", "--checkpoint-freq", "64", "--no-progress"]
    assert main([*common, "--algo", "ppo", "--n-timesteps", "128", *tiny, *SHORT_EPISODES]) == 0
    model = sb3_graph.PPO.load(out / "final_model.zip")
    assert model.num_timesteps == 128 and type(model.policy).__name__ == "GraphActorCriticPolicy"
    assert json.loads((out / "run.json").read_text())["algo"] == "ppo"
    assert not list((out / "checkpoints").glob("model_replay_buffer_*"))  # on-policy: no buffer to keep
    assert main([*common, "--resume", "--n-timesteps", "192"]) == 0  # the run's own algorithm
    assert sb3_graph.PPO.load(out / "final_model.zip").num_timesteps == 192
    assert main([*common, "--resume", "--algo", "sac"]) == 2
    assert "is a ppo run" in capsys.readouterr().err


@pytest.mark.parametrize("algo", ["sac", "tqc"])
def test_off_policy_zoo_configs_train(tmp_path, algo):
    import sb3_graph

    out = tmp_path / algo
    config = ROOT / "zoo_configs" / f"{algo}.yml"
    assert main(["train", "--algo", algo, "--config", str(config), "--env", ENV_ID, "--out", str(out),
                 "--n-timesteps", "100", "--eval-freq", "100", "--eval-episodes", "1", "--no-progress",
                 *TINY, *SHORT_EPISODES]) == 0
    cls = {"sac": sb3_graph.SAC, "tqc": sb3_graph.TQC}[algo]
    model = cls.load(out / "final_model.zip")
    assert type(model.replay_buffer).__name__ == "GraphReplayBuffer" or model.replay_buffer is None
    acts(out / "final_model.zip", cls)


# PPO runs by default (rl-zoo3 builds stock PPO with SB3's padded DictRolloutBuffer); SAC takes
# the path of the TD3 test above, so it is left to the slow run.
@pytest.mark.parametrize("algo", [pytest.param("sac", marks=pytest.mark.slow), "ppo"])
def test_rl_zoo3_runs_the_other_experiment_files(tmp_path, algo):
    pytest.importorskip("rl_zoo3")
    params = ["learning_starts:64", "batch_size:16", "buffer_size:1000"] if algo == "sac" else [
        "n_envs:1", "n_steps:64", "batch_size:32", "n_epochs:1"]
    command = [
        sys.executable, "-m", "rl_zoo3.train", "--algo", algo, "--env", ENV_ID, "--gym-packages", "envs",
        "-conf", str(ROOT / "zoo_configs" / f"{algo}.yml"), "-n", "128", "-params", *params,
        "--eval-freq", "-1", "-f", str(tmp_path), "--seed", "1", "--env-kwargs", "config:{'duration':8.0}",
        "--num-threads", "1",
    ]
    result = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    saved = list(tmp_path.glob(f"{algo}/{ENV_ID}_*/{ENV_ID}.zip"))
    assert len(saved) == 1
def test_env_kwargs_merge_into_the_config_block(tmp_path):
    """--env-kwargs adds to the entry's env_kwargs['config'] instead of replacing it."""
    import argparse

    from sb3_graph.commands.train import _entry_from_file

    args = argparse.Namespace(config=str(CONFIG), env=ENV_ID, hyperparams=[], n_timesteps=None,
                              env_kwargs={"config": {"max_vehicles": 16}, "render_mode": None})  # fmt: skip
    entry = _entry_from_file(args)
    assert entry["env_kwargs"] == {
        "config": {
            "reward": "paper", "spawn_queue": 0, "duration": 60.0, "spawn_probability": 0.05, "max_vehicles": 16,
        },
        "render_mode": None,
    }  # fmt: skip
    assert entry["n_timesteps"] == 200000 and isinstance(entry["n_timesteps"], int)


def test_failed_run_leaves_nothing_and_reruns_once_the_file_is_fixed(tmp_path, capsys):
    entry = yaml.safe_load(CONFIG.read_text())[ENV_ID]
    entry["callback"][0]["sb3_graph.callbacks.LinearScheduleCallback"]["method"] = "set_spawn_probabilty"  # typo
    config = tmp_path / "exp.yml"
    config.write_text(yaml.safe_dump({ENV_ID: entry}))
    out = tmp_path / "run"
    args = ["train", "--config", str(config), "--env", ENV_ID, "--out", str(out), "--eval-freq", "100",
            "--eval-episodes", "1", "--n-timesteps", "20", "--no-progress", *TINY, *SHORT_EPISODES]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "learning_starts 64" in err  # 20 steps train nothing: warned before the run
    errors = [line for line in err.splitlines() if ": warning: " not in line]
    assert len(errors) == 1 and "set_spawn_probabilty" in errors[0] and "run the command again" in errors[0]
    assert not out.exists()
    # An older failed run left a folder with its config but no checkpoint: --resume reads the file again.
    out.mkdir()
    (out / "config.yml").write_text(yaml.safe_dump(entry))
    entry["callback"][0]["sb3_graph.callbacks.LinearScheduleCallback"]["method"] = "set_spawn_probability"
    config.write_text(yaml.safe_dump({ENV_ID: entry}))
    assert main([*args, "--resume"]) == 0, capsys.readouterr().err
    stored = yaml.safe_load((out / "config.yml").read_text())
    assert stored["callback"][0]["sb3_graph.callbacks.LinearScheduleCallback"]["method"] == "set_spawn_probability"
    shutil.rmtree(out)
    assert main(args) == 0  # the same command as the first time, now that the file is fixed


def test_run_record_holds_no_user_folder(tmp_path, monkeypatch):
    from sb3_graph.commands.train import portable_command, portable_path

    monkeypatch.chdir(tmp_path)
    argv = ["/home/me/.venv/bin/sb3-graph", "train", "--config", str(tmp_path / "zoo" / "td3.yml"), "--out=/srv/x"]
    assert portable_command(argv) == "sb3-graph train --config zoo/td3.yml --out=/srv/x"  # as typed
    assert portable_path(str(Path.home() / "runs" / "a")) == "~/runs/a"
    assert portable_path("relative/path") == "relative/path"


def test_seeds_train_one_run_per_seed_and_never_overwrite(tmp_path, capsys):
    out = tmp_path / "seeds"
    tiny = ["--n-timesteps", "80", *TINY, *SHORT_EPISODES]
    assert train(out, "--seeds", "0", "1", *tiny) == 0
    for seed in (0, 1):
        record = json.loads((out / f"seed_{seed}" / "run.json").read_text())
        assert record["seed"] == seed and record["num_timesteps"] == 80
        assert (out / f"seed_{seed}" / "final_model.zip").is_file()
    stamp = (out / "seed_0" / "run.json").read_text()
    capsys.readouterr()
    # an existing seed folder is never overwritten: checked before any run starts
    assert train(out, "--seeds", "2", "1", *tiny) == 2
    assert "seed_1 already hold files" in capsys.readouterr().err and not (out / "seed_2").exists()
    assert train(out, "--seeds", "0", "--seed", "3", *tiny) == 2
    assert "--seed and --seeds exclude each other" in capsys.readouterr().err
    assert train(out, "--seeds", "4", "4", *tiny) == 2
    assert "each seed once" in capsys.readouterr().err
    # --resume continues the runs that exist and starts the missing ones
    assert train(out, "--seeds", "0", "2", "--resume", "--n-timesteps", "80") == 0
    assert (out / "seed_0" / "run.json").read_text() != stamp  # its record gained a session
    assert json.loads((out / "seed_2" / "run.json").read_text())["seed"] == 2


@pytest.mark.parametrize(
    "name",
    ["td3_fair.yml", "td3_tune.yml", "td3_priority.yml", "td3_advice.yml", "td3_glide_clone.yml", "td3_mixed.yml"],
)
def test_intersection_zoo_entries_read_and_build(name):
    # The retraining, study and cloning entries are read without eval and make the environment they name.
    from sb3_graph.files.experiment_files import build_algorithm_kwargs, build_callbacks, read_experiment

    entry = read_experiment(ROOT / "zoo_configs" / name, "CoopIntersection4Way-v0")
    env = gym.make("CoopIntersection4Way-v0", **entry["env_kwargs"])
    assert env.unwrapped.config["spawn_probability_range"] == [0.01, 0.07]
    assert build_algorithm_kwargs(entry, action_dim=1)["learning_rate"] > 0
    assert build_callbacks(entry)
    if name == "td3_mixed.yml":  # mixed traffic: a share per episode, and the vertices say who is human
        assert env.unwrapped.config["human_share"] == [0.0, 0.75]
        assert "human" in env.unwrapped.config["vertex_features"]
    env.close()


def test_short_run_warns_names_its_settings_and_records_the_typed_command(tmp_path, capsys, monkeypatch):
    import importlib.util

    monkeypatch.chdir(tmp_path)
    find_spec = importlib.util.find_spec  # a base install: no TensorBoard

    def hidden(name, *args):
        return None if name == "tensorboard" else find_spec(name, *args)

    monkeypatch.setattr(importlib.util, "find_spec", hidden)
    args = ["--n-timesteps", "120", "--hyperparams", "learning_starts:500", "batch_size:16", "buffer_size:1000",
            *SHORT_EPISODES]  # fmt: skip
    assert train("short", *args) == 0
    captured = capsys.readouterr()
    assert "warning: n_timesteps 120 <= learning_starts 500: no gradient step" in captured.err
    assert "note: TensorBoard is not installed, so this run writes no tb/ logs" in captured.err
    assert not (tmp_path / "short" / "tb").exists()
    assert "--eval-freq" not in captured.err  # a validation runs at step 100
    assert "Eval num_timesteps=100" in captured.out  # the validation score on the console
    record = json.loads((tmp_path / "short" / "run.json").read_text())
    assert " --out short " in record["command"] + " " and record["command"].startswith("sb3-graph train ")
    results = np.load(tmp_path / "short" / "evaluations.npz")["results"]  # one validation: (1, episodes)
    assert results.shape == (1, 1) and record["best_mean_reward"] == pytest.approx(float(results.mean(axis=1).max()))
    # what the run wrote, and what to do next (export, then the domain's evaluate; no TensorBoard line)
    lines = captured.out.splitlines()
    summary = lines[[k for k, line in enumerate(lines) if line.startswith("sb3-graph train: 120 steps")][0] + 1 :]
    checkpoints = sum(1 for _ in (tmp_path / "short" / "checkpoints").iterdir())
    assert summary[0] == (
        f"  wrote: best_model.zip, final_model.zip, evaluations.npz, checkpoints/ ({checkpoints} files), config.yml, "
        "run.json"
    )
    assert summary[2].startswith("    sb3-graph export short/best_model.zip short/best_model.safetensors")
    assert summary[3].startswith(f"    sb3-graph evaluate --env {ENV_ID} --planner mine=short/best_model.safetensors")
    assert "--resume" in summary[4] and not any("tensorboard" in line for line in summary)


def test_short_run_warnings_name_learning_starts_and_eval_freq():
    from sb3_graph.commands.train import short_run_warnings

    both = short_run_warnings(2000, 0, 2000, 5000)
    assert len(both) == 2 and "learning_starts 2000" in both[0] and "--eval-freq 5000" in both[1]
    assert short_run_warnings(20_000, 0, 2000, 5000) == []
    assert short_run_warnings(2000, 0, None, 1000) == []  # on-policy: no learning_starts
    assert len(short_run_warnings(6000, 5000, 100, 5000)) == 0  # resumed past the first validation
