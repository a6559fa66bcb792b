"""``sb3-graph train``: run one rl-zoo3 style experiment into a run folder, resumable.

A run folder holds::

    config.yml          the experiment entry as resolved (file entry + command-line overrides)
    run.json            seed, versions, command, steps, wall time, best validation reward
    best_model.zip      the model with the best validation reward so far (paper: "Experiments")
    evaluations.npz     every validation result (SB3 EvalCallback's log; the same episodes each time)
    checkpoints/        model_<steps>_steps.zip and the latest replay buffer, for --resume, with
                        signatures.json (see below)
    final_model.zip     the model at the end of training
    tb/                 TensorBoard logs (reward terms, curriculum, losses)

Checkpoints are pickles (SB3's format): ``--resume`` loads only checkpoint files that this
machine's ``sb3-graph train`` signed when it wrote them (:mod:`sb3_graph.files.signing`), so a run
folder from elsewhere cannot run code here; ``--trust-run-files`` loads unsigned ones (runs made
before signatures existed, or your own run copied from another machine). The stored
``config.yml`` is read like any experiment file, without evaluating code.

``--seeds 0 1 2`` trains one such run per seed into ``OUT/seed_0``, ``OUT/seed_1``, ... (one
after the other; no existing seed folder is overwritten, ``--resume`` continues them);
``sb3-graph aggregate`` summarizes runs over seeds and scenarios.

A fresh run that fails before its first checkpoint leaves no run folder behind, and ``--resume``
of a folder without checkpoints reads ``--config`` again: a run that failed on a wrong value is
rerun with the same command once the file is fixed.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import platform
import re
import shutil
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sb3_graph.commands import UserError
from sb3_graph.commands.arguments import json_object, seed_value
from sb3_graph.common.experts import PRETRAIN_STEPS, PRETRAIN_TRANSITIONS, ExpertError, make_expert
from sb3_graph.registry import ALGORITHMS

CHECKPOINT_PATTERN = re.compile(r"model_(\d+)_steps\.zip$")
# Said when TensorBoard is missing (it is not in the base install): the run goes on without tb/.
TENSORBOARD_MISSING = (
    "TensorBoard is not installed, so this run writes no tb/ logs (pip install tensorboard, or pip install "
    "'sb3-graph[zoo]'); the validation results go to evaluations.npz either way"
)
# What a finished run folder may hold, in the order listed after a run (see the module docstring).
RUN_FILES = ("best_model.zip", "final_model.zip", "evaluations.npz", "checkpoints", "tb", "callbacks", "config.yml",
             "run.json")  # fmt: skip
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
    parser.add_argument("--n-timesteps", type=int, default=None, help="override n_timesteps of the entry (>= 1)")
    parser.add_argument(
        "--seed", type=seed_value, default=None, help="seed of the training envs and the learner (>= 0, default 0)"
    )
    parser.add_argument(
        "--seeds",
        type=seed_value,
        nargs="+",
        default=None,
        metavar="SEED",
        help="train one run per seed, one after the other, into OUT/seed_<SEED> (instead of --seed); "
        "with --resume, runs that exist continue and missing ones start",
    )
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    parser.add_argument(
        "--trust-run-files",
        action="store_true",
        help="with --resume: load checkpoints that this machine did not sign (they are pickles: your own runs only)",
    )
    parser.add_argument("--eval-freq", type=int, default=5000, help="steps between validations (paper: 5000)")
    parser.add_argument("--eval-episodes", type=int, default=10, help="validation episodes (paper: 10)")
    parser.add_argument("--checkpoint-freq", type=int, default=10_000, help="steps between checkpoints")
    parser.add_argument(
        "--gym-packages",
        nargs="*",
        default=None,
        help="modules to import so that they register their environments (default: those of the installed "
        "domains, their sb3_graph.gym_packages entry points; the repository's intersection package)",
    )
    parser.add_argument(
        "--env-kwargs",
        type=json_object,
        default=None,
        help="JSON object merged into the entry's env_kwargs (one level deep: keys of 'config' are merged)",
    )
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
        help="start from the network weights of a saved model .zip or a .safetensors policy file (fine-tuning; "
        "read as tensors only, the architecture must match); recorded in run.json",
    )
    parser.add_argument(
        "--pretrain-from",
        default=None,
        metavar="PLANNER",
        help="clone this expert before training (sb3_graph.behaviour_clone): for the intersection envs any planner "
        "word of evaluate (aim, fifo, pr, fullthrottle, file.py:Class...), for the toy task 'exact'; the entry "
        "key pretrain_from",
    )
    parser.add_argument(
        "--pretrain-transitions",
        type=int,
        default=None,
        metavar="N",
        help=f"environment steps of demonstrations (default {PRETRAIN_TRANSITIONS}; entry key pretrain_transitions)",
    )
    parser.add_argument(
        "--pretrain-steps",
        type=int,
        default=None,
        metavar="M",
        help=f"gradient steps of cloning (default {PRETRAIN_STEPS}; entry key pretrain_steps; the critics' warm-up, "
        "off-policy, takes pretrain_critic_steps, default M // 4)",
    )
    parser.add_argument(
        "--pretrain-cache",
        default=None,
        metavar="FOLDER",
        help="keep the cloning's labelled transitions and the cloned model in FOLDER, under a hash of everything "
        "they depend on, and reuse them when a fresh run asks for the same (a costly expert labels once)",
    )
    parser.add_argument(
        "--label-jobs",
        type=int,
        default=None,
        metavar="N",
        help="label the cloning's rounds on N parallel workers, one job per sub-environment and round, each kept in "
        "--pretrain-cache as it comes (a run cut short labels only what it lacks; every round starts new episodes)",
    )
    parser.add_argument(
        "--label-executor",
        default=None,
        choices=("local", "dask", "ray"),
        help="where --label-jobs run: local processes (default), a Dask cluster or Ray, as evaluate's --executor",
    )
    parser.add_argument(
        "--label-address", default=None, metavar="ADDRESS", help="the Dask scheduler or Ray cluster to label on"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (see benchmarks/)")
    parser.add_argument("--device", default="auto", help="torch device (auto, cpu, cuda)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--verbose", type=int, default=0, choices=(0, 1, 2))


def parse_overrides(items: list[str], flag: str = "--hyperparams") -> dict[str, Any]:
    """``["batch_size:64", "gamma:0.9"]`` -> ``{"batch_size": 64, "gamma": 0.9}`` (values as YAML).

    :param items: ``KEY:VALUE`` strings
    :param flag: the option named in errors
    """
    from sb3_graph.files.safe_values import UnsafeValueError, load_yaml

    overrides = {}
    for item in items:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise UserError(f"{flag}: expected KEY:VALUE, got {item!r}")
        try:
            overrides[key] = load_yaml(value, f"{flag} {key}")
        except UnsafeValueError as error:
            raise UserError(f"{error} (in {item[:60]!r})") from None
    return overrides


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in ("sb3_graph", "stable_baselines3", "torch", "torch_geometric", "gymnasium", "highway_env", "numpy"):
        try:
            versions[name] = getattr(importlib.import_module(name), "__version__", "unknown")
        except ImportError:
            continue
    return versions


def portable_path(text: str) -> str:
    """A path as it may be recorded in a run record: relative to the working folder where it lies
    below it, ``~/...`` below the home folder (no user's folder in a shared record), else as typed
    (a record that names another folder than the one typed would not rerun)."""
    path = Path(text)
    if not path.is_absolute():
        return text
    for base, prefix in ((Path.cwd(), ""), (Path.home(), "~/")):
        try:
            return prefix + str(path.relative_to(base))
        except ValueError:
            continue
    return text


def portable_command(argv: list[str]) -> str:
    """The command line for the run record: ``sb3-graph`` instead of the executable's path, and
    every absolute path argument made :func:`portable_path`."""
    program = Path(argv[0]).name if argv else "sb3-graph"
    if program in ("cli.py", "__main__.py") or program.startswith("python"):
        program = "sb3-graph"
    return " ".join([program, *(_portable_argument(item) for item in argv[1:])])


def _portable_argument(item: str) -> str:
    if item.startswith("--") and "=" in item:
        flag, _, value = item.partition("=")
        return f"{flag}={portable_path(value)}"
    return portable_path(item)


def _new_record(args: argparse.Namespace, seed: int) -> dict[str, Any]:
    return {
        "algo": args.algo or "td3",
        "env": args.env,
        "config_file": portable_path(str(args.config)),
        "seed": seed,
        "command": portable_command(list(getattr(args, "argv", None) or sys.argv)),
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
    """Save the model and its replay buffer as ``model_<steps>_steps``, each signed (see
    :mod:`sb3_graph.files.signing`); drop older replay buffers."""
    from sb3_graph.files.signing import sign

    folder.mkdir(parents=True, exist_ok=True)
    steps = model.num_timesteps
    path = folder / f"model_{steps}_steps.zip"
    model.save(path)
    sign(path)
    if getattr(model, "replay_buffer", None) is None:  # on-policy: nothing to carry over
        return
    newest = folder / f"model_replay_buffer_{steps}_steps.pkl"
    model.save_replay_buffer(newest)
    sign(newest)
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


def _import_packages(names: list[str] | None) -> None:
    """Import the ``--gym-packages`` (default: every installed domain's, see :mod:`sb3_graph.plugins`)."""
    if names is None:
        from sb3_graph.plugins import gym_packages

        names = gym_packages()
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
    except (TypeError, ValueError) as error:  # the environment's own configuration check
        raise UserError(f"env_kwargs of {env_id!r}: {error}") from error


def _check_flags(args: argparse.Namespace) -> None:
    from sb3_graph.commands.arguments import check_device

    for flag in ("eval_freq", "eval_episodes", "checkpoint_freq", "threads"):
        if getattr(args, flag) < 1:
            raise UserError(f"--{flag.replace('_', '-')} must be at least 1, got {getattr(args, flag)}")
    if args.n_timesteps is not None and args.n_timesteps < 1:
        raise UserError(f"--n-timesteps must be at least 1, got {args.n_timesteps}")
    if args.seed is not None and args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    if args.trust_run_files and not args.resume:
        raise UserError("--trust-run-files applies to --resume only")
    if args.pretrain_cache is not None and args.resume:
        raise UserError("--pretrain-cache applies to a fresh run, not --resume (a resumed run has cloned already)")
    pretrain = {flag: getattr(args, flag, None) for flag in ("pretrain_from", "pretrain_transitions", "pretrain_steps")}
    if args.resume and any(value is not None for value in pretrain.values()):
        raise UserError("--pretrain-from/--pretrain-transitions/--pretrain-steps apply to a fresh run, not --resume")
    for flag, low in (("pretrain_transitions", 1), ("pretrain_steps", 0)):
        if pretrain[flag] is not None and pretrain[flag] < low:
            raise UserError(f"--{flag.replace('_', '-')} must be at least {low}, got {pretrain[flag]}")
    _check_labelling(args)
    check_device(args.device)


def _entry_from_file(args: argparse.Namespace) -> dict[str, Any]:
    """The entry of ``--env`` in ``--config`` with the command line's overrides, checked."""
    from sb3_graph.files.experiment_files import ExperimentError, check_entry, merge_env_kwargs, read_experiment

    try:
        entry = read_experiment(args.config, args.env)
        entry.update(parse_overrides(args.hyperparams))
        if args.n_timesteps is not None:
            entry["n_timesteps"] = args.n_timesteps
        for key in ("pretrain_from", "pretrain_transitions", "pretrain_steps"):
            if getattr(args, key, None) is not None:
                entry[key] = getattr(args, key)
        if args.env_kwargs:
            if entry.get("env_kwargs") is not None and not isinstance(entry["env_kwargs"], dict):
                raise ExperimentError(f"env_kwargs must be a mapping, got {entry['env_kwargs']!r}")
            entry["env_kwargs"] = merge_env_kwargs(entry.get("env_kwargs") or {}, args.env_kwargs)
        return check_entry(entry)
    except ExperimentError as error:
        raise UserError(str(error)) from None


def _check_links(out: Path) -> None:
    from sb3_graph.files.output_folders import OutputError, check_no_links

    written = ("checkpoints", "tb", "callbacks", "config.yml", "run.json", "signatures.json", "best_model.zip",
               "evaluations.npz", "final_model.zip")  # fmt: skip
    try:
        check_no_links(out, written, "--resume")
    except OutputError as error:
        raise UserError(str(error)) from None


def _stored_record(record_path: Path, trust: bool) -> dict[str, Any] | None:
    """The run record (``run.json``) if there is one, signed (unless ``trust``) and checked."""
    from sb3_graph.files.experiment_files import ExperimentError, check_run_record
    from sb3_graph.files.safe_values import UnsafeValueError, load_json, read_text_file
    from sb3_graph.files.signing import SignatureError, verify_run_file

    if not record_path.exists() and not record_path.is_symlink():
        return None
    try:
        verify_run_file(record_path, trust)
        record = load_json(read_text_file(record_path, "--resume"), f"--resume: {record_path}")
        return check_run_record(record, list(ALGORITHMS), f"--resume: {record_path}")
    except (SignatureError, UnsafeValueError, ExperimentError) as error:
        raise UserError(str(error)) from None


def _stored_entry(config_path: Path, n_timesteps: int | None, trust: bool = False) -> dict[str, Any]:
    """The entry a run folder recorded (``config.yml``), signed (unless ``trust``) and checked like a
    file entry (its expressions are read safely too, though the checkpoint holds the model)."""
    from sb3_graph.files.experiment_files import ExperimentError, build_algorithm_kwargs, check_entry
    from sb3_graph.files.safe_values import UnsafeValueError, load_yaml, read_text_file
    from sb3_graph.files.signing import SignatureError, verify_run_file

    try:
        verify_run_file(config_path, trust)
        entry = load_yaml(read_text_file(config_path, "--resume"), f"--resume: {config_path}")
    except (SignatureError, UnsafeValueError) as error:
        raise UserError(str(error)) from None
    if not isinstance(entry, dict):
        raise UserError(f"--resume: {config_path} is not a mapping of hyperparameters")
    if n_timesteps is not None:  # extend (or shorten) a run; recorded in config.yml
        entry["n_timesteps"] = n_timesteps
    try:
        entry = check_entry(entry)
        build_algorithm_kwargs(entry, 1)
    except ExperimentError as error:
        raise UserError(f"{config_path}: {error}") from None
    return entry


def _algorithm(args: argparse.Namespace):
    return ALGORITHMS[args.algo].load_class()


def _load_weights(model, path: str) -> None:
    # SB3's set_parameters reads only the zip's .pth files, with torch.load(weights_only=True); a
    # .safetensors policy file is tensors by construction (sb3_graph.files.policy_files).
    if not Path(path).is_file():
        raise UserError(f"--init-weights: file not found: {path!r}")
    if Path(path).suffix == ".safetensors":
        from sb3_graph.files.policy_files import PolicyFileError, init_from_file

        try:
            init_from_file(model.policy, path)
        except PolicyFileError as error:
            raise UserError(f"--init-weights: {error}") from None
        return
    try:
        model.set_parameters(path, exact_match=True, device=model.device)
    except Exception as error:  # a zip of another architecture, or not a model at all
        raise UserError(f"--init-weights: cannot load the weights of {path!r}: {error}") from error
    from sb3_graph.files.policy_kwargs import PolicyKwargsError, check_finite_weights

    try:
        check_finite_weights(model.policy, f"--init-weights: {path}")
    except PolicyKwargsError as error:
        raise UserError(str(error)) from None


def _load_checkpoint(path: Path, buffer_path: Path, trust: bool, algorithm, **load_kwargs):
    """Load a checkpoint and its replay buffer, each only if this machine signed it (or ``trust``)."""
    from sb3_graph.files.signing import SignatureError, verify

    if not trust:
        for file in (path, buffer_path) if buffer_path.is_file() else (path,):
            try:
                verify(file)
            except SignatureError as error:
                raise UserError(
                    f"--resume: {error}; it is a pickle and is not loaded (--trust-run-files loads it: "
                    "only for your own run, e.g. one copied from another machine of yours)"
                ) from None
    model = algorithm.load(path, **load_kwargs)
    if buffer_path.is_file() and getattr(model, "replay_buffer", None) is not None:
        model.load_replay_buffer(buffer_path)
    return model


def _build_model(entry: dict[str, Any], train_env, seed: int, args: argparse.Namespace, tensorboard_log):
    from sb3_graph.files.experiment_files import (
        ExperimentError,
        build_algorithm_kwargs,
        check_algorithm_keys,
        resolve_object,
    )

    try:
        algo_kwargs = build_algorithm_kwargs(entry, int(np.prod(train_env.action_space.shape)))
        check_algorithm_keys(algo_kwargs, _algorithm(args))  # a typo (learnig_rate) named, with the closest key
        policy = entry.get("policy", "GraphPolicy")
        if isinstance(policy, str) and "." in policy:
            policy = resolve_object(policy, "policy")
    except ExperimentError as error:
        raise UserError(str(error)) from None
    try:
        model = _algorithm(args)(
            policy,
            train_env,
            seed=seed,
            device=args.device,
            verbose=args.verbose,
            tensorboard_log=tensorboard_log,
            **algo_kwargs,
        )
    except (TypeError, ValueError, KeyError, AssertionError) as error:
        raise UserError(f"hyperparameters of {args.env!r} for {args.algo}: {error}") from None
    if args.init_weights:
        _load_weights(model, args.init_weights)
    return model


def _labelling(args: argparse.Namespace) -> dict[str, Any] | None:
    """The sharded labelling's settings (``--label-jobs``/``--label-executor``/``--label-address``), or ``None``."""
    flags = [getattr(args, name, None) for name in ("label_jobs", "label_executor", "label_address")]
    if all(flag is None for flag in flags):
        return None
    workers = 1 if args.label_jobs is None else args.label_jobs
    return {"seed": args.seed, "executor": args.label_executor or "local", "workers": workers,
            "address": args.label_address}  # fmt: skip


def _check_labelling(args: argparse.Namespace) -> None:
    from sb3_graph.common.executors import ExecutorError, check_executor

    labelling = _labelling(args)
    if labelling is None:
        return
    if args.resume:
        raise UserError("--label-jobs/--label-executor/--label-address apply to a fresh run, not --resume")
    if labelling["workers"] < 1:
        raise UserError(f"--label-jobs must be at least 1, got {labelling['workers']}")
    try:
        check_executor(labelling["executor"], labelling["address"])
    except (ExecutorError, ValueError) as error:
        raise UserError(str(error).replace("--executor", "--label-executor").replace(
            "--scheduler-address", "--label-address")) from None  # fmt: skip


def _make_expert(spec: str, env_id: str, train_env) -> Any:
    """:func:`sb3_graph.common.experts.make_expert`, a refused spec a :class:`UserError`."""
    try:
        return make_expert(spec, env_id, train_env)
    except ExpertError as error:
        raise UserError(str(error)) from None


def _pretrain(
    model,
    entry: dict[str, Any],
    env_id: str,
    train_env,
    cache: str | None = None,
    algo: str = "td3",
    labelling: dict[str, Any] | None = None,
) -> dict[str, Any] | None:
    """Clone the entry's ``pretrain_from`` expert into the model (nothing without one); its summary.
    With ``cache`` (a folder) the labelled transitions and the clone are kept and reused there; with
    ``labelling`` the rounds are labelled on an executor (:mod:`sb3_graph.common.labelling`)."""
    from sb3_graph.common.cloning import behaviour_clone
    from sb3_graph.tuning.pretrain import dagger_arguments, pretrain_trial

    spec = entry.get("pretrain_from")
    if spec is None:
        if labelling is not None:
            raise UserError("--label-jobs/--label-executor/--label-address label a cloning: the entry has no "
                            "pretrain_from (set it, or --pretrain-from)")  # fmt: skip
        return None
    try:
        if labelling is not None:
            where = f"{labelling['executor']}, {labelling['workers']} worker{'s' * (labelling['workers'] != 1)}"
            print(f"sb3-graph train: cloning {spec!r}, labelled on {where}"
                  + (f", through the cache {cache}" if cache is not None else ""), flush=True)  # fmt: skip
            return pretrain_trial(model, entry, env_id, train_env, algo, None if cache is None else Path(cache),
                                  labelling=labelling)  # fmt: skip
        if cache is not None:
            print(f"sb3-graph train: cloning {spec!r} through the cache {cache}", flush=True)
            return pretrain_trial(model, entry, env_id, train_env, algo, Path(cache))
    except ExpertError as error:
        raise UserError(str(error)) from None
    expert = _make_expert(str(spec), env_id, train_env)
    transitions = int(entry.get("pretrain_transitions", PRETRAIN_TRANSITIONS))
    steps = int(entry.get("pretrain_steps", PRETRAIN_STEPS))
    critic_steps = entry.get("pretrain_critic_steps")
    print(f"sb3-graph train: cloning {spec!r}: {transitions} transitions, {steps} gradient steps", flush=True)
    result = behaviour_clone(
        model,
        expert,
        transitions=transitions,
        gradient_steps=steps,
        batch_size=int(getattr(model, "batch_size", 256) or 256),
        critic_steps=None if critic_steps is None else int(critic_steps),
        **dagger_arguments(entry),
    )
    summary = {
        "from": str(spec),
        "transitions": result["transitions"],
        "gradient_steps": steps,
        "critic_steps": len(result["critic_loss"]),
        "actor_loss_first": result["actor_loss"][0] if result["actor_loss"] else None,
        "actor_loss_last": result["actor_loss"][-1] if result["actor_loss"] else None,
        "critic_loss_last": result["critic_loss"][-1] if result["critic_loss"] else None,
        "collect_s": round(result["collect_s"], 2),
        "train_s": round(result["train_s"] + result["critic_s"], 2),
    }
    print(f"sb3-graph train: cloned in {summary['collect_s'] + summary['train_s']:.0f} s, actor loss "
          f"{summary['actor_loss_first']} -> {summary['actor_loss_last']}", flush=True)  # fmt: skip
    return summary


def _discard(out: Path, created: bool) -> None:
    """Remove what a failed fresh run wrote: the folder if the run made it, else its contents."""
    if created:
        shutil.rmtree(out, ignore_errors=True)
        return
    for item in out.iterdir():
        shutil.rmtree(item, ignore_errors=True) if item.is_dir() else item.unlink(missing_ok=True)


def short_run_warnings(
    n_timesteps: int, done: int, learning_starts: int | None, eval_freq: int
) -> list[str]:
    """What a run of ``n_timesteps`` steps will silently not do: gradient steps, validations.

    :param n_timesteps: the run's total steps (``n_timesteps`` of the entry or ``--n-timesteps``)
    :param done: steps already trained (a resumed run)
    :param learning_starts: the algorithm's ``learning_starts`` (``None``: an on-policy algorithm)
    :param eval_freq: ``--eval-freq``
    :return: one sentence per problem, naming the setting to change
    """
    warnings = []
    if learning_starts is not None and n_timesteps <= learning_starts:
        warnings.append(
            f"n_timesteps {n_timesteps} <= learning_starts {learning_starts}: no gradient step will run, the "
            f"model stays untrained (more steps, or e.g. -params learning_starts:{max(n_timesteps // 4, 1)})"
        )
    if eval_freq > n_timesteps and done < eval_freq:
        warnings.append(
            f"n_timesteps {n_timesteps} < --eval-freq {eval_freq}: no validation will run, so no best_model.zip "
            f"and no best_mean_reward (more steps, or e.g. --eval-freq {max(n_timesteps // 2, 1)})"
        )
    return warnings


def seed_folder(out: str | Path, seed: int) -> Path:
    """The run folder of ``seed`` in a ``--seeds`` run: ``OUT/seed_<seed>``."""
    return Path(out) / f"seed_{seed}"


def run(args: argparse.Namespace) -> int:
    """Run the command: one run (``--seed``) or one per seed (``--seeds``)."""
    if getattr(args, "seeds", None) is None:
        if args.seed is None:
            args.seed = 0
        return _run_one(args)
    return _run_seeds(args)


def _run_seeds(args: argparse.Namespace) -> int:
    """One run per seed into ``OUT/seed_<seed>``; nothing that exists is overwritten.

    Every seed folder is checked before the first run starts, so a mistake does not surface after
    hours of training. The runs go one after the other (the learner is single-process; two runs at
    once on a small machine only share its cores). The first run that does not end normally (an
    interrupt: exit 130) stops the loop; ``--resume`` continues from there.
    """
    import copy

    _check_flags(args)
    if args.seed is not None:
        raise UserError("--seed and --seeds exclude each other: give the seeds with --seeds only")
    seeds = list(args.seeds)
    if any(seed < 0 for seed in seeds):
        raise UserError(f"--seeds must be >= 0, got {seeds}")
    if len(set(seeds)) != len(seeds):
        raise UserError(f"--seeds: each seed once, got {seeds}")
    folders = {seed: seed_folder(args.out, seed) for seed in seeds}
    if not args.resume:
        busy = [str(f) for f in folders.values() if f.exists() and (not f.is_dir() or any(f.iterdir()))]
        if busy:
            raise UserError(f"--out: {', '.join(busy)} already hold files; choose a new --out or pass --resume")
    for seed, folder in folders.items():
        one = copy.copy(args)
        one.seeds, one.seed, one.out = None, seed, str(folder)
        # --resume continues the runs that exist and starts the missing ones (a loop cut short)
        one.resume = bool(args.resume and (folder / "config.yml").is_file())
        one.trust_run_files = args.trust_run_files and one.resume
        print(f"sb3-graph train: seed {seed} -> {folder}", flush=True)
        status = _run_one(one)
        if status:
            return status
    return 0


def _run_one(args: argparse.Namespace) -> int:
    import torch as th
    from stable_baselines3.common.callbacks import CallbackList

    from sb3_graph.callbacks import FixedEpisodesEvalCallback
    from sb3_graph.files.experiment_files import ExperimentError, build_callbacks
    from sb3_graph.files.signing import write_signed

    _check_flags(args)
    th.set_num_threads(args.threads)
    out = Path(args.out)
    config_path = out / "config.yml"
    checkpoint = None
    if args.resume:
        if not config_path.is_file():
            raise UserError(f"--resume: {str(out)!r} holds no run (no config.yml)")
        _check_links(out)
        checkpoint = latest_checkpoint(out)
        record = _stored_record(out / "run.json", args.trust_run_files)
        if record is None:
            # a run killed before it wrote its record: start one, say so
            print(f"sb3-graph train: no {out / 'run.json'}; recording seed {args.seed}", file=sys.stderr)
            record = _new_record(args, args.seed)
        record.setdefault("sessions", [])
        recorded = record.get("algo", "td3")  # runs recorded before --algo were TD3 runs
        if args.algo is not None and args.algo != recorded:
            raise UserError(f"--algo: the run in {str(out)!r} is a {recorded} run, got --algo {args.algo}")
        args.algo = recorded
        seed = record["seed"]
        if checkpoint is None:  # nothing trained yet: the run starts again, from the (fixed) file
            print(f"sb3-graph train: no checkpoint in {out}, starting again from {args.config}", file=sys.stderr)
            entry = _entry_from_file(args)
        else:
            entry = _stored_entry(config_path, args.n_timesteps, args.trust_run_files)
        created = False
    else:
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise UserError(f"--out: {str(out)!r} already holds files; choose a new folder or pass --resume")
        args.algo = args.algo or "td3"
        entry = _entry_from_file(args)
        seed = args.seed
        record = _new_record(args, seed)
        created = not out.exists()

    _import_packages(args.gym_packages)
    n_timesteps = int(entry["n_timesteps"])
    n_envs = int(entry.get("n_envs", 1))
    env_kwargs = dict(entry.get("env_kwargs") or {})
    train_env = _make_env(args.env, n_envs, seed, env_kwargs)
    # Validation: built the same way, another seed (paper, "Experiments").
    eval_env = _make_env(args.env, 1, seed + VALIDATION_SEED_OFFSET, env_kwargs)
    try:
        user_callbacks = build_callbacks(entry, out)
    except ExperimentError as error:
        raise UserError(str(error)) from None
    tensorboard_log = str(out / "tb") if importlib.util.find_spec("tensorboard") else None
    if tensorboard_log is None:
        print(f"sb3-graph train: note: {TENSORBOARD_MISSING}", file=sys.stderr, flush=True)
    if checkpoint is not None:
        steps, path = checkpoint
        buffer_path = out / "checkpoints" / f"model_replay_buffer_{steps}_steps.pkl"
        model = _load_checkpoint(
            path,
            buffer_path,
            args.trust_run_files,
            _algorithm(args),
            env=train_env,
            device=args.device,
            tensorboard_log=tensorboard_log,
        )
        if entry.get("pretrain_from") is not None and getattr(model, "rollout_buffer", None) is not None:
            # an on-policy bc_coef labels its rollouts with the expert (not saved with the model)
            model.bc_expert = _make_expert(str(entry["pretrain_from"]), args.env, train_env)
    else:
        model = _build_model(entry, train_env, seed, args, tensorboard_log)
        if args.init_weights:
            record["init_weights"] = str(args.init_weights)
        pretrained = _pretrain(model, entry, args.env, train_env, args.pretrain_cache, args.algo, _labelling(args))
        if pretrained is not None:
            record["pretrain"] = pretrained

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UserError(f"--out: cannot create {str(out)!r}: {error.strerror or error}") from None
    if checkpoint is None:
        write_signed(config_path, yaml.safe_dump(entry, sort_keys=False))
    write_signed(out / "run.json", json.dumps(record, indent=2))

    eval_callback = FixedEpisodesEvalCallback(
        eval_env,
        seed=seed + VALIDATION_SEED_OFFSET,
        n_eval_episodes=args.eval_episodes,
        eval_freq=max(args.eval_freq // n_envs, 1),
        best_model_save_path=str(out),
        log_path=str(out),
        deterministic=True,
        verbose=max(args.verbose, 1),  # the validation scores on the console
    )
    # A resumed run keeps its best model unless a validation beats it.
    best = record.get("best_mean_reward")
    eval_callback.best_mean_reward = -np.inf if best is None else float(best)
    for warning in short_run_warnings(n_timesteps, model.num_timesteps, getattr(model, "learning_starts", None),
                                      args.eval_freq):  # fmt: skip
        print(f"sb3-graph train: warning: {warning}", file=sys.stderr, flush=True)
    checkpoint_callback = _make_checkpoint_callback(args.checkpoint_freq, out / "checkpoints")
    callbacks = CallbackList([*user_callbacks, eval_callback, checkpoint_callback])

    remaining = n_timesteps - model.num_timesteps
    _interrupt_on_sigterm()
    start = time.time()
    interrupted = False
    try:
        if remaining > 0:
            model.learn(
                remaining,
                callback=callbacks,
                reset_num_timesteps=checkpoint is None,
                progress_bar=not args.no_progress,
                tb_log_name=ALGORITHMS[args.algo].name,
            )
    except KeyboardInterrupt:
        interrupted = True
    except Exception as error:
        train_env.close()
        eval_env.close()
        if checkpoint is None and latest_checkpoint(out) is None:
            # Nothing worth keeping: leave no folder that blocks the rerun or holds the failed
            # config. Before the first checkpoint, a failure is almost always a value of the entry
            # (a callback's method name, a policy option): one line, naming it.
            _discard(out, created)
            first = str(error).strip().splitlines()[0] if str(error).strip() else ""
            raise UserError(
                f"training failed at step {model.num_timesteps}: {type(error).__name__}: {first} "
                f"(nothing was kept in {str(out)!r}; fix the config and run the command again)"
            ) from error
        raise
    save_checkpoint(model, out / "checkpoints")
    elapsed = time.time() - start
    record["wall_time_s"] = record.get("wall_time_s", 0.0) + elapsed
    record["num_timesteps"] = int(model.num_timesteps)
    # JSON has no -Infinity: no validation yet is null (and best_model.zip is missing)
    best = float(eval_callback.best_mean_reward)
    record["best_mean_reward"] = best if np.isfinite(best) else None
    record["sessions"].append({"started": start, "wall_time_s": elapsed, "steps_until": int(model.num_timesteps)})
    write_signed(out / "run.json", json.dumps(record, indent=2))
    train_env.close()
    eval_env.close()
    if interrupted:
        print(f"sb3-graph train: interrupted at step {model.num_timesteps}; continue with --resume", file=sys.stderr)
        return 130
    model.save(out / "final_model.zip")
    print(f"sb3-graph train: {model.num_timesteps} steps in {record['wall_time_s']:.0f} s, run folder {out}")
    for line in run_summary(out, args):
        print(f"  {line}")
    return 0


def run_summary(out: Path, args: argparse.Namespace) -> list[str]:
    """What a finished run wrote and what to do next, as lines for the console.

    :param out: the run folder
    :param args: the command's arguments (``--env``, ``--config``)
    :return: ``"wrote: ..."``, then ``"next: ..."`` lines: export the best model as a weights-only file, evaluate
        it (when an installed domain provides ``evaluate`` for the environment), watch TensorBoard, train longer
    """
    wrote = []
    for name in RUN_FILES:
        path = out / name
        if path.is_dir():
            wrote.append(f"{name}/ ({sum(1 for p in path.rglob('*') if p.is_file())} files)")
        elif path.is_file():
            wrote.append(name)
    model = out / ("best_model.zip" if (out / "best_model.zip").is_file() else "final_model.zip")
    policy = model.with_suffix(".safetensors")
    lines = [f"wrote: {', '.join(wrote)}", "next:"]
    lines.append(f"  sb3-graph export {model} {policy}   # the policy as a weights-only file (runs no code)")
    if _domain_evaluates(args.env):
        lines.append(
            f"  sb3-graph evaluate --env {args.env} --planner mine={policy} --planner ...   # against other planners"
        )
    if (out / "tb").is_dir():
        lines.append(f"  tensorboard --logdir {out / 'tb'}   # the training curves")
    lines.append(
        f"  sb3-graph train --config {args.config} --env {args.env} --out {out} --resume --n-timesteps N   # train on"
    )
    return lines


def _domain_evaluates(env_id: str) -> bool:
    """Whether an installed domain's ``evaluate`` command runs ``env_id`` (an environment that is not this
    package's own, and a domain that provides ``evaluate``)."""
    import gymnasium as gym

    from sb3_graph.plugins import domain_commands

    spec = gym.registry.get(env_id)
    own = spec is None or str(spec.entry_point).startswith("sb3_graph.")
    return not own and "evaluate" in domain_commands()
