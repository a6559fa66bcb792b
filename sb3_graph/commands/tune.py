"""``sb3-graph tune``: tune reward weights (and environment-config keys, the algorithm's settings) with Optuna,
on one machine or many.

Every invocation adds ``--n-trials`` trials to the study named ``--study-name`` in ``--storage``
(created on first use): re-running the command resumes the study, and workers on other machines
that run the same command against the same PostgreSQL server or journal file join it.
``--jobs N`` starts N worker processes on this machine, sharing the trials of this invocation.

Each trial trains as the entry says (behind the shield when its env config asks for it), from
scratch or from ``--init-weights`` (tensors only, fitted once here on a probe model), and is scored
by the domain's evaluator on task metrics (``--objective``), never on the training reward.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
from pathlib import Path
from typing import Any

from sb3_graph.commands import UserError
from sb3_graph.commands.arguments import check_device, json_object, seed_value
from sb3_graph.commands.train import parse_overrides
from sb3_graph.registry import ALGORITHMS

DEFAULT_STORAGE = "sqlite:///studies/{study}.db"
# The package's own environment ids with a tuning plug-in: prefix -> (evaluator, env preset). A
# domain adds its own through the `sb3_graph.tuning` entry point group (sb3_graph.plugins).
DOMAIN_DEFAULTS = {
    "GraphMaxNeighbour": ("sb3_graph.tuning.toy:evaluate_max_neighbour", "none"),
}
TOY_GYM_PACKAGE = "sb3_graph.toy_envs"
# Study user attributes written when the study is created, checked when it is resumed.
CHECKED_ATTRS = ("objective", "metrics", "env", "algo", "init_weights_sha256")
# Values of attributes that studies made before the attribute existed have.
ATTR_DEFAULTS = {"algo": "td3", "init_weights_sha256": ""}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sb3-graph tune``."""
    parser.add_argument("--config", required=True, help="rl-zoo3 style YAML file (one entry per env id)")
    parser.add_argument("--env", required=True, help="environment id, the entry to read from --config")
    parser.add_argument("--study-name", required=True, help="Optuna study (created on first use, then resumed)")
    parser.add_argument(
        "--storage",
        default=None,
        help="sqlite:///PATH.db (default sqlite:///studies/<study-name>.db), "
        "postgresql://USER:PASSWORD@HOST:PORT/DB or journal://PATH (shared by many workers)",
    )
    parser.add_argument(
        "--allow-foreign-storage",
        action="store_true",
        help="use a --storage database that holds tables of another application, or a journal:// file that "
        "is not an Optuna journal (refused by default: Optuna would add its tables or lines to it)",
    )
    parser.add_argument("--n-trials", type=int, default=10, help="trials this invocation adds to the study")
    parser.add_argument("--timesteps", type=int, default=None, help="training steps per trial (default: entry)")
    parser.add_argument(
        "--objective",
        default="flow",
        help="task metric on the validation scenarios, every one under the --max-collision-rate constraint: "
        "flow (max flow rate), flow-delay (max flow_rate - W * delay_mean [s]), flow-stop (max flow_rate - "
        "W * stop_ratio), or pareto (NSGA-II front of flow up, delay down, stops down)",
    )
    parser.add_argument(
        "--objective-weight",
        type=float,
        default=None,
        metavar="W",
        help="W of flow-delay (default 0.01 veh/s per s of mean delay) or flow-stop (default 0.2)",
    )
    parser.add_argument(
        "--algo", choices=ALGORITHMS, default="td3", help="algorithm that the trials train, as rl-zoo3's --algo"
    )
    parser.add_argument(
        "--tune-algo", action="store_true", help="also tune the algorithm's settings (learning rate, batch...)"
    )
    parser.add_argument("--jobs", type=int, default=1, help="worker processes on this machine")
    parser.add_argument(
        "--weights",
        nargs="*",
        default=None,
        metavar="TERM",
        help="reward terms to tune (default: every term of the env's reward_weights, i.e. of the preset that the "
        "entry's config['reward'] selects; none: --weights with no term)",
    )
    parser.add_argument(
        "--weight-spread",
        type=float,
        default=10.0,
        help="log range factor each way around each weight of the entry's env (its reward preset's weights, with "
        "the entry's reward_weights over them)",
    )
    parser.add_argument(
        "--tune-config",
        nargs="+",
        default=[],
        metavar="KEY:LOW:HIGH[:log]",
        help="also tune numbers of the env's config, e.g. residual_scale:0.25:2 for a residual policy "
        "(the env checks both bounds)",
    )
    parser.add_argument(
        "--init-weights",
        default=None,
        metavar="FILE",
        help="every trial fine-tunes the policy of FILE (.safetensors policy file, or a model .zip read without "
        "unpickling; tensors only) instead of training from scratch; its architecture must be the entry's",
    )
    parser.add_argument(
        "--max-collision-rate", type=float, default=0.02, help="collision-rate constraint of every objective"
    )
    parser.add_argument(
        "--evaluations", type=int, default=3, help="evaluations per trial (single objectives: pruning points)"
    )
    parser.add_argument("--eval-episodes", type=int, default=3, help="validation episodes per evaluation")
    parser.add_argument("--eval-seed", type=int, default=10_000, help="seed of the validation episodes")
    parser.add_argument("--evaluator", default=None, help="metric plug-in module:function (default per env id)")
    parser.add_argument(
        "--env-preset",
        default=None,
        help="module:attribute, a dict or function giving the reduced env kwargs, or none "
        "(default: the preset of the env id's domain, e.g. the intersection's 'tuning' preset)",
    )
    parser.add_argument("--env-kwargs", type=json_object, default=None, help="JSON dict merged over the preset")
    parser.add_argument(
        "--trial-hyperparams",
        nargs="+",
        default=[],
        metavar="KEY:VALUE",
        help="entry keys for the trials only, e.g. train_freq:2 n_envs:2 (cheaper trials); the report's "
        "zoo entry keeps the file's values",
    )
    parser.add_argument(
        "--pruner",
        default="median",
        help="pruner of a single objective (not pareto) on its intermediate value: median, successive-halving, "
        "hyperband or none",
    )
    parser.add_argument(
        "--min-resource",
        type=int,
        default=None,
        help="successive-halving/hyperband: training steps of the first rung "
        "(default: --timesteps / --reduction-factor ** (--evaluations - 1), rounded up)",
    )
    parser.add_argument(
        "--reduction-factor", type=int, default=3, help="successive-halving/hyperband: factor between two rungs (>= 2)"
    )
    parser.add_argument("--population-size", type=int, default=10, help="NSGA-II population (pareto)")
    parser.add_argument("--seed", type=seed_value, default=0, help="base training seed (trial k uses seed + k)")
    parser.add_argument("--sampler-seed", type=int, default=None, help="sampler seed (worker i uses seed + i)")
    parser.add_argument(
        "--heartbeat", type=int, default=60, help="seconds between heartbeats; a trial silent for two is failed"
    )
    parser.add_argument("--max-retry", type=int, default=0, help="retries of a trial whose worker died")
    parser.add_argument("--save-models", default=None, help="folder for each trial's final model")
    parser.add_argument(
        "--pretrain-cache",
        default=None,
        metavar="DIR",
        help="an entry with pretrain_from: folder where the study keeps its demonstrations and cloned models, "
        "shared by its trials (default: <study-name>.pretrain next to the --storage file; studies/ otherwise)",
    )
    parser.add_argument(
        "--gym-packages",
        nargs="*",
        default=None,
        help="modules that register the env (default: the installed domains' sb3_graph.gym_packages)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads per worker")
    parser.add_argument("--device", default="cpu", help="torch device")


