"""``sb3-graph train``: run one rl-zoo3 style experiment into a run folder, resumable.

A run folder holds::

    config.yml          the experiment entry as resolved (file entry + command-line overrides)
    run.json            seed, versions, command, steps, wall time, best validation reward
    best_model.zip      the model with the best validation reward so far (paper: "Experiments")
    evaluations.npz     every validation result (SB3 EvalCallback's log)
    checkpoints/        model_<steps>_steps.zip and the latest replay buffer, for --resume
    final_model.zip     the model at the end of training
    tb/                 TensorBoard logs (reward terms, curriculum, losses)
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import platform
import re
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sb3_graph.cli import UserError

CHECKPOINT_PATTERN = re.compile(r"model_(\d+)_steps\.zip$")
#: --algo names (rl-zoo3's) -> class names in sb3_graph
ALGORITHMS = {
    "td3": "TD3",
    "ddpg": "DDPG",
    "sac": "SAC",
    "tqc": "TQC",
    "crossq": "CrossQ",
    "ppo": "PPO",
    "a2c": "A2C",
}
VALIDATION_SEED_OFFSET = 10_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--algo",
        choices=ALGORITHMS,
        default=None,
        help="algorithm (default td3; a resumed run keeps its own), as rl-zoo3's --algo",
    )
    parser.add_argument("--config", required=True, help="rl-zoo3 style YAML file (one entry per env id)")
    parser.add_argument("--env", required=True, help="environment id, the entry to read from --config")
    parser.add_argument("--out", required=True, help="run folder; must not exist unless --resume")
    parser.add_argument("--n-timesteps", type=int, default=None, help="override n_timesteps of the entry")
    parser.add_argument("--seed", type=int, default=0, help="seed of the training envs and the learner")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    parser.add_argument("--eval-freq", type=int, default=5000, help="steps between validations (paper: 5000)")
    parser.add_argument("--eval-episodes", type=int, default=10, help="validation episodes (paper: 10)")
    parser.add_argument("--checkpoint-freq", type=int, default=10_000, help="steps between checkpoints")
    parser.add_argument(
        "--gym-packages",
        nargs="*",
        default=["envs"],
        help="modules to import so that they register their environments (default: envs)",
    )
    parser.add_argument("--env-kwargs", type=json.loads, default=None, help="JSON dict merged into env_kwargs")
    parser.add_argument(
        "--hyperparams",
        "-params",
        nargs="+",
        default=[],
        metavar="KEY:VALUE",
        help="override entries of the experiment, as rl-zoo3 (values are read as YAML)",
    )
    parser.add_argument(
        "--init-weights",
        default=None,
        help="start from the network weights of a saved model .zip (fine-tuning; read as tensors only, "
        "the architecture must match); recorded in run.json",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (see benchmarks/)")
    parser.add_argument("--device", default="auto", help="torch device (auto, cpu, cuda)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--verbose", type=int, default=0, choices=(0, 1, 2))


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["batch_size:64", "gamma:0.9"]`` -> ``{"batch_size": 64, "gamma": 0.9}`` (values as YAML)."""
    overrides = {}
    for item in items:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise UserError(f"--hyperparams: expected KEY:VALUE, got {item!r}")
        overrides[key] = yaml.safe_load(value)
    return overrides


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in ("sb3_graph", "stable_baselines3", "torch", "torch_geometric", "gymnasium", "highway_env", "numpy"):
        try:
            versions[name] = getattr(importlib.import_module(name), "__version__", "unknown")
        except ImportError:
            continue
    return versions


def _new_record(args: argparse.Namespace, seed: int) -> dict[str, Any]:
    return {
        "algo": args.algo or "td3",
        "env": args.env,
        "config_file": str(args.config),
        "seed": seed,
        "command": " ".join(sys.argv),
        "versions": _versions(),
        "wall_time_s": 0.0,
        "sessions": [],
    }


def _interrupt_on_sigterm() -> None:
    # A scheduler's SIGTERM (and a background job, which ignores SIGINT) ends training like Ctrl-C:
    # with a complete checkpoint and the run record written.
    def handler(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)


def latest_checkpoint(folder: Path) -> tuple[int, Path] | None:
    """The checkpoint with the most steps in ``folder/checkpoints``, or ``None``."""
    found = [
        (int(match.group(1)), path)
        for path in (folder / "checkpoints").glob("model_*_steps.zip")
        if (match := CHECKPOINT_PATTERN.search(path.name))
    ]
    return max(found) if found else None


def save_checkpoint(model, folder: Path) -> None:
    """Save the model and (off-policy) its replay buffer as ``model_<steps>_steps``; drop older
    replay buffers."""
    folder.mkdir(parents=True, exist_ok=True)
    steps = model.num_timesteps
    model.save(folder / f"model_{steps}_steps.zip")
    if getattr(model, "replay_buffer", None) is None:  # on-policy: nothing to carry over
        return
    newest = folder / f"model_replay_buffer_{steps}_steps.pkl"
    model.save_replay_buffer(newest)
    _drop_old_buffers(folder, keep=newest)


