"""One trial: sample, train the study's algorithm (``--algo``, TD3 by default) on the (reduced) environment,
from scratch or from the tensors of ``--init-weights``, evaluate on task metrics.

The evaluator is a plug-in: any callable ``evaluate(model, env_id, env_kwargs, episodes, seed)``
returning a mapping of metric names to numbers (e.g. the intersection domain's, named by its
``sb3_graph.tuning`` entry point). It always sees the same validation episodes (``seed`` is fixed per
study, not per trial), so trials are compared like for like.

Outcomes (the reason is the user attribute ``reason``; the study always continues):

- ``COMPLETE``: the metrics are stored as user attributes (one per metric);
- ``PRUNED``: the pruner (median, successive halving, Hyperband) stopped a poor trial at an
  intermediate evaluation, or training diverged (non-finite network parameters or metrics: a poor
  configuration that the TPE sampler should learn to avoid, which it does for pruned trials but not
  for failed ones);
- ``FAIL``: the trial raised an exception (its type and message are stored).
"""

from __future__ import annotations

import importlib
import os
import socket
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

from sb3_graph.registry import ALGORITHMS
from sb3_graph.tuning.objectives import Objective, check_metrics
from sb3_graph.tuning.pruners import evaluation_steps
from sb3_graph.tuning.search_space import (
    DEFAULT_SPREAD,
    entry_with_params,
    sample_algo,
    sample_config,
    sample_reward_weights,
)

Evaluator = Callable[..., Mapping[str, float]]
REASON = "reason"


class TrialDiverged(Exception):
    """Training produced non-finite parameters or metrics."""


def resolve_callable(spec: str | Callable, field_name: str = "--evaluator") -> Callable:
    """Import ``"module:function"`` (a callable passes through).

    :param spec: ``"package.module:attribute"`` or a callable
    :param field_name: the option named in errors
    :raises ValueError: a malformed spec or an import failure
    """
    if callable(spec):
        return spec
    if not isinstance(spec, str) or spec.count(":") != 1 or not all(spec.split(":")):
        raise ValueError(f"{field_name} must have the form 'module:function', got {spec!r}")
    module_name, attribute = spec.split(":")
    try:
        return getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as error:
        raise ValueError(f"{field_name}: cannot import {spec!r}: {error}") from error


@dataclass
class TrialSettings:
    """Everything a trial needs besides its sampled parameters.

    :param env_id: gymnasium id
    :param entry: experiment entry the trials start from (its ``env_kwargs`` already hold the
        tuning preset and the user's overrides)
    :param timesteps: training steps per trial
    :param objective: what is optimized
    :param evaluator: the metric plug-in (see the module docstring)
    :param weight_defaults: reward weights to tune and their centres (empty: weights not tuned)
    :param weight_spread: factor each way of the weights' log ranges
    :param config_space: environment-config keys to sample, key -> ``(low, high, log)``
        (``--tune-config``, :func:`~sb3_graph.tuning.search_space.parse_config_space`)
    :param tune_algo: also sample the algorithm's settings (its registry entry's ``tune_space``)
    :param algo: ``--algo`` name of the trained algorithm (a key of :data:`sb3_graph.registry.ALGORITHMS`)
    :param evaluations: evaluations per trial (the last at the end); only prunable objectives
        evaluate before the end
    :param eval_steps: training steps of the intermediate evaluations (default: ``evaluations``
        evenly spaced; SHA and Hyperband studies give their rungs, see :mod:`sb3_graph.tuning.pruners`)
    :param eval_episodes: validation episodes per evaluation
    :param eval_seed: seed of the validation episodes (the same for every trial)
    :param seed: base training seed (trial ``k`` trains with ``seed + k``)
    :param device: torch device
    :param save_models: folder for each trial's final model (``trial_<k>.zip``), or ``None``
    :param init_weights: a policy file (``.safetensors``, or an SB3 ``.zip`` read without unpickling)
        whose tensors every trial's policy starts from (fine-tuning), or ``None`` (from scratch)
    :param pretrain_cache: folder of the study's cloning cache (an entry with ``pretrain_from``; see
        :mod:`sb3_graph.tuning.pretrain`), or ``None``: each trial clones without a cache
    """

    env_id: str
    entry: dict[str, Any]
    timesteps: int
    objective: Objective
    evaluator: Evaluator
    weight_defaults: dict[str, float] = field(default_factory=dict)
    weight_spread: float = DEFAULT_SPREAD
    config_space: dict[str, tuple[float, float, bool]] = field(default_factory=dict)
    tune_algo: bool = False
    algo: str = "td3"
    evaluations: int = 3
    eval_steps: tuple[int, ...] | None = None
    eval_episodes: int = 3
    eval_seed: int = 10_000
    seed: int = 0
    device: str = "cpu"
    save_models: Path | None = None
    init_weights: Path | None = None
    pretrain_cache: Path | None = None