def _domain_default(env_id: str, index: int) -> str | None:
    from sb3_graph.plugins import tuning_defaults

    for prefix, values in {**DOMAIN_DEFAULTS, **tuning_defaults()}.items():
        if env_id.startswith(prefix):
            return values[index]
    return None


def _gym_packages(args: argparse.Namespace) -> list[str]:
    from sb3_graph.plugins import gym_packages

    if args.gym_packages is not None:
        return list(args.gym_packages)
    if any(args.env.startswith(prefix) for prefix in DOMAIN_DEFAULTS):
        return [TOY_GYM_PACKAGE]
    return [*gym_packages(), TOY_GYM_PACKAGE]


def _preset(args: argparse.Namespace) -> dict[str, Any]:
    import importlib

    spec = args.env_preset or _domain_default(args.env, 1) or "none"
    if spec == "none":
        return {}
    module_name, _, attribute = spec.partition(":")
    try:
        value = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError, ValueError) as error:
        raise UserError(f"--env-preset: cannot import {spec!r} (form module:attribute or none): {error}") from error
    value = value() if callable(value) else value
    if not isinstance(value, dict):
        raise UserError(f"--env-preset: {spec!r} must give a dict of env kwargs, got {type(value).__name__}")
    return value


def prepare(args: argparse.Namespace):
    """Check the options, read the entry, probe the env: everything a worker needs, or a UserError.

    :return: ``(settings, study attributes)``
    """
    import importlib

    import gymnasium as gym

    from sb3_graph.files.experiment_files import (
        ExperimentError,
        build_algorithm_kwargs,
        build_callbacks,
        check_algorithm_keys,
        check_entry,
        merge_env_kwargs,
        read_experiment,
        resolve_object,
    )
    from sb3_graph.tuning.objectives import make_objective
    from sb3_graph.tuning.runner import TrialSettings, resolve_callable
    from sb3_graph.tuning.search_space import WEIGHTS_KEY, parse_config_space, weights_in

    for name in ("n_trials", "jobs", "evaluations", "eval_episodes", "population_size", "heartbeat", "threads"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    if not args.weight_spread > 1:
        raise UserError(f"--weight-spread must be > 1 (a factor each way), got {args.weight_spread}")
    if args.max_retry < 0:
        raise UserError(f"--max-retry must be >= 0, got {args.max_retry}")
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    if args.timesteps is not None and args.timesteps < 1:
        raise UserError(f"--timesteps must be at least 1, got {args.timesteps}")
    check_device(args.device)
    try:
        objective = make_objective(args.objective, args.max_collision_rate, getattr(args, "objective_weight", None))
    except ValueError as error:
        raise UserError(f"--objective/--objective-weight/--max-collision-rate: {error}") from error
    try:
        config_space = parse_config_space(getattr(args, "tune_config", None) or [])
    except ValueError as error:
        raise UserError(f"--tune-config: {error}") from None
    if WEIGHTS_KEY[1] in config_space:
        raise UserError(f"--tune-config: {WEIGHTS_KEY[1]!r} is tuned by --weights")
    overrides = parse_overrides(args.trial_hyperparams, "--trial-hyperparams")
    try:
        entry = check_entry(read_experiment(args.config, args.env))
        trial_entry = check_entry({**entry, **overrides})
        # Every value that a trial turns into an object, checked once here (a typo fails the
        # command, not every trial): no expression is evaluated, see sb3_graph.files.safe_values.
        # a key that the algorithm does not take (a typo: learnig_rate) names itself here, not in every trial
        check_algorithm_keys(build_algorithm_kwargs(trial_entry, 1), ALGORITHMS[args.algo].load_class())
        build_callbacks(trial_entry)
        if isinstance(trial_entry.get("policy"), str) and "." in trial_entry["policy"]:
            resolve_object(trial_entry["policy"], "policy")
    except ExperimentError as error:
        raise UserError(f"{error} (--config or --trial-hyperparams)" if overrides else str(error)) from error
    timesteps = int(float(args.timesteps if args.timesteps is not None else trial_entry["n_timesteps"]))
    if timesteps < 1:
        raise UserError(f"--timesteps must be at least 1, got {timesteps}")
    learning_starts = 0 if ALGORITHMS[args.algo].on_policy else int(trial_entry.get("learning_starts", 100))
    if learning_starts >= timesteps:
        raise UserError(
            f"--timesteps {timesteps} <= learning_starts {learning_starts} of the entry: no gradient step would run"
        )
    if args.evaluations > 1 and timesteps // args.evaluations < 1:
        raise UserError(f"--evaluations {args.evaluations} exceeds --timesteps {timesteps}")
    eval_steps = _evaluation_steps(args, timesteps)
    for name in _gym_packages(args):
        try:
            importlib.import_module(name)
        except ImportError as error:
            raise UserError(f"--gym-packages: cannot import {name!r}: {error}") from error
    if args.env not in gym.registry:
        raise UserError(f"--env: unknown environment id {args.env!r} (registered by --gym-packages?)")
    evaluator_spec = args.evaluator or _domain_default(args.env, 0)
    if evaluator_spec is None:
        raise UserError(f"--evaluator is required for {args.env!r} (form module:function)")
    try:
        resolve_callable(evaluator_spec)
    except ValueError as error:
        raise UserError(str(error)) from error

    original_env_kwargs = dict(trial_entry.get("env_kwargs") or {})
    env_kwargs = merge_env_kwargs(merge_env_kwargs(original_env_kwargs, _preset(args)), dict(args.env_kwargs or {}))
    try:
        probe = gym.make(args.env, **env_kwargs)
    except (TypeError, ValueError) as error:
        raise UserError(f"env kwargs of {args.env!r}: {error}") from error
    config = getattr(probe.unwrapped, "config", None)
    probe.close()
    defaults = dict(config.get(WEIGHTS_KEY[1]) or {}) if isinstance(config, dict) else {}
    defaults.update(weights_in(env_kwargs))
    if args.weights is not None:
        defaults = _chosen_weights(args.weights, defaults, config)
    _check_config_space(args.env, env_kwargs, config, config_space)
    if not defaults and not config_space and not args.tune_algo:
        raise UserError(
            f"nothing to tune: {args.env!r} has no config['reward_weights'] (or --weights is empty), "
            "no --tune-config and --tune-algo is off"
        )
    init_weights, init_hash = None, ""
    if getattr(args, "init_weights", None):
        init_weights = Path(args.init_weights)
        init_hash = _check_init_weights(args, trial_entry, env_kwargs, init_weights)
    pretrain_cache = None
    if trial_entry.get("pretrain_from") is not None:
        pretrain_cache = _check_pretrain(args, trial_entry, env_kwargs)
    study_entry = {**trial_entry, "env_kwargs": env_kwargs}
    settings = TrialSettings(
        env_id=args.env,
        entry=study_entry,
        timesteps=timesteps,
        objective=objective,
        evaluator=evaluator_spec,  # resolved in each worker
        weight_defaults=defaults,
        weight_spread=args.weight_spread,
        config_space=config_space,
        tune_algo=args.tune_algo,
        algo=args.algo,
        evaluations=args.evaluations,
        eval_steps=eval_steps,
        eval_episodes=args.eval_episodes,
        eval_seed=args.eval_seed,
        seed=args.seed,
        device=args.device,
        save_models=Path(args.save_models) if args.save_models else None,
        init_weights=init_weights,
        pretrain_cache=pretrain_cache,
    )
    attrs = {
        "objective": objective.name,
        "env": args.env,
        "algo": args.algo,
        "config_file": str(args.config),
        # the entry as in the file (full env): the report's YAML puts the best parameters into it
        "entry": json.loads(json.dumps(entry, default=str)),
        "tuning_env_kwargs": json.loads(json.dumps(env_kwargs, default=str)),
        "metrics": list(objective.labels),
        "objective_weight": -objective.coefficients[1] if objective.coefficients else None,
        "max_collision_rate": objective.max_collision_rate,
        "reward": config.get("reward") if isinstance(config, dict) else None,
        "weight_centres": json.loads(json.dumps(defaults, default=str)),
        "config_space": {key: list(bounds) for key, bounds in config_space.items()},
        "init_weights": str(init_weights) if init_weights is not None else "",
        "init_weights_sha256": init_hash,
        "evaluator": evaluator_spec,
        "timesteps": timesteps,
        "pruner": args.pruner if objective.prunable else "none",
        "trial_hyperparams": json.loads(json.dumps(overrides, default=str)),
        "eval_steps": list(eval_steps) if objective.prunable else [],
    }
    return settings, attrs


def _chosen_weights(terms: list[str], defaults: dict[str, Any], config: Any) -> dict[str, Any]:
    """The ``--weights`` terms with their centres, or a UserError naming the env's terms."""
    preset = config.get("reward") if isinstance(config, dict) else None
    of = f" of reward {preset!r}" if isinstance(preset, str) else ""
    unknown = sorted(set(terms) - set(defaults))
    if unknown:
        raise UserError(f"--weights: unknown reward terms {unknown}; the terms{of}: {sorted(defaults)}")
    flat = sorted(term for term in terms if not float(defaults[term]) > 0)
    if flat:
        raise UserError(
            f"--weights: {flat} weigh {[defaults[t] for t in flat]}{of}: a log range needs a centre > 0 "
            "(set one in the entry's reward_weights)"
        )
    return {term: defaults[term] for term in terms}


def _check_config_space(env_id: str, env_kwargs: dict[str, Any], config: Any, space: dict) -> None:
    """Each ``--tune-config`` key is a number of the env's config that the env accepts at both bounds."""
    import gymnasium as gym

    from sb3_graph.files.experiment_files import merge_env_kwargs

    def number(value: Any) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool)

    config = config if isinstance(config, dict) else {}
    for key, (low, high, _) in space.items():
        if not number(config.get(key)):
            known = sorted(k for k, v in config.items() if number(v))
            raise UserError(f"--tune-config: {key!r} is not a number of {env_id!r}'s config; its numbers: {known}")
        for bound in (low, high):
            try:
                gym.make(env_id, **merge_env_kwargs(env_kwargs, {"config": {key: bound}})).close()
            except (TypeError, ValueError) as error:
                raise UserError(f"--tune-config {key}: {bound:g} is refused by {env_id!r}: {error}") from None


