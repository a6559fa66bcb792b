"""Bad input to every command: a one-line error naming the field, flag, file or value, a non-zero
exit, no traceback, and no ``--out`` left behind (table-driven)."""

from __future__ import annotations

import gzip
import io
import json
import os
import zipfile
from pathlib import Path

import pandas as pd
import pytest
import torch as th
import yaml

from envs.ind.format import recording_file
from envs.ind.synthetic import SyntheticSite, default_vehicles, make_recording, write_recording
from sb3_graph.cli import main

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "zoo_configs" / "td3.yml"
ENV_ID = "CoopIntersection4Way-v0"
FAST_EVAL = ["--scenarios", "1", "--duration", "2", "--jobs", "1", "--no-progress"]
SITE = SyntheticSite(centre=(-75.0, 140.0), rotation_deg=17.0, location_id=1)


def _config(folder: Path, name: str, **changes) -> Path:
    entry = yaml.safe_load(CONFIG.read_text())[ENV_ID]
    entry.update(changes)
    path = folder / f"{name}.yml"
    path.write_text(yaml.safe_dump({ENV_ID: entry}))
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3 import TD3 as SB3TD3

    import envs  # noqa: F401
    from sb3_graph import TD3, GraphPolicy
    from sb3_graph.files.policy_files import save_policy

    th.set_num_threads(1)
    f = tmp_path_factory.mktemp("inputs")
    paths = {"dir": f}
    (f / "notzip.zip").write_bytes(b"this is not a zip file")
    paths["notzip"] = f / "notzip.zip"
    with zipfile.ZipFile(f / "emptyzip.zip", "w"):
        pass
    paths["emptyzip"] = f / "emptyzip.zip"
    with zipfile.ZipFile(f / "nonjson.zip", "w") as archive:
        archive.writestr("data", "{not json")
        archive.writestr("policy.pth", b"")
    paths["nonjson"] = f / "nonjson.zip"
    SB3TD3("MlpPolicy", "Pendulum-v1", buffer_size=10).save(f / "mlp.zip")
    paths["mlp"] = f / "mlp.zip"
    PPO("MlpPolicy", "CartPole-v1", n_steps=16, batch_size=16).save(f / "ppo.zip")
    paths["ppo"] = f / "ppo.zip"
    small = TD3(GraphPolicy, gym.make(ENV_ID, config={"max_vehicles": 8}), buffer_size=10, seed=0)
    small.save(f / "small.zip")
    paths["small"] = f / "small.zip"
    save_policy(small.policy, f / "small.safetensors", "TD3")
    paths["small_st"] = f / "small.safetensors"
    (f / "junk.safetensors").write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}garbage")
    paths["junk_st"] = f / "junk.safetensors"
    (f / "afile").write_text("a file, not a folder")
    paths["afile"] = f / "afile"
    for name, changes in {
        "lin_abc": {"learning_rate": "lin_abc"},
        "typo": {"learnig_rate": 0.001},
        "gamma_high": {"gamma": "high"},
        "n_envs_0": {"n_envs": 0},
        "negative_steps": {"n_timesteps": -5},
        "env_kwargs_list": {"env_kwargs": [1]},
        "narrow": {"policy_kwargs": "dict(encoder_dim=16, conv_dims=(16,))"},
    }.items():
        paths[name] = _config(f, name, **changes)
    valid = f / "ind"
    write_recording(valid, make_recording(7, default_vehicles(seed=7, num=8), SITE))
    texts = {kind: recording_file(valid, 7, kind).read_text() for kind in ("tracks", "tracksMeta", "recordingMeta")}
    for name, change in {
        "ind_gz": lambda t: gzip.compress(t["tracks"].encode()),
        "ind_truncated": lambda t: "\n".join(t["tracks"].splitlines()[: len(t["tracks"].splitlines()) // 2]).encode(),
        "ind_cut_row": lambda t: _cut_row(t["tracks"]),
        "ind_header_only": lambda t: t["tracks"].splitlines()[0].encode() + b"\n",
    }.items():
        folder = f / name
        for kind, text in texts.items():
            recording_file(folder.mkdir(exist_ok=True) or folder, 7, kind).write_text(text)
        recording_file(folder, 7, "tracks").write_bytes(change(texts))
        paths[name] = folder
    words = f / "ind_words"
    for kind, text in texts.items():
        recording_file(words.mkdir(exist_ok=True) or words, 7, kind).write_text(text)
    frame = pd.read_csv(recording_file(words, 7, "recordingMeta"), dtype=str)
    frame.loc[0, "frameRate"] = "fast"
    frame.to_csv(recording_file(words, 7, "recordingMeta"), index=False)
    paths["ind_words"] = words
    paths["ind"] = valid
    paths.update(_hostile_inputs(f, small, texts))
    return paths


def _changed_zip(source: Path, target: Path, kwargs: dict | None = None, state: dict | None = None) -> Path:
    """A copy of an SB3 zip with other ``policy_kwargs`` (plain JSON parts) or other weights."""
    with zipfile.ZipFile(source) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    if kwargs is not None:
        data = json.loads(entries["data"])
        data["policy_kwargs"].update(kwargs)
        entries["data"] = json.dumps(data).encode()
    if state is not None:
        buffer = io.BytesIO()
        th.save(state, buffer)
        entries["policy.pth"] = buffer.getvalue()
    with zipfile.ZipFile(target, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)
    return target


def _garbage_lzma_zip(source: Path, target: Path) -> Path:
    """The zip's entries compressed with LZMA, the compressed bytes of ``data`` then overwritten."""
    with zipfile.ZipFile(source) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_LZMA) as archive:
        for name, content in entries.items():
            archive.writestr(name, content)
    with zipfile.ZipFile(target) as archive:
        info = archive.getinfo("data")
    raw = bytearray(target.read_bytes())
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    # keep LZMA's 4-byte header and 5 property bytes; the stream after them is garbage
    raw[start + 9 : start + info.compress_size] = (b"\x5a\xa5" * info.compress_size)[: info.compress_size - 9]
    target.write_bytes(bytes(raw))
    return target


def _nested(depth: int) -> list:
    value: list = []
    for _ in range(depth):
        value = [value]
    return value


def _scenario(folder: Path, name: str, **changes) -> Path:
    from envs.simulation.traffic import generate_scenario

    folder.mkdir(exist_ok=True)
    data = generate_scenario("4way", 5.0, 0).to_dict()
    for key, value in changes.items():
        if key == "width":
            data["vehicles"][0]["width"] = value
        else:
            data[key] = value
    (folder / f"{name}.json").write_text(json.dumps(data))
    return folder


def _hostile_inputs(f: Path, small, texts: dict[str, str]) -> dict[str, Path]:
    """Inputs of the second hostile-input round (docs/security.md)."""
    from safetensors.torch import save_file

    from sb3_graph.files.policy_files import METADATA_KEY, describe_policy

    paths: dict[str, Path] = {}
    for name, kwargs in {
        "zip_pooling_null": {"pooling": None},
        "zip_encoder_huge": {"encoder_dim": 1e12},
        "zip_activation_module": {"activation_fn": "<class 'torch.nn.modules.module.Module'>"},
        "zip_kwargs_deep": {"deep": _nested(500)},
    }.items():
        paths[name] = _changed_zip(f / "small.zip", f / f"{name}.zip", kwargs=kwargs)
    state = {key: value.clone() for key, value in small.policy.state_dict().items()}
    first = next(key for key, value in state.items() if value.is_floating_point())
    state[first].view(-1)[0] = float("nan")
    paths["zip_nan"] = _changed_zip(f / "small.zip", f / "zip_nan.zip", state=state)
    paths["zip_lzma"] = _garbage_lzma_zip(f / "small.zip", f / "zip_lzma.zip")
    description = describe_policy(small.policy, "TD3").to_json()
    save_file(state, str(f / "nan.safetensors"), metadata={METADATA_KEY: description})
    paths["st_nan"] = f / "nan.safetensors"
    good = {key: value.contiguous() for key, value in small.policy.state_dict().items()}
    deep = "[" * 30_000 + "]" * 30_000
    save_file(good, str(f / "deep.safetensors"), metadata={METADATA_KEY: deep})
    paths["st_deep"] = f / "deep.safetensors"
    fused = json.loads(description)
    fused["policy_kwargs"]["optimizer_kwargs"] = {"fused": True, "foreach": True}
    save_file(good, str(f / "fused.safetensors"), metadata={METADATA_KEY: json.dumps(fused)})
    paths["st_fused"] = f / "fused.safetensors"
    # experiment files
    for name, changes in {
        "pooling_null": {"policy_kwargs": "dict(pooling=None)"},
        "encoder_huge": {"policy_kwargs": "dict(encoder_dim=1e12)"},
        "activation_module": {"policy_kwargs": "dict(activation_fn=nn.Module)"},
        "activation_lazy": {"policy_kwargs": "dict(activation_fn=torch.nn.modules.lazy.LazyModuleMixin)"},
        "activation_error": {"policy_kwargs": "dict(activation_fn=sb3_graph.commands.UserError)"},
        "fused_foreach": {"policy_kwargs": "dict(optimizer_kwargs=dict(fused=True, foreach=True))"},
        "too_large": {"policy_kwargs": f"dict(encoder_dim=4096, conv_dims={[4096] * 20})"},
        "buffer_huge": {"buffer_size": 10**12},
        "n_envs_huge": {"n_envs": 100_000},
        "tensorboard_path": {"tensorboard_log": "/tmp/elsewhere"},
    }.items():
        paths[name] = _config(f, name, **changes)
    entry = yaml.safe_load(CONFIG.read_text())[ENV_ID]
    (f / "deep.yml").write_text(yaml.safe_dump({ENV_ID: entry}) + "  deep: " + "[" * 20_000 + "]" * 20_000 + "\n")
    paths["yaml_deep"] = f / "deep.yml"
    laughs = ["  lol0: &a0 [x, x, x, x, x, x, x, x, x]"]
    laughs += [f"  lol{k}: &a{k} [{', '.join([f'*a{k - 1}'] * 9)}]" for k in range(1, 9)]
    (f / "laughs.yml").write_text(yaml.safe_dump({ENV_ID: entry}) + "\n".join(laughs) + "\n")
    paths["yaml_laughs"] = f / "laughs.yml"
    (f / "binary.yml").write_bytes(bytes(range(256)) * 4)
    paths["yaml_binary"] = f / "binary.yml"
    (f / "malformed.yml").write_text(f"{ENV_ID}:\n  n_timesteps: 10\n   gamma: [0.9\n")
    paths["yaml_malformed"] = f / "malformed.yml"
    # scenario folders
    paths["sc_version"] = _scenario(f / "sc_version", "a", version=99)
    paths["sc_width"] = _scenario(f / "sc_width", "a", width=1e300)
    paths["sc_duration"] = _scenario(f / "sc_duration", "a", duration=1e12)
    (f / "sc_fifo").mkdir()
    os.mkfifo(f / "sc_fifo" / "a.json")
    paths["sc_fifo"] = f / "sc_fifo"
    (f / "sc_zero").mkdir()
    (f / "sc_zero" / "a.json").symlink_to("/dev/zero")
    paths["sc_zero"] = f / "sc_zero"
    # evaluate reports for aggregate
    for name, (column, value) in {"agg_inf": ("flow_rate", "1e400"), "agg_text": ("delay_mean", "abc")}.items():
        (f / name).mkdir()
        rows = [f"RL:seed_{k},scenario_000.json,0.5,0.1,2.0,0.0" for k in range(3)]
        header = "planner,scenario,flow_rate,stop_ratio_all,delay_mean,collision_rate"
        columns = header.split(",")
        first = rows[0].split(",")
        first[columns.index(column)] = value
        (f / name / "metrics.csv").write_text("\n".join([header, ",".join(first), *rows[1:]]) + "\n")
        paths[name] = f / name
    (f / "agg_fifo").mkdir()
    os.mkfifo(f / "agg_fifo" / "metrics.csv")
    paths["agg_fifo"] = f / "agg_fifo"
    # inD recordings with a zero and a negative duration
    for name, duration in {"ind_zero": "0", "ind_negative": "-5"}.items():
        folder = f / name
        folder.mkdir()
        for kind, text in texts.items():
            recording_file(folder, 7, kind).write_text(text)
        frame = pd.read_csv(recording_file(folder, 7, "recordingMeta"))
        frame.loc[0, "duration"] = float(duration)
        frame.to_csv(recording_file(folder, 7, "recordingMeta"), index=False)
        paths[name] = folder
    # storages of other applications
    import sqlite3

    with sqlite3.connect(f / "app.db") as connection:
        connection.execute("CREATE TABLE notes (id INTEGER PRIMARY KEY, text TEXT)")
        connection.execute("INSERT INTO notes (text) VALUES ('keep me')")
    connection.close()
    paths["app_db"] = f / "app.db"
    (f / "notes.txt").write_text("my notes\n")
    paths["notes"] = f / "notes.txt"
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="s", storage=f"sqlite:///{f / 'bad_study.db'}")
    study.set_user_attr("timesteps", "many")
    study.add_trial(optuna.trial.create_trial(value=1.0))
    paths["bad_study"] = f / "bad_study.db"
    return paths


