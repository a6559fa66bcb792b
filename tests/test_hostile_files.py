"""Files from others never run their code: planner files (evaluate, ind, export), experiment
files (train, tune) and run folders (train --resume). Every payload here would create a marker
file when unpickled or evaluated; the tests check that it never appears."""

from __future__ import annotations

import base64
import io
import json
import pickle
import zipfile
from pathlib import Path

import pytest
import torch as th
import yaml

from envs.commands.evaluate import PAPER_MODEL
from envs.ind.synthetic import SyntheticSite, default_vehicles, make_recording, write_recording
from sb3_graph.cli import main

SHIPPED_ZIP = PAPER_MODEL.with_suffix(".zip")
ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "zoo_configs" / "td3.yml"
ENV_ID = "CoopIntersection4Way-v0"


class Payload:
    """Unpickling it opens (creates) the marker file: proof that the file ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def serialized(marker: Path) -> str:
    return base64.b64encode(pickle.dumps(Payload(marker))).decode()


def rewrite_zip(source: Path, target: Path, data_change=None, policy_bytes: bytes | None = None) -> Path:
    """A copy of an SB3 zip with its ``data`` JSON changed and/or another ``policy.pth``."""
    with zipfile.ZipFile(source) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    if data_change is not None:
        data = json.loads(entries["data"])
        data_change(data)
        entries["data"] = json.dumps(data).encode()
    if policy_bytes is not None:
        entries["policy.pth"] = policy_bytes
    with zipfile.ZipFile(target, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)
    return target


def _set_serialized(field: str, marker: Path):
    def change(data):
        data[field][":serialized:"] = serialized(marker)

    return change


def _payload_kwargs(marker: Path):
    def change(data):  # a pickled dict whose plain parts look harmless
        plain = data["policy_kwargs"]
        data["policy_kwargs"] = {":type:": "<class 'dict'>", ":serialized:": serialized(marker), **plain}

    return change


def _new_field(marker: Path):
    def change(data):
        data["surprise"] = {":type:": "<class 'object'>", ":serialized:": serialized(marker)}

    return change


# variant -> (how the zip changes, loads with weights only (True) or is refused (False))
LOADABLE = {
    "policy_kwargs": _payload_kwargs,
    "observation_space": lambda marker: _set_serialized("observation_space", marker),
    "action_space": lambda marker: _set_serialized("action_space", marker),
    "lr_schedule": lambda marker: _set_serialized("lr_schedule", marker),
    "new_field": _new_field,
}
REFUSED = {"policy_class": lambda marker: _set_serialized("policy_class", marker)}


@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hostile")
    marker = folder / "MARKER"
    files = {}
    for name, make in {**LOADABLE, **REFUSED}.items():
        files[name] = rewrite_zip(SHIPPED_ZIP, folder / f"{name}.zip", data_change=make(marker))
    buffer = io.BytesIO()
    th.save({"actor.head.weight": Payload(marker)}, buffer)  # a torch file whose pickle opens the marker
    files["policy.pth"] = rewrite_zip(SHIPPED_ZIP, folder / "policy_pth.zip", policy_bytes=buffer.getvalue())
    return folder, marker, files


def test_the_payloads_are_live(hostile, tmp_path):
    """SB3's own loader runs them: what the safe readers must avoid."""
    from sb3_graph import TD3

    _, _, files = hostile
    marker = tmp_path / "MARKER"
    rewrite_zip(SHIPPED_ZIP, tmp_path / "m.zip", data_change=_new_field(marker))
    TD3.load(tmp_path / "m.zip")
    assert marker.exists()