def _check_init_weights(args: argparse.Namespace, entry: dict[str, Any], env_kwargs: dict[str, Any], path: Path):
    """Read ``--init-weights`` (tensors only) and fit it to the policy that the trials build.

    :return: the file's SHA-256 (recorded in the study: a resumed study fine-tunes the same file)
    :raises UserError: one line: no such file, not a policy file, another architecture
    """
    import hashlib

    import numpy as np
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_graph.files.experiment_files import build_algorithm_kwargs, resolve_object
    from sb3_graph.files.policy_files import PolicyFileError
    from sb3_graph.tuning.runner import load_init_weights

    if not path.is_file():
        raise UserError(f"--init-weights: file not found: {str(path)!r}")
    probe = make_vec_env(args.env, n_envs=1, seed=0, env_kwargs=env_kwargs)
    try:
        kwargs = build_algorithm_kwargs(entry, int(np.prod(probe.action_space.shape)))
        if not ALGORITHMS[args.algo].on_policy:
            kwargs["buffer_size"] = 16  # the probe never trains: a small buffer, not the entry's
        policy = entry.get("policy", "GraphPolicy")
        if isinstance(policy, str) and "." in policy:
            policy = resolve_object(policy, "policy")
        try:
            model = ALGORITHMS[args.algo].load_class()(policy, probe, device="cpu", verbose=0, **kwargs)
        except (TypeError, ValueError, KeyError, AssertionError) as error:
            raise UserError(f"hyperparameters of {args.env!r} for {args.algo}: {error}") from None
        try:
            load_init_weights(model, path)
        except PolicyFileError as error:
            raise UserError(f"--init-weights: {error}") from None
    finally:
        probe.close()
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _check_pretrain(args: argparse.Namespace, entry: dict[str, Any], env_kwargs: dict[str, Any]) -> Path:
    """The entry's ``pretrain_from`` names an expert of the env (checked once, not in every trial).

    :return: the study's cloning cache folder
    :raises UserError: no expert for the env, a spec that its factory refuses, a cache path that is a file
    """
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_graph.commands.train import _make_expert
    from sb3_graph.tuning.pretrain import default_cache_folder

    probe = make_vec_env(args.env, n_envs=1, seed=0, env_kwargs=env_kwargs)
    try:
        _make_expert(str(entry["pretrain_from"]), args.env, probe)
    finally:
        probe.close()
    chosen = getattr(args, "pretrain_cache", None)
    folder = Path(chosen) if chosen else default_cache_folder(storage_url(args), args.study_name)
    if folder.exists() and not folder.is_dir():
        raise UserError(f"--pretrain-cache: {str(folder)!r} is a file, not a folder")
    return folder