def _cut_row(text: str) -> bytes:
    """The file cut in the middle of a row (its first three fields kept)."""
    lines = text.splitlines()
    half = len(lines) // 2
    return ("\n".join(lines[:half]) + "\n" + ",".join(lines[half].split(",")[:3])).encode()


def _train(config="{cfg}", *extra):
    return ["train", "--config", config, "--env", ENV_ID, "--out", "{out}", "--n-timesteps", "10", *extra]


def _tune(config="{cfg}", *extra):
    return ["tune", "--config", config, "--env", ENV_ID, "--study-name", "s", "--storage", "sqlite:///{tmp}/s.db",
            "--n-trials", "1", "--timesteps", "3000", *extra]  # fmt: skip


def _tune_storage(storage: str, *extra):
    return ["tune", "--config", str(CONFIG), "--env", ENV_ID, "--study-name", "s", "--storage", storage,
            "--n-trials", "1", "--timesteps", "3000", *extra]  # fmt: skip


def _report(storage: str):
    return ["tune-report", "--study-name", "s", "--storage", storage, "--out", "{out}"]


def _scenarios(folder: str):
    return ["evaluate", "--scenario-dir", folder, "--planner", "pr"]


def _planner(path: str):
    return ["evaluate", "--planner", path]


def _ind(*extra, data="{ind}"):
    return ["ind", "--data", data, "--recordings", "07", "--jobs", "1", "--no-progress", "--out", "{out}", *extra]