def sample_params(trial: optuna.Trial, settings: TrialSettings) -> dict[str, Any]:
    """Sample the trial's parameters (``weight.*``, ``config.*`` and ``algo.*``); the trial records them."""
    sample_reward_weights(trial, settings.weight_defaults, settings.weight_spread)
    sample_config(trial, settings.config_space)
    if settings.tune_algo:
        sample_algo(trial, ALGORITHMS[settings.algo].tune_space)
    return dict(trial.params)


def _finite_parameters(model) -> bool:
    return all(bool(th.isfinite(p).all()) for p in model.policy.parameters())


class TrialEvalCallback(BaseCallback):
    """Evaluate during training, report to the trial, stop when the pruner says so or on divergence.

    :param evaluate: ``model -> metrics``
    :param trial: the Optuna trial
    :param objective: gives the reported value and whether to report at all
    :param steps: training steps of the intermediate evaluations (the final one is the caller's);
        with several envs an evaluation runs at the first step count at or past each
    """

    def __init__(self, evaluate: Callable, trial: optuna.Trial, objective: Objective, steps: Sequence[int]) -> None:
        super().__init__()
        self.evaluate = evaluate
        self.trial = trial
        self.objective = objective
        self.steps = sorted(int(step) for step in steps)
        self._next = 0
        self.pruned_at: int | None = None
        self.last_value: float | None = None
        self.diverged: str | None = None

    def _on_step(self) -> bool:
        if self._next >= len(self.steps) or self.num_timesteps < self.steps[self._next]:
            return True
        while self._next < len(self.steps) and self.num_timesteps >= self.steps[self._next]:
            self._next += 1
        if not _finite_parameters(self.model):
            self.diverged = f"non-finite network parameters at step {self.num_timesteps}"
            return False
        metrics = self.evaluate(self.model)
        problem = check_metrics(metrics, self.objective)
        if problem:
            self.diverged = f"{problem} at step {self.num_timesteps}"
            return False
        self.last_value = float(self.objective.values(metrics))
        self.trial.report(self.last_value, self.num_timesteps)
        if self.trial.should_prune():
            self.pruned_at = self.num_timesteps
            return False
        return True


def load_init_weights(model, path: str | Path) -> None:
    """Start ``model``'s policy from the tensors of a policy file (tensors only, nothing unpickled).

    :raises sb3_graph.files.policy_files.PolicyFileError: an unreadable file or another architecture (one line)
    """
    from sb3_graph.files.policy_files import init_from_file

    init_from_file(model.policy, path)


def run_trial(trial: optuna.Trial, settings: TrialSettings) -> float | tuple[float, ...]:
    """Train and evaluate one sampled configuration (the Optuna objective function).

    :param trial: the trial (its parameters are sampled here)
    :param settings: the study's settings
    :return: the objective value(s)
    :raises optuna.TrialPruned: pruned or diverged (reason in the user attribute ``reason``)
    :raises Exception: anything else the trial raised (reason recorded first; the study catches it)
    """
    trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
    try:
        return _run(trial, settings)
    except optuna.TrialPruned:
        raise
    except TrialDiverged as error:
        trial.set_user_attr(REASON, f"diverged: {error}")
        raise optuna.TrialPruned(str(error)) from error
    except Exception as error:
        tail = "".join(traceback.format_exception(type(error), error, error.__traceback__)[-3:])
        trial.set_user_attr(REASON, f"{type(error).__name__}: {error}"[:1000])
        trial.set_user_attr("traceback", tail[-2000:])
        raise