def _evaluation_steps(args: argparse.Namespace, timesteps: int) -> tuple[int, ...]:
    """The intermediate evaluation steps of a trial, or a UserError naming the pruner flags."""
    from sb3_graph.tuning.pruners import PRUNERS, RUNG_PRUNERS, evaluation_steps

    if args.pruner not in PRUNERS:
        raise UserError(f"--pruner: unknown pruner {args.pruner!r}; allowed: {', '.join(PRUNERS)}")
    if args.reduction_factor < 2:
        raise UserError(f"--reduction-factor must be at least 2, got {args.reduction_factor}")
    if args.min_resource is not None:
        if args.pruner not in RUNG_PRUNERS:
            raise UserError(f"--min-resource applies to --pruner {' or '.join(RUNG_PRUNERS)}, not {args.pruner!r}")
        if not 1 <= args.min_resource < timesteps:
            raise UserError(f"--min-resource must be in [1, --timesteps {timesteps}), got {args.min_resource}")
    try:
        return evaluation_steps(args.pruner, timesteps, args.evaluations, args.min_resource, args.reduction_factor)
    except ValueError as error:  # e.g. one evaluation per trial leaves no rung below the budget
        raise UserError(f"--pruner {args.pruner} with --evaluations {args.evaluations}: {error}") from None