# (id, argv with {placeholders}, what the message must name)
CASES = [
    # evaluate: model files
    ("not-a-zip", ["evaluate", "--planner", "{notzip}"], ["--planner", "notzip.zip", "not a zip"]),
    ("empty-zip", ["evaluate", "--planner", "{emptyzip}"], ["--planner", "emptyzip.zip", "'data'"]),
    ("non-json-data", ["evaluate", "--planner", "{nonjson}"], ["--planner", "nonjson.zip", "JSON"]),
    ("mlp-policy-zip", ["evaluate", "--planner", "{mlp}"], ["mlp.zip", "policy_class", "TD3Policy"]),
    ("ppo-zip", ["evaluate", "--planner", "{ppo}"], ["ppo.zip", "policy_class", "ActorCriticPolicy"]),
    ("max-nodes-too-small", ["evaluate", "--planner", "{small}"], ["small.zip", "max_nodes=8", "max_vehicles=64"]),
    ("max-nodes-too-small-st", ["evaluate", "--planner", "{small_st}"], ["small.safetensors", "max_nodes=8"]),
    ("junk-safetensors", ["evaluate", "--planner", "{junk_st}"], ["junk.safetensors", "not a .safetensors"]),
    # evaluate: flags
    ("duration-inf", ["evaluate", "--duration", "inf"], ["--duration", "'inf'"]),
    ("duration-nan", ["evaluate", "--duration", "nan"], ["--duration", "'nan'"]),
    ("duration-zero", ["evaluate", "--duration", "0"], ["--duration"]),
    ("seed-negative", ["evaluate", "--seed", "-1"], ["--seed", "-1"]),
    ("out-is-a-file", ["evaluate", "--planner", "pr", "--out", "{afile}"], ["--out", "afile", "exists"]),
    ("out-under-a-file", ["evaluate", "--planner", "pr", "--out", "{afile}/report"], ["--out", "afile"]),
    ("env-not-intersection", ["evaluate", "--env", "CartPole-v1"], ["--env", "CartPole-v1", "not an intersection"]),
    ("env-unknown", ["evaluate", "--env", "Nope-v9"], ["--env", "Nope-v9"]),
    ("env-kwargs-list", ["evaluate", "--env-kwargs", "[1]"], ["--env-kwargs", "JSON object"]),
    ("env-config-list", ["evaluate", "--env-kwargs", '{"config": [["max_vehicles", 8]]}'], ["--env-kwargs", "config"]),
    ("env-render-mode", ["evaluate", "--env-kwargs", '{"render_mode": "video"}'],
     ["--env-kwargs", "render_mode", "'video'", "rgb_array"]),  # fmt: skip
    ("env-observation-scale", ["evaluate", "--env-kwargs", '{"config": {"s_scale": 1e300}}'],
     ["--env-kwargs", "s_scale", "1e+300"]),  # fmt: skip
    ("tune-hyperparameter-typo", _tune("{typo}"), ["learnig_rate", "did you mean 'learning_rate'"]),
    ("tune-trial-hyperparameter-typo", _tune(str(CONFIG), "--trial-hyperparams", "batch_sise:64"),
     ["batch_sise", "did you mean 'batch_size'"]),  # fmt: skip
    ("train-hyperparameter-typo", _train("{typo}"), ["learnig_rate", "did you mean 'learning_rate'"]),
    ("env-kwargs-not-json", ["evaluate", "--env-kwargs", "{duration: 5"], ["--env-kwargs", "JSON"]),
    ("max-vehicles-huge", ["evaluate", "--env-kwargs", '{"config": {"max_vehicles": 1000000000}}'],
     ["--env-kwargs", "max_vehicles"]),  # fmt: skip
    ("max-vehicles-word", ["evaluate", "--env-kwargs", '{"config": {"max_vehicles": "many"}}'],
     ["--env-kwargs", "max_vehicles", "'many'"]),  # fmt: skip
    ("config-not-object", ["evaluate", "--env-kwargs", '{"config": 3}'], ["--env-kwargs", "config"]),
    # train
    ("train-device", _train(str(CONFIG), "--device", "cudaX"), ["--device", "cudaX"]),
    ("train-env-kwargs-list", _train(str(CONFIG), "--env-kwargs", "[1]"), ["--env-kwargs", "JSON object"]),
    ("train-lin-abc", _train("{lin_abc}"), ["learning_rate", "lin_abc"]),
    ("train-gamma-word", _train("{gamma_high}"), ["gamma", "high"]),
    ("train-n-envs-0", _train("{n_envs_0}"), ["n_envs", "0"]),
    ("train-n-timesteps-flag", _train(str(CONFIG), "--n-timesteps", "-5"), ["--n-timesteps", "-5"]),
    ("train-n-timesteps-file", ["train", "--config", "{negative_steps}", "--env", ENV_ID, "--out", "{out}"],
     ["n_timesteps", "-5"]),  # fmt: skip
    ("train-seed", _train(str(CONFIG), "--seed", "-1"), ["--seed", "-1"]),
    ("train-env-kwargs-in-file", _train("{env_kwargs_list}"), ["env_kwargs", "mapping"]),
    ("train-env-kwargs-override", _train(str(CONFIG), "--hyperparams", "env_kwargs:5"), ["env_kwargs", "5"]),
    ("train-bad-env-config", _train(str(CONFIG), "--env-kwargs", '{"config": {"max_vehicles": 0}}'),
     ["env_kwargs", "max_vehicles"]),  # fmt: skip
    ("train-env-not-in-file", ["train", "--config", str(CONFIG), "--env", "CartPole-v1", "--out", "{out}"],
     ["CartPole-v1", "no entry"]),  # fmt: skip
    ("train-hyperparam-yaml", _train(str(CONFIG), "--hyperparams", "gamma:[0.9"), ["--hyperparams", "gamma"]),
    ("train-resume-nothing", _train(str(CONFIG), "--resume"), ["--resume", "no config.yml"]),
    ("train-seeds-negative", _train(str(CONFIG), "--seeds", "0", "-1"), ["--seeds", "-1"]),
    ("train-seed-and-seeds", _train(str(CONFIG), "--seeds", "0", "--seed", "1"), ["--seed", "--seeds"]),
    # tune and tune-report
    ("tune-device", _tune(str(CONFIG), "--device", "cudaX"), ["--device", "cudaX"]),
    ("tune-env-kwargs-list", _tune(str(CONFIG), "--env-kwargs", "[1]"), ["--env-kwargs", "JSON object"]),
    ("tune-gamma-word", _tune("{gamma_high}"), ["gamma", "high"]),
    ("tune-lin-abc", _tune("{lin_abc}"), ["learning_rate", "lin_abc"]),
    ("tune-timesteps", _tune(str(CONFIG), "--timesteps", "-5"), ["--timesteps", "-5"]),
    ("tune-seed", _tune(str(CONFIG), "--seed", "-1"), ["--seed", "-1"]),
    ("tune-pruner", _tune(str(CONFIG), "--pruner", "asha"), ["--pruner", "'asha'", "successive-halving", "hyperband"]),
    ("tune-min-resource", _tune(str(CONFIG), "--pruner", "hyperband", "--min-resource", "0"), ["--min-resource"]),
    ("aggregate-no-report", ["aggregate", "{tmp}/nothing", "--out", "{out}"], ["REPORT", "no metrics.csv"]),
    ("aggregate-reps", ["aggregate", "{tmp}", "--reps", "0", "--out", "{out}"], ["--reps", "0"]),
    ("report-unreachable-server", ["tune-report", "--study-name", "s", "--storage", "postgresql://u:p@127.0.0.1:1/db",
                                   "--out", "{out}"], ["--storage"]),  # fmt: skip
    ("report-storage-under-file", ["tune-report", "--study-name", "s", "--storage", "sqlite:///{afile}/x/s.db",
                                   "--out", "{out}"], ["--storage", "afile"]),  # fmt: skip
    # ind
    ("ind-gzipped", _ind("--dataset-only", data="{ind_gz}"), ["07_tracks.csv", "gzip"]),
    ("ind-truncated", _ind("--dataset-only", data="{ind_truncated}"), ["07_tracks.csv", "truncated"]),
    ("ind-cut-row", _ind("--dataset-only", data="{ind_cut_row}"), ["07_tracks.csv", "'xCenter'", "line", "empty"]),
    ("ind-header-only", _ind("--dataset-only", data="{ind_header_only}"), ["07_tracks.csv", "no track rows"]),
    ("ind-non-numeric", _ind("--dataset-only", data="{ind_words}"), ["07_recordingMeta.csv", "frameRate", "'fast'"]),
    ("ind-layout-mismatch", _ind("--planner", "fifo", "--env", ENV_ID), ["--env", "layout", "'4way'", "'inD'"]),
    ("ind-model-too-small", _ind("--planner", "{small}"), ["--planner", "small.zip", "max_nodes=8"]),
    ("ind-model-not-zip", _ind("--planner", "{notzip}"), ["--planner", "notzip.zip"]),
    ("ind-seed", _ind("--seed", "-1"), ["--seed", "-1"]),
    ("ind-huge-recording-range", ["ind", "--data", "{ind}", "--recordings", "0-99999999999", "--dataset-only",
                                  "--out", "{out}"], ["--recordings", "99999999999"]),  # fmt: skip
    ("ind-out-is-a-file", ["ind", "--data", "{ind}", "--recordings", "07", "--dataset-only", "--out", "{afile}"],
     ["--out", "afile", "exists"]),  # fmt: skip
    ("ind-env-kwargs-list", _ind("--env-kwargs", "[1]"), ["--env-kwargs", "JSON object"]),
    # policy_kwargs, wherever they come from: a zip, a .safetensors header, YAML, the command line
    ("zip-pooling-null", _planner("{zip_pooling_null}"), ["zip_pooling_null.zip", "policy_kwargs.pooling", "None"]),
    ("zip-encoder-huge", _planner("{zip_encoder_huge}"), ["zip_encoder_huge.zip", "policy_kwargs.encoder_dim"]),
    ("zip-activation-module", _planner("{zip_activation_module}"), ["activation_fn", "torch.nn.modules.module.Module"]),
    ("zip-kwargs-deep", _planner("{zip_kwargs_deep}"), ["zip_kwargs_deep.zip", "policy_kwargs", "nested"]),
    ("zip-nan-weights", _planner("{zip_nan}"), ["zip_nan.zip", "NaN"]),
    ("ind-nan-weights", _ind("--planner", "{zip_nan}"), ["--planner", "zip_nan.zip", "NaN"]),
    ("zip-garbage-lzma", _planner("{zip_lzma}"), ["zip_lzma.zip", "'data'"]),
    ("st-nan-weights", _planner("{st_nan}"), ["nan.safetensors", "NaN"]),
    ("st-deep-metadata", _planner("{st_deep}"), ["deep.safetensors", "JSON"]),
    ("st-fused-foreach", _planner("{st_fused}"), ["fused.safetensors", "optimizer_kwargs", "fused"]),
    ("train-pooling-null", _train("{pooling_null}"), ["policy_kwargs.pooling", "None"]),
    ("train-encoder-huge", _train("{encoder_huge}"), ["policy_kwargs.encoder_dim", "1000000000000.0"]),
    ("train-activation-module", _train("{activation_module}"), ["activation_fn", "torch.nn.modules.module.Module"]),
    ("train-activation-lazy", _train("{activation_lazy}"), ["activation_fn", "LazyModuleMixin"]),
    ("train-activation-error", _train("{activation_error}"), ["activation_fn", "sb3_graph.commands.UserError"]),
    ("train-fused-foreach", _train("{fused_foreach}"), ["policy_kwargs.optimizer_kwargs", "fused"]),
    ("train-too-large", _train("{too_large}"), ["policy_kwargs", "GiB"]),
    ("train-cli-pooling-null", _train(str(CONFIG), "--hyperparams", "policy_kwargs:dict(pooling=None)"),
     ["policy_kwargs.pooling"]),  # fmt: skip
    ("tune-pooling-null", _tune("{pooling_null}"), ["policy_kwargs.pooling"]),
    # counts, sizes, depths and files that are not regular files
    ("train-buffer-huge", _train("{buffer_huge}"), ["buffer_size", "1000000000000"]),
    ("train-n-envs-huge", _train("{n_envs_huge}"), ["n_envs", "100000"]),
    ("tune-n-envs-huge", _tune("{n_envs_huge}"), ["n_envs", "100000"]),
    ("train-tensorboard-path", _train("{tensorboard_path}"), ["tensorboard_log"]),
    ("train-yaml-deep", _train("{yaml_deep}"), ["deep.yml", "nested"]),
    ("tune-yaml-laughs", _tune("{yaml_laughs}"), ["laughs.yml", "1000000 values"]),
    ("train-yaml-binary", _train("{yaml_binary}"), ["binary.yml", "UTF-8"]),
    ("train-yaml-malformed", _train("{yaml_malformed}"), ["malformed.yml", "YAML"]),
    ("train-hyperparams-deep", _train(str(CONFIG), "--hyperparams", "gamma:" + "[" * 20_000 + "]" * 20_000),
     ["--hyperparams gamma", "nested"]),  # fmt: skip
    ("evaluate-env-kwargs-deep", ["evaluate", "--env-kwargs", "[" * 20_000 + "]" * 20_000], ["--env-kwargs", "nested"]),
    ("train-yaml-fifo", _train("{sc_fifo}/a.json"), ["a.json", "not a regular file"]),
    ("evaluate-duration-huge", ["evaluate", "--duration", "1e12"], ["--duration", "1e+12"]),
    ("evaluate-scenarios-huge", ["evaluate", "--scenarios", "1000000000"], ["--scenarios", "1000000000"]),
    ("evaluate-seed-huge", ["evaluate", "--seed", str(2**64)], ["--seed", str(2**64)]),
    ("train-seed-huge", _train(str(CONFIG), "--seed", str(2**64)), ["--seed", str(2**64)]),
    ("sweep-demand-tiny", ["sweep", "--demand", "1e-300", "--scenarios", "1", "--duration", "2", "--jobs", "1",
                           "--out", "{out}"], ["--demand", "1e-300"]),  # fmt: skip
    ("aggregate-reps-huge", ["aggregate", "{agg_text}", "--reps", "1000000000", "--out", "{out}"],
     ["--reps", "1000000000"]),  # fmt: skip
    ("aggregate-inf", ["aggregate", "{agg_inf}", "--out", "{out}"], ["flow_rate", "'inf'", "row 2"]),
    ("aggregate-text", ["aggregate", "{agg_text}", "--out", "{out}"], ["delay_mean", "'abc'"]),
    ("aggregate-fifo", ["aggregate", "{agg_fifo}", "--out", "{out}"], ["metrics.csv", "not a regular file"]),
    ("scenario-version", _scenarios("{sc_version}"), ["a.json", "version", "99"]),
    ("scenario-width", _scenarios("{sc_width}"), ["a.json", "width", "1e+300"]),
    ("scenario-duration", _scenarios("{sc_duration}"), ["a.json", "duration"]),
    ("scenario-fifo", _scenarios("{sc_fifo}"), ["a.json", "not a regular file"]),
    ("scenario-dev-zero", _scenarios("{sc_zero}"), ["a.json", "not a regular file"]),
    ("ind-duration-zero", _ind("--dataset-only", data="{ind_zero}"), ["07_recordingMeta.csv", "duration"]),
    ("ind-duration-negative", _ind("--dataset-only", data="{ind_negative}"), ["duration", "-5"]),
    ("env-max-acceleration", ["evaluate", "--env-kwargs", '{"config": {"max_acceleration": 1e308}}'],
     ["--env-kwargs", "max_acceleration"]),  # fmt: skip
    # tune's search space and start (issue #23)
    ("tune-weights-unknown", _tune(str(CONFIG), "--weights", "speed"), ["--weights", "['speed']", "terms of reward"]),
    ("tune-config-range", _tune(str(CONFIG), "--tune-config", "residual_scale:0.5:3"),
     ["--tune-config residual_scale", "(0, 2]"]),  # fmt: skip
    ("tune-config-form", _tune(str(CONFIG), "--tune-config", "residual_scale"), ["--tune-config", "KEY:LOW:HIGH"]),
    ("tune-objective-weight", _tune(str(CONFIG), "--objective-weight", "0.1"), ["objective 'flow' takes no weight"]),
    ("tune-init-weights-architecture", _tune("{narrow}", "--init-weights", "{small_st}"),
     ["--init-weights", "small.safetensors", "another architecture"]),  # fmt: skip
    ("tune-init-weights-junk", _tune(str(CONFIG), "--init-weights", "{junk_st}"), ["--init-weights", "junk.safetens"]),
    ("tune-init-weights-mlp", _tune(str(CONFIG), "--init-weights", "{mlp}"), ["--init-weights", "mlp.zip"]),
    ("train-init-weights-architecture", _train("{narrow}", "--init-weights", "{small_st}"),
     ["--init-weights", "small.safetensors", "another architecture"]),  # fmt: skip
    # storages: a read-only command creates nothing, tune writes into no other application's file
    ("report-foreign-db", _report("sqlite:///{app_db}"), ["--storage", "no Optuna study"]),
    ("report-text-journal", _report("journal://{notes}"), ["--storage", "notes.txt", "not an Optuna journal"]),
    ("report-bad-study", _report("sqlite:///{bad_study}"), ["study 's'", "timesteps", "many"]),
    ("tune-foreign-db", _tune_storage("sqlite:///{app_db}"), ["--storage", "notes", "--allow-foreign-storage"]),
    ("tune-text-journal", _tune_storage("journal://{notes}"), ["notes.txt", "not an Optuna journal"]),
    # export
    ("export-not-zip", ["export", "{notzip}", "{out}.safetensors"], ["MODEL", "notzip.zip"]),
    ("export-ppo", ["export", "{ppo}", "{out}.safetensors"], ["MODEL", "ppo.zip", "policy_class"]),
    ("export-suffix", ["export", "{small}", "{out}.pt"], ["OUT", ".safetensors"]),
    ("export-missing", ["export", "{out}_missing.zip", "{out}.safetensors"], ["MODEL", "file not found"]),
    ("export-out-exists", ["export", "{small}", "{small_st}"], ["OUT", "exists"]),
]