def _run(trial: optuna.Trial, settings: TrialSettings) -> float | tuple[float, ...]:
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_graph.files.experiment_files import build_algorithm_kwargs, build_callbacks, resolve_object
    params = sample_params(trial, settings)
    entry = entry_with_params(settings.entry, params)
    env_kwargs = dict(entry.get("env_kwargs") or {})
    seed = settings.seed + trial.number
    trial.set_user_attr("seed", seed)
    trial.set_user_attr("timesteps", settings.timesteps)

    def evaluate(model) -> Mapping[str, float]:
        tic = time.perf_counter()
        metrics = settings.evaluator(
            model, env_id=settings.env_id, env_kwargs=env_kwargs, episodes=settings.eval_episodes,
            seed=settings.eval_seed,
        )  # fmt: skip
        evaluate.seconds += time.perf_counter() - tic
        return {key: float(value) if value is not None else float("nan") for key, value in metrics.items()}

    evaluate.seconds = 0.0
    train_env = make_vec_env(settings.env_id, n_envs=int(entry.get("n_envs", 1)), seed=seed, env_kwargs=env_kwargs)
    try:
        policy = entry.get("policy", "GraphPolicy")
        if isinstance(policy, str) and "." in policy:
            policy = resolve_object(policy, "policy")
        algo_kwargs = build_algorithm_kwargs(entry, int(np.prod(train_env.action_space.shape)))
        algorithm = ALGORITHMS[settings.algo].load_class()
        model = algorithm(policy, train_env, seed=seed, device=settings.device, verbose=0, **algo_kwargs)
        if settings.init_weights is not None:
            load_init_weights(model, settings.init_weights)
        if entry.get("pretrain_from") is not None:
            from sb3_graph.tuning.pretrain import pretrain_trial

            pretrained = pretrain_trial(model, entry, settings.env_id, train_env, settings.algo,
                                        settings.pretrain_cache, settings.init_weights)  # fmt: skip
            trial.set_user_attr("pretrain", pretrained)
        callbacks = build_callbacks(entry)
        monitor = None
        steps = settings.eval_steps
        if steps is None:
            steps = evaluation_steps("median", settings.timesteps, settings.evaluations)
        steps = [step for step in steps if step < settings.timesteps]
        if settings.objective.prunable and steps:
            monitor = TrialEvalCallback(evaluate, trial, settings.objective, steps)
            callbacks.append(monitor)
        tic = time.perf_counter()
        model.learn(settings.timesteps, callback=CallbackList(callbacks), progress_bar=False)
        trial.set_user_attr("train_s", round(time.perf_counter() - tic - evaluate.seconds, 2))
        if monitor is not None and monitor.diverged:
            raise TrialDiverged(monitor.diverged)
        if monitor is not None and monitor.pruned_at is not None:
            trial.set_user_attr(
                REASON, f"pruned at step {monitor.pruned_at} (intermediate value {monitor.last_value:.4g})"
            )
            raise optuna.TrialPruned(f"step {monitor.pruned_at}")
        if not _finite_parameters(model):
            raise TrialDiverged(f"non-finite network parameters at step {model.num_timesteps}")
        if settings.save_models is not None:
            settings.save_models.mkdir(parents=True, exist_ok=True)
            model.save(settings.save_models / f"trial_{trial.number}.zip")
        metrics = evaluate(model)
    finally:
        train_env.close()
    trial.set_user_attr("eval_s", round(evaluate.seconds, 2))
    for name, value in metrics.items():
        if np.isfinite(value):  # JSON storages refuse NaN; a missing attribute reads as "undefined"
            trial.set_user_attr(name, value)
    problem = check_metrics(metrics, settings.objective)
    if problem:
        raise TrialDiverged(problem)
    if settings.objective.prunable:  # the last point of the learning curve that the pruner compares
        trial.report(float(settings.objective.values(metrics)), settings.timesteps)
    trial.set_constraint("collision_rate", settings.objective.constraint(metrics))
    return settings.objective.values(metrics)