def storage_url(args: argparse.Namespace) -> str:
    """``--storage``, or the default SQLite file of the study."""
    return args.storage or DEFAULT_STORAGE.format(study=args.study_name)


def open_storage(args: argparse.Namespace):
    from sb3_graph.tuning.storage import make_storage

    try:
        return make_storage(
            storage_url(args), heartbeat_interval=args.heartbeat, max_retry=args.max_retry,
            allow_foreign=getattr(args, "allow_foreign_storage", False),
        )  # fmt: skip
    except ValueError as error:
        raise UserError(f"--storage: {error}") from error


def create_or_load(args: argparse.Namespace, settings, attrs: dict[str, Any], storage, worker: int = 0):
    """Create the study, or load it and check that it was made for the same objective and env."""
    import optuna

    seed = None if args.sampler_seed is None else args.sampler_seed + worker
    objective = settings.objective
    study = optuna.create_study(
        study_name=args.study_name,
        storage=storage,
        load_if_exists=True,
        directions=list(objective.directions),
        sampler=objective.sampler(seed=seed, population_size=args.population_size),
        pruner=objective.pruner(
            args.pruner, settings.timesteps, args.evaluations, _first_rung(settings), args.reduction_factor
        ),
    )
    existing = study.user_attrs
    for key in CHECKED_ATTRS:
        recorded = existing.get(key, ATTR_DEFAULTS.get(key)) if existing else None
        if recorded is not None and recorded != attrs[key]:
            raise UserError(
                f"study {args.study_name!r} was created with {key} {recorded!r}, not {attrs[key]!r}: "
                "choose another --study-name"
            )
    if [d.name.lower() for d in study.directions] != list(objective.directions):
        raise UserError(f"study {args.study_name!r} has other directions than objective {objective.name!r}")
    for key, value in attrs.items():
        if key not in existing:
            study.set_user_attr(key, value)
    return study