def _drop_old_buffers(folder: Path, keep: Path) -> None:
    # Each replay buffer file is as large as the buffer: keep the newest only.
    for old in folder.glob("model_replay_buffer_*_steps.pkl"):
        if old != keep:
            old.unlink()


def _make_checkpoint_callback(save_freq: int, folder: Path):
    from stable_baselines3.common.callbacks import BaseCallback

    class CompleteCheckpoint(BaseCallback):
        """:func:`save_checkpoint` every ``save_freq`` environment steps, with the complete replay buffer.

        SB3's ``CheckpointCallback`` saves in ``on_step``, which SB3 calls before it stores the
        step's transition, so its buffer would lack the newest one; ``on_rollout_end`` comes after.
        """

        def _on_training_start(self) -> None:
            self.next_save = (self.num_timesteps // save_freq + 1) * save_freq

        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            if self.num_timesteps >= self.next_save:
                save_checkpoint(self.model, folder)
                self.next_save = (self.num_timesteps // save_freq + 1) * save_freq

    return CompleteCheckpoint()


def _load_weights(model, path: str) -> None:
    # SB3's set_parameters reads only the zip's .pth files, with torch.load(weights_only=True).
    if not Path(path).is_file():
        raise UserError(f"--init-weights: no such file {path!r}")
    try:
        model.set_parameters(path, exact_match=True, device=model.device)
    except Exception as error:  # a zip of another architecture, or not a model at all
        raise UserError(f"--init-weights: cannot load the weights of {path!r}: {error}") from error


def _import_packages(names: list[str]) -> None:
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError as error:
            raise UserError(f"--gym-packages: cannot import {name!r}: {error}") from error


def _make_env(env_id: str, n_envs: int, seed: int, env_kwargs: dict[str, Any]):
    import gymnasium as gym
    from stable_baselines3.common.env_util import make_vec_env

    if env_id not in gym.registry:
        raise UserError(f"--env: unknown environment id {env_id!r} (registered by --gym-packages?)")
    try:
        return make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs)
    except ValueError as error:  # the environment's own configuration check
        raise UserError(f"env_kwargs: {error}") from error


def _resume_entry(args: argparse.Namespace, out: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The entry and the run record of the run in ``out`` (``--resume``); sets ``args.algo`` to the run's."""
    config_path = out / "config.yml"
    if not config_path.is_file():
        raise UserError(f"--resume: {str(out)!r} holds no run (no config.yml)")
    entry = yaml.safe_load(config_path.read_text())
    record_path = out / "run.json"
    if record_path.is_file():
        record = json.loads(record_path.read_text())
    else:  # a run killed before it wrote its record: start one, say so
        print(f"sb3-graph train: {record_path} is missing; recording seed {args.seed}", file=sys.stderr)
        record = _new_record(args, args.seed)
    recorded = record.get("algo", "td3")  # runs recorded before --algo were TD3 runs
    if args.algo is not None and args.algo != recorded:
        raise UserError(f"--algo: the run in {str(out)!r} is a {recorded} run, got --algo {args.algo}")
    args.algo = recorded
    if args.n_timesteps is not None:  # extend (or shorten) a run; recorded in config.yml
        entry["n_timesteps"] = args.n_timesteps
        config_path.write_text(yaml.safe_dump(entry, sort_keys=False))
    return entry, record


def _new_entry(args: argparse.Namespace, out: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The entry of ``--config`` with the command line's overrides, and a fresh run record."""
    from sb3_graph.experiment import ExperimentError, read_experiment

    if out.exists() and any(out.iterdir()):
        raise UserError(f"--out: {str(out)!r} already holds files; choose a new folder or pass --resume")
    try:
        entry = read_experiment(args.config, args.env)
    except ExperimentError as error:
        raise UserError(str(error)) from error
    entry.update(parse_overrides(args.hyperparams))
    if args.n_timesteps is not None:
        entry["n_timesteps"] = args.n_timesteps
    if args.env_kwargs:
        entry["env_kwargs"] = {**(entry.get("env_kwargs") or {}), **args.env_kwargs}
    args.algo = args.algo or "td3"
    return entry, _new_record(args, args.seed)


def _build_model(args, entry, algo_kwargs, train_env, out, seed, tensorboard_log):
    """The model of a checkpoint of the run (with its replay buffer), or a new one; and the
    checkpoint's step count (``None`` for a new model)."""
    algorithm = getattr(importlib.import_module("sb3_graph"), ALGORITHMS[args.algo])
    checkpoint = latest_checkpoint(out) if args.resume else None
    if checkpoint is not None:
        steps, path = checkpoint
        model = algorithm.load(path, env=train_env, device=args.device, tensorboard_log=tensorboard_log)
        buffer_path = out / "checkpoints" / f"model_replay_buffer_{steps}_steps.pkl"
        if buffer_path.is_file() and getattr(model, "replay_buffer", None) is not None:
            model.load_replay_buffer(buffer_path)
        return model, steps
    if args.resume:
        print(f"sb3-graph train: no checkpoint in {out}, starting the run again", file=sys.stderr)
    policy = entry.get("policy", "GraphPolicy")
    if isinstance(policy, str) and "." in policy:
        from sb3_graph.experiment import resolve_object

        policy = resolve_object(policy, "policy")
    try:
        model = algorithm(
            policy,
            train_env,
            seed=seed,
            device=args.device,
            verbose=args.verbose,
            tensorboard_log=tensorboard_log,
            **algo_kwargs,
        )
    except (TypeError, ValueError) as error:
        raise UserError(f"hyperparameters of {args.env!r} for {args.algo}: {error}") from error
    if args.init_weights:
        _load_weights(model, args.init_weights)
    return model, None


def _learn(args, model, callbacks, remaining: int, resumed: bool, record: dict[str, Any], out: Path) -> bool:
    """Train for ``remaining`` steps; always leave a checkpoint and the updated record. True when
    interrupted (Ctrl-C or SIGTERM)."""
    _interrupt_on_sigterm()
    start = time.time()
    interrupted = False
    try:
        if remaining > 0:
            model.learn(
                remaining,
                callback=callbacks,
                reset_num_timesteps=not resumed,
                progress_bar=not args.no_progress,
                tb_log_name=ALGORITHMS[args.algo],
            )
    except KeyboardInterrupt:
        interrupted = True
    finally:
        save_checkpoint(model, out / "checkpoints")
        elapsed = time.time() - start
        record["wall_time_s"] = record.get("wall_time_s", 0.0) + elapsed
        record["num_timesteps"] = int(model.num_timesteps)
        record["sessions"].append({"started": start, "wall_time_s": elapsed, "steps_until": int(model.num_timesteps)})
    return interrupted


def run(args: argparse.Namespace) -> int:
    import torch as th
    from stable_baselines3.common.callbacks import CallbackList, EvalCallback

    from sb3_graph.experiment import ExperimentError, build_algorithm_kwargs, build_callbacks

    for flag in ("eval_freq", "eval_episodes", "checkpoint_freq", "threads"):
        if getattr(args, flag) < 1:
            raise UserError(f"--{flag.replace('_', '-')} must be at least 1, got {getattr(args, flag)}")
    th.set_num_threads(args.threads)
    out = Path(args.out)
    entry, record = _resume_entry(args, out) if args.resume else _new_entry(args, out)
    seed = record["seed"] if args.resume else args.seed

    _import_packages(args.gym_packages)
    n_timesteps = int(float(entry["n_timesteps"]))
    n_envs = int(entry.get("n_envs", 1))
    env_kwargs = dict(entry.get("env_kwargs") or {})
    train_env = _make_env(args.env, n_envs, seed, env_kwargs)
    # Validation: built the same way, another seed (paper, "Experiments").
    eval_env = _make_env(args.env, 1, seed + VALIDATION_SEED_OFFSET, env_kwargs)
    try:
        algo_kwargs = build_algorithm_kwargs(entry, int(np.prod(train_env.action_space.shape)))
        user_callbacks = build_callbacks(entry)
    except ExperimentError as error:
        raise UserError(str(error)) from error

    out.mkdir(parents=True, exist_ok=True)
    if not args.resume:
        (out / "config.yml").write_text(yaml.safe_dump(entry, sort_keys=False))
    (out / "run.json").write_text(json.dumps(record, indent=2))
    tensorboard_log = str(out / "tb") if importlib.util.find_spec("tensorboard") else None
    model, checkpoint_steps = _build_model(args, entry, algo_kwargs, train_env, out, seed, tensorboard_log)
    if args.init_weights and checkpoint_steps is None:
        record["init_weights"] = str(args.init_weights)

    eval_callback = EvalCallback(
        eval_env,
        n_eval_episodes=args.eval_episodes,
        eval_freq=max(args.eval_freq // n_envs, 1),
        best_model_save_path=str(out),
        log_path=str(out),
        deterministic=True,
        verbose=args.verbose,
    )
    # A resumed run keeps its best model unless a validation beats it.
    eval_callback.best_mean_reward = record.get("best_mean_reward", -np.inf)
    checkpoint_callback = _make_checkpoint_callback(args.checkpoint_freq, out / "checkpoints")
    callbacks = CallbackList([*user_callbacks, eval_callback, checkpoint_callback])
    try:
        remaining = n_timesteps - model.num_timesteps
        interrupted = _learn(args, model, callbacks, remaining, checkpoint_steps is not None, record, out)
    finally:
        record["best_mean_reward"] = float(eval_callback.best_mean_reward)
        (out / "run.json").write_text(json.dumps(record, indent=2))
        train_env.close()
        eval_env.close()
    if interrupted:
        print(f"sb3-graph train: interrupted at step {model.num_timesteps}; continue with --resume", file=sys.stderr)
        return 130
    model.save(out / "final_model.zip")
    print(f"sb3-graph train: {model.num_timesteps} steps in {record['wall_time_s']:.0f} s, run folder {out}")
    return 0
