"""Bad input to every command: a one-line error naming the field, flag, file or value, a non-zero
exit, no traceback, and no ``--out`` left behind (table-driven)."""

from __future__ import annotations

import gzip
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
    from sb3_graph.weights import save_policy

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
        "gamma_high": {"gamma": "high"},
        "n_envs_0": {"n_envs": 0},
        "negative_steps": {"n_timesteps": -5},
        "env_kwargs_list": {"env_kwargs": [1]},
    }.items():
        paths[name] = _config(f, name, **changes)
    valid = f / "ind"
    write_recording(valid, make_recording(7, default_vehicles(seed=7, num=8), SITE))
    texts = {kind: recording_file(valid, 7, kind).read_text() for kind in ("tracks", "tracksMeta", "recordingMeta")}
    for name, change in {
        "ind_gz": lambda t: gzip.compress(t["tracks"].encode()),
        "ind_truncated": lambda t: "\n".join(t["tracks"].splitlines()[: len(t["tracks"].splitlines()) // 2]).encode(),
        "ind_cut_row": lambda t: _cut_row(t["tracks"]),
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
    # export
    ("export-not-zip", ["export", "{notzip}", "{out}.safetensors"], ["MODEL", "notzip.zip"]),
    ("export-ppo", ["export", "{ppo}", "{out}.safetensors"], ["MODEL", "ppo.zip", "policy_class"]),
    ("export-suffix", ["export", "{small}", "{out}.pt"], ["OUT", ".safetensors"]),
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