def _first_rung(settings) -> int | None:
    return settings.eval_steps[0] if settings.eval_steps else None


def work(args: argparse.Namespace, n_trials: int, worker: int = 0) -> int:
    """One worker: open the study and run ``n_trials`` trials (also the body of each ``--jobs`` process).

    :return: the number of trials this worker ran
    """
    import optuna
    import torch as th

    from sb3_graph.tuning.runner import resolve_callable, run_trial

    th.set_num_threads(max(1, args.threads))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    settings, attrs = prepare(args)
    settings.evaluator = resolve_callable(settings.evaluator)
    study = create_or_load(args, settings, attrs, open_storage(args), worker)
    ran = []

    def record(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        ran.append(trial.number)
        reason = trial.user_attrs.get("reason", "")
        values = trial.values if trial.values is not None else ""
        print(f"[worker {worker}] trial {trial.number} {trial.state.name} {values} {reason}".rstrip(), flush=True)

    # catch: a trial that raises is recorded FAIL (reason in its user attributes) and the study goes on
    study.optimize(lambda trial: run_trial(trial, settings), n_trials=n_trials, catch=(Exception,), callbacks=[record])
    return len(ran)


def _work_process(args: argparse.Namespace, n_trials: int, worker: int) -> None:
    try:
        work(args, n_trials, worker)
    except UserError as error:
        print(f"sb3-graph tune (worker {worker}): error: {error}", file=sys.stderr)
        sys.exit(2)


def run(args: argparse.Namespace) -> int:
    """Run the command (see the module docstring)."""
    import optuna

    from sb3_graph.tuning.storage import redact

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    settings, attrs = prepare(args)
    storage = open_storage(args)
    study = create_or_load(args, settings, attrs, storage)  # once, before any worker starts
    before = len(study.get_trials(deepcopy=False))
    if args.jobs == 1:
        work(args, args.n_trials)
    else:
        # spawn: fresh interpreters (no forked torch threads or database connections)
        context = multiprocessing.get_context("spawn")
        shares = [args.n_trials // args.jobs + (i < args.n_trials % args.jobs) for i in range(args.jobs)]
        processes = [
            context.Process(target=_work_process, args=(args, share, i), name=f"tune-worker-{i}")
            for i, share in enumerate(shares)
            if share
        ]
        for process in processes:
            process.start()
        for process in processes:
            process.join()
        if any(process.exitcode for process in processes):
            print("sb3-graph tune: a worker process failed (see its messages above)", file=sys.stderr)
            return 1
    trials = study.get_trials(deepcopy=False)
    states = {state.name: sum(t.state == state for t in trials) for state in optuna.trial.TrialState}
    summary = ", ".join(f"{count} {name.lower()}" for name, count in states.items() if count)
    print(
        f"sb3-graph tune: study {args.study_name!r} in {redact(storage_url(args))}: {len(trials)} trials "
        f"({len(trials) - before} new; {summary})"
    )
    return _all_failed(sorted(trials, key=lambda t: t.number)[before:])


def _all_failed(new_trials) -> int:
    """Exit status 1 with the first trial's error when every new trial failed, else 0."""
    import optuna

    if not new_trials or any(t.state != optuna.trial.TrialState.FAIL for t in new_trials):
        return 0
    first = new_trials[0]
    reason = first.user_attrs.get("reason") or first.system_attrs.get("fail_reason") or "no reason recorded"
    print(
        f"sb3-graph tune: error: all {len(new_trials)} new trials failed; trial {first.number}: "
        f"{str(reason).splitlines()[0]}",
        file=sys.stderr,
    )
    return 1