@pytest.mark.parametrize("argv, names", [pytest.param(a, n, id=i) for i, a, n in CASES])
def test_bad_input_is_one_line_naming_it(files, tmp_path, capsys, argv, names):
    out = tmp_path / "out"
    values = {key: str(value) for key, value in files.items()}
    values.update(out=str(out), tmp=str(tmp_path), cfg=str(CONFIG))
    args = []
    for item in argv:
        for key, value in values.items():
            item = item.replace("{" + key + "}", value)
        args.append(item)
    if args[0] == "evaluate":  # small runs, in case one got through; the case's own flags come last
        args = [args[0], *FAST_EVAL, *([] if "--out" in args else ["--out", str(out)]), *args[1:]]
    before = sorted(p.name for p in files["dir"].iterdir())
    try:
        code = main(args)
    except SystemExit as exit_:  # argparse's own refusals
        code = exit_.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.endswith("\n") and err.count("\n") == 1, err  # one line
    assert "Traceback" not in err
    for name in names:
        assert name in err, (name, err)
    assert not out.exists() and not list(tmp_path.glob(".out.partial-*"))  # no half-written --out
    assert not list(tmp_path.glob("out.*"))
    assert sorted(p.name for p in files["dir"].iterdir()) == before  # nothing written next to the inputs
    assert files["afile"].read_text() == "a file, not a folder"
    assert files["notes"].read_text() == "my notes\n"
    assert _tables(files["app_db"]) == ["notes"]


def _tables(path: Path) -> list[str]:
    import sqlite3

    connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return sorted(row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type='table'"))
    finally:
        connection.close()