def test_evaluate_loads_weights_only_and_refuses_what_it_cannot_rebuild(hostile, tmp_path, capsys):
    folder, marker, files = hostile
    small = ["--scenarios", "1", "--duration", "2", "--jobs", "1", "--no-progress"]
    args = ["evaluate", "--planner", "fifo"]
    for name in LOADABLE:
        args += ["--planner", str(files[name])]
    assert main([*args, "--out", str(tmp_path / "ok"), *small]) == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "ok" / "summary.json").read_text())
    assert set(summary) == {"FIFO", *(f"RL:{name}" for name in LOADABLE)}
    for name in [*REFUSED, "policy.pth"]:
        out = tmp_path / f"refused-{name}"
        assert main(["evaluate", "--planner", str(files[name]), "--out", str(out), *small]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--planner" in err and files[name].name in err and "Traceback" not in err
        assert not out.exists()
    assert "sb3-graph export" in _refusal(capsys, files["policy_class"], tmp_path)
    assert not marker.exists()


def _refusal(capsys, path, tmp_path):
    main(["evaluate", "--planner", str(path), "--out", str(tmp_path / "never"), "--scenarios", "1"])
    return capsys.readouterr().err


def test_ind_loads_weights_only_and_refuses_what_it_cannot_rebuild(hostile, tmp_path, capsys):
    folder, marker, files = hostile
    data = tmp_path / "data"
    site = SyntheticSite(centre=(-75.0, 140.0), rotation_deg=17.0, location_id=1)
    write_recording(data, make_recording(7, default_vehicles(seed=7, num=8), site))
    base = ["ind", "--data", str(data), "--recordings", "07", "--jobs", "1", "--no-progress"]
    args = [*base, "--planner", str(files["policy_kwargs"]), "--planner", str(files["new_field"])]
    assert main([*args, "--out", str(tmp_path / "ok")]) == 0, capsys.readouterr().err
    for name in [*REFUSED, "policy.pth"]:
        out = tmp_path / f"refused-{name}"
        assert main([*base, "--planner", str(files[name]), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and files[name].name in err and "Traceback" not in err
        assert not out.exists()
    assert not marker.exists()


def test_export_writes_weights_only_and_trust_restores_sb3_load(hostile, tmp_path, capsys):
    from sb3_graph.files.policy_files import load_policy, read_weights_file

    folder, marker, files = hostile
    out = tmp_path / "p.safetensors"
    assert main(["export", str(files["observation_space"]), str(out)]) == 0
    description, state = read_weights_file(out)
    assert description.policy_class == "GraphPolicy" and "actor.head.weight" in state
    assert load_policy(out).policy.observation_space.max_nodes == 64
    assert main(["export", str(files["policy_class"]), str(tmp_path / "q.safetensors")]) == 2
    assert "--trust-planner-files" in capsys.readouterr().err and not (tmp_path / "q.safetensors").exists()
    assert not marker.exists()
    # --trust-planner-files is SB3's full load: it runs the file's pickles (here: the marker appears)
    assert main(["export", str(files["new_field"]), str(tmp_path / "t.safetensors"), "--trust-planner-files"]) == 0
    assert marker.exists()
    marker.unlink()


# ---------------------------------------------------------------- experiment files
HOSTILE_VALUES = [
    ("policy_kwargs", "dict(x=open('{marker}', 'w'))"),
    ("policy_kwargs", "__import__('builtins').open('{marker}', 'w')"),
    ("policy_kwargs", "importlib.import_module('builtins').open('{marker}', 'w')"),
    ("policy_kwargs", "dict(activation_fn=sb3_graph.files.experiment_files.importlib)"),
    ("replay_buffer_class", "importlib.import_module('pathlib').Path('{marker}').touch()"),
    ("replay_buffer_kwargs", "(lambda: open('{marker}', 'w'))()"),
    ("policy", "stable_baselines3.common.save_util.load_from_pkl"),
    ("callback", "builtins.open"),
]


def _hostile_config(tmp_path, field, value):
    marker = tmp_path / "MARKER"
    entry = yaml.safe_load(CONFIG.read_text())[ENV_ID]
    entry[field] = value.format(marker=marker)
    path = tmp_path / "hostile.yml"
    path.write_text(yaml.safe_dump({ENV_ID: entry, "GraphMaxNeighbour-v0": entry}))
    return path, marker


@pytest.mark.parametrize("field, value", HOSTILE_VALUES)
def test_hostile_experiment_file_never_runs_in_train_or_tune(tmp_path, capsys, field, value):
    path, marker = _hostile_config(tmp_path, field, value)
    out = tmp_path / "run"
    rc = main(["train", "--config", str(path), "--env", ENV_ID, "--out", str(out), "--n-timesteps", "10"])
    err = capsys.readouterr().err
    assert rc == 2 and field in err and "Traceback" not in err and err.count("\n") == 1
    assert not out.exists()
    storage = f"sqlite:///{tmp_path}/s.db"
    rc = main(["tune", "--config", str(path), "--env", ENV_ID, "--study-name", "s", "--storage", storage,
               "--n-trials", "1", "--timesteps", "3000"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 2 and field in err and err.count("\n") == 1
    assert not marker.exists()


def test_hostile_override_on_the_command_line_never_runs(tmp_path, capsys):
    marker = tmp_path / "MARKER"
    out = tmp_path / "run"
    rc = main(["train", "--config", str(CONFIG), "--env", ENV_ID, "--out", str(out), "--n-timesteps", "10",
               "--hyperparams", f"policy_kwargs:__import__('os').system('touch {marker}')"])  # fmt: skip
    assert rc == 2 and "policy_kwargs" in capsys.readouterr().err
    assert not marker.exists() and not out.exists()


def test_safe_reader_gives_what_rl_zoo3_would(tmp_path):
    """The shipped experiment file reads the same without eval."""
    import torch.nn as nn

    from sb3_graph import GraphReplayBuffer
    from sb3_graph.files.experiment_files import build_algorithm_kwargs

    entry = yaml.safe_load(CONFIG.read_text())[ENV_ID]
    policy_kwargs = entry["policy_kwargs"][:-1] + ", activation_fn=nn.Tanh)"
    kwargs = build_algorithm_kwargs({**entry, "policy_kwargs": policy_kwargs}, 4)
    assert kwargs["replay_buffer_class"] is GraphReplayBuffer
    assert kwargs["policy_kwargs"] == {
        "encoder_dim": 64, "conv_dims": (64, 64), "aggregation": "max", "pooling": "max", "activation_fn": nn.Tanh
    }  # fmt: skip


# ---------------------------------------------------------------- run folders
def _run_folder(tmp_path, marker):
    """A run folder as someone might hand it over: a checkpoint whose pickles open the marker."""
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    entry = yaml.safe_load(CONFIG.read_text())[ENV_ID]
    entry["policy_kwargs"] = f"dict(x=open('{marker}', 'w'))"
    (out / "config.yml").write_text(yaml.safe_dump(entry))
    (out / "run.json").write_text(json.dumps({"seed": 0, "sessions": []}))
    checkpoint = rewrite_zip(SHIPPED_ZIP, out / "checkpoints" / "model_10_steps.zip", data_change=_new_field(marker))
    (out / "checkpoints" / "model_replay_buffer_10_steps.pkl").write_bytes(pickle.dumps(Payload(marker)))
    return out, checkpoint


def test_resume_does_not_unpickle_files_it_did_not_write(tmp_path, capsys):
    from sb3_graph.files.signing import SIGNATURES, sign

    marker = tmp_path / "MARKER"
    out, checkpoint = _run_folder(tmp_path, marker)
    args = ["train", "--config", str(CONFIG), "--env", ENV_ID, "--out", str(out), "--resume"]
    # a folder from elsewhere: its record and config were not signed here, so they are not read
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "run.json" in err and "no signature" in err and "--trust-run-files" in err and err.count("\n") == 1
    # signed here (a run of this machine whose config was then changed and signed): read safely
    sign(out / "config.yml")
    sign(out / "run.json")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "policy_kwargs" in err and err.count("\n") == 1
    entry = yaml.safe_load((out / "config.yml").read_text())
    entry["policy_kwargs"] = "dict(encoder_dim=64)"
    (out / "config.yml").write_text(yaml.safe_dump(entry))
    assert main(args) == 2
    assert "config.yml does not match its signature" in capsys.readouterr().err
    sign(out / "config.yml")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "no signature" in err and "model_10_steps.zip" in err and "--trust-run-files" in err
    # signatures made elsewhere (another key) do not count either
    (out / "checkpoints" / SIGNATURES).write_text(json.dumps({checkpoint.name: "0" * 64}))
    assert main(args) == 2
    assert "does not match its signature" in capsys.readouterr().err
    assert not marker.exists()


# ---------------------------------------------------------------- no file chooses where we write
TINY = ["--eval-freq", "100", "--eval-episodes", "1", "--checkpoint-freq", "100", "--no-progress",
        "--hyperparams", "learning_starts:64", "batch_size:16", "buffer_size:1000",
        "--env-kwargs", json.dumps({"config": {"duration": 8.0}})]  # fmt: skip
CHECKPOINT_CALLBACK = "stable_baselines3.common.callbacks.CheckpointCallback"


def _with_callback(tmp_path, name, **kwargs):
    entry = yaml.safe_load(CONFIG.read_text())[ENV_ID]
    entry["callback"] = [*entry.get("callback", []), {CHECKPOINT_CALLBACK: {"save_freq": 50, **kwargs}}]
    path = tmp_path / f"{name}.yml"
    path.write_text(yaml.safe_dump({ENV_ID: entry}))
    return path


@pytest.mark.parametrize(
    "kwargs, names",
    [
        ({"save_path": "{elsewhere}"}, ["save_path", "relative path"]),
        ({"save_path": "../../elsewhere"}, ["save_path", "'..'"]),
        ({"save_path": "ok", "name_prefix": "../../../elsewhere/model"}, ["name_prefix", "path"]),
    ],
    ids=["absolute", "dot-dot", "prefix"],
)
def test_a_callback_path_outside_the_run_folder_is_refused(tmp_path, capsys, kwargs, names):
    elsewhere = tmp_path / "elsewhere"
    kwargs = {key: value.format(elsewhere=elsewhere) for key, value in kwargs.items()}
    config = _with_callback(tmp_path, "cb", **kwargs)
    out = tmp_path / "a" / "b" / "run"
    assert main(["train", "--config", str(config), "--env", ENV_ID, "--out", str(out), "--n-timesteps", "10"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and all(name in err for name in names), err
    assert not out.exists() and not elsewhere.exists()
    # tune has no run folder: a path argument is refused there whatever it is
    storage = f"sqlite:///{tmp_path}/s.db"
    config = _with_callback(tmp_path, "cb2", save_path="ok")
    assert main(["tune", "--config", str(config), "--env", ENV_ID, "--study-name", "s", "--storage", storage,
                 "--n-trials", "1", "--timesteps", "3000"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "save_path" in err and "no run folder" in err and err.count("\n") == 1
    assert not elsewhere.exists()


def test_callback_paths_are_rerooted_and_resume_reads_only_signed_run_files(tmp_path, capsys):
    config = _with_callback(tmp_path, "cb", save_path="snapshots", name_prefix="cb")
    out = tmp_path / "run"
    args = ["train", "--config", str(config), "--env", ENV_ID, "--out", str(out), *TINY]
    assert main([*args, "--n-timesteps", "100"]) == 0, capsys.readouterr().err
    assert sorted(p.name for p in (out / "callbacks" / "snapshots").iterdir())[0].startswith("cb_")
    assert not (tmp_path / "snapshots").exists()
    # someone adds a callback that writes elsewhere to the stored config: --resume refuses it
    stored = (out / "config.yml").read_text()
    entry = yaml.safe_load(stored)
    entry["callback"] = [{CHECKPOINT_CALLBACK: {"save_freq": 1, "save_path": str(tmp_path / "elsewhere")}}]
    (out / "config.yml").write_text(yaml.safe_dump(entry))
    resume = [*args, "--resume", "--n-timesteps", "150"]
    assert main(resume) == 2
    err = capsys.readouterr().err
    assert "config.yml does not match its signature" in err and err.count("\n") == 1
    # with --trust-run-files the file is read, and its path is still refused by name
    assert main([*resume, "--trust-run-files"]) == 2
    assert "save_path" in capsys.readouterr().err
    assert not (tmp_path / "elsewhere").exists()
    (out / "config.yml").write_text(stored)
    record = (out / "run.json").read_text()
    for change in ({"algo": "bogus"}, {"best_mean_reward": "high"}, {"sessions": "many"}, {"wall_time_s": "long"}):
        (out / "run.json").write_text(json.dumps({**json.loads(record), **change}))
        assert main(resume) == 2
        assert "run.json does not match its signature" in capsys.readouterr().err
        assert main([*resume, "--trust-run-files"]) == 2
        err = capsys.readouterr().err
        assert f"field '{next(iter(change))}'" in err and err.count("\n") == 1, err
    # the signatures file replaced by a device: nothing counts as signed, nothing hangs
    (out / "run.json").write_text(record)
    (out / "signatures.json").rename(out / "kept.json")
    (out / "signatures.json").symlink_to("/dev/zero")
    assert main(resume) == 2
    assert "signatures.json' is a symbolic link" in capsys.readouterr().err
    (out / "signatures.json").unlink()
    (out / "kept.json").rename(out / "signatures.json")
    (out / "checkpoints" / "signatures.json").unlink()
    (out / "checkpoints" / "signatures.json").symlink_to("/dev/zero")
    assert main(resume) == 2
    err = capsys.readouterr().err
    assert "model_100_steps.zip has no signature" in err and err.count("\n") == 1


# ---------------------------------------------------------------- storages and outputs
def _study(path: Path, **attrs) -> str:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = f"sqlite:///{path}"
    study = optuna.create_study(study_name="s", storage=storage, load_if_exists=True)
    for key, value in attrs.items():
        study.set_user_attr(key, value)
    if not study.trials:
        study.add_trial(optuna.trial.create_trial(params={"algo.gamma": 0.9}, distributions={
            "algo.gamma": optuna.distributions.FloatDistribution(0.8, 0.999)}, value=1.0))  # fmt: skip
    return storage


def test_report_overwrite_replaces_the_whole_folder_or_nothing(tmp_path, capsys):
    storage = _study(tmp_path / "s.db", timesteps=100)
    out = tmp_path / "report"
    report = ["tune-report", "--study-name", "s", "--storage", storage, "--out", str(out)]
    assert main(report) == 0, capsys.readouterr().err
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert "trials.csv" in before and "report.md" in before
    _study(tmp_path / "s.db", timesteps="many")  # the study now fails its check
    assert main([*report, "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "timesteps" in err and err.count("\n") == 1
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # the old report, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", "s.db"]  # no staging left
    _study(tmp_path / "s.db", timesteps=200)
    (out / "old-figure.png").write_bytes(b"from the old report")
    assert main([*report, "--overwrite"]) == 0
    assert not (out / "old-figure.png").exists()  # one folder, one study
    assert "200" in (out / "report.md").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", "s.db"]


def test_a_server_that_accepts_and_never_answers_times_out(tmp_path, capsys, monkeypatch):
    import socket
    import threading
    import time

    pytest.importorskip("psycopg2")
    from sb3_graph.tuning import storage as storage_module

    monkeypatch.setattr(storage_module, "CONNECT_TIMEOUT_S", 2)  # libpq's smallest
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    held = []
    stop = threading.Event()

    def accept():
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])  # accepted, never answered
            except OSError:
                continue

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    url = f"postgresql://u:p@127.0.0.1:{server.getsockname()[1]}/db"
    result = {}
    command = ["tune-report", "--study-name", "s", "--storage", url, "--out", str(tmp_path / "out")]
    client = threading.Thread(target=lambda: result.update(code=main(command)), daemon=True)
    try:
        tic = time.monotonic()
        client.start()
        client.join(60)  # bounded even if the timeout were lost: closing the sockets below ends the wait
        elapsed = time.monotonic() - tic
    finally:
        stop.set()
        thread.join(5)
        for connection in held:
            connection.close()
        server.close()
        client.join(10)
    err = capsys.readouterr().err
    assert held and elapsed < 30, elapsed
    assert result.get("code") == 2 and "--storage" in err and "u:***@" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_sigterm_cleans_up_a_staged_report_as_ctrl_c_does(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "report"
    command = [sys.executable, "-m", "sb3_graph.cli", "evaluate", "--planner", "pr", "--scenarios", "200",
               "--duration", "60", "--jobs", "1", "--no-progress", "--out", str(out)]  # fmt: skip
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(600):  # the staging folder holds the generated scenarios before the runs start
            if list(tmp_path.glob(".report.partial-*/scenarios/*.json")):
                break
            time.sleep(0.1)
        assert process.poll() is None, process.communicate()
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # neither the report nor its staging folder
