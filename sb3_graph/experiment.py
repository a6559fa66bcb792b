"""rl-zoo3 style experiment files: read one entry, check it, and turn it into SB3 objects.

The YAML format is rl-zoo3's (one top-level entry per environment id), so the same file runs
with ``python -m rl_zoo3.train -conf FILE`` and with ``sb3-graph train --config FILE``. Values
that rl-zoo3 evaluates as Python (``policy_kwargs``, ``replay_buffer_class``) are evaluated
here in a namespace holding only ``dict``, ``nn``/``th`` (torch) and ``importlib``.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
import yaml
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.utils import LinearSchedule

# Keys the trainer consumes itself; all others go to the algorithm's constructor.
TRAINER_KEYS = {"n_timesteps", "n_envs", "env_kwargs", "noise_type", "noise_std", "callback", "policy"}
# Keys of rl-zoo3 that this trainer does not implement: refused rather than silently ignored.
UNSUPPORTED_KEYS = {"normalize", "frame_stack", "env_wrapper", "vec_env_wrapper", "monitor_kwargs"}
NOISE_TYPES = ("normal", "ornstein-uhlenbeck")
_EVAL_NAMESPACE = {"__builtins__": {}, "dict": dict, "nn": th.nn, "th": th, "importlib": importlib}


class ExperimentError(ValueError):
    """An experiment file or entry that cannot be used as given."""


def read_experiment(path: str | Path, env_id: str) -> dict[str, Any]:
    """Read the entry of ``env_id`` from an rl-zoo3 style YAML file.

    :param path: YAML file with one top-level entry per environment id
    :param env_id: the entry to read
    :return: the entry's hyperparameters (a fresh dictionary)
    :raises ExperimentError: missing file, invalid YAML, missing entry or invalid keys
    """
    path = Path(path)
    if not path.is_file():
        raise ExperimentError(f"config file {str(path)!r} does not exist")
    try:
        content = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise ExperimentError(f"config file {str(path)!r} is not valid YAML: {error}") from error
    if not isinstance(content, dict) or not content:
        raise ExperimentError(f"config file {str(path)!r} must map environment ids to hyperparameters")
    if env_id not in content:
        raise ExperimentError(
            f"config file {str(path)!r} has no entry for env {env_id!r}; entries: {', '.join(map(str, content))}"
        )
    entry = content[env_id]
    if not isinstance(entry, dict):
        raise ExperimentError(f"entry {env_id!r} in {str(path)!r} must be a mapping of hyperparameters")
    unsupported = sorted(UNSUPPORTED_KEYS & set(entry))
    if unsupported:
        raise ExperimentError(f"entry {env_id!r}: keys {unsupported} are not supported by sb3-graph train")
    if "n_timesteps" not in entry:
        raise ExperimentError(f"entry {env_id!r}: n_timesteps is required")
    return dict(entry)


def resolve_object(value: Any, field: str) -> Any:
    """Turn an rl-zoo3 string into an object: a dotted class path or a Python expression."""
    if not isinstance(value, str):
        return value
    if value.replace(".", "").replace("_", "").isalnum() and "." in value:
        module_name, _, attribute = value.rpartition(".")
        try:
            return getattr(importlib.import_module(module_name), attribute)
        except (ImportError, AttributeError) as error:
            raise ExperimentError(f"{field}: cannot import {value!r}: {error}") from error
    try:
        return eval(value, dict(_EVAL_NAMESPACE))  # the rl-zoo3 convention for these fields
    except Exception as error:  # noqa: BLE001 - any failure is the user's expression
        raise ExperimentError(f"{field}: cannot evaluate {value!r}: {error}") from error


def _schedule(value: Any, field: str) -> Any:
    """rl-zoo3 schedules (``learning_rate``, PPO's ``clip_range`` and ``clip_range_vf``):
    ``lin_<start>`` decays linearly to 0 over training."""
    if isinstance(value, str):
        if not value.startswith("lin_"):
            raise ExperimentError(f"{field}: expected a number or 'lin_<value>', got {value!r}")
        return LinearSchedule(float(value[4:]), 0.0, 1.0)
    return value


def build_algorithm_kwargs(entry: dict[str, Any], action_dim: int) -> dict[str, Any]:
    """Constructor keyword arguments for the algorithm from one experiment entry.

    :param entry: hyperparameters as read by :func:`read_experiment`
    :param action_dim: size of the flat action space (for the exploration noise)
    :return: keyword arguments (``policy`` not included)
    """
    kwargs = {key: value for key, value in entry.items() if key not in TRAINER_KEYS}
    for field in ("policy_kwargs", "replay_buffer_class", "replay_buffer_kwargs"):
        if field in kwargs:
            kwargs[field] = resolve_object(kwargs[field], field)
    for field in ("learning_rate", "clip_range", "clip_range_vf"):
        if field in kwargs:
            kwargs[field] = _schedule(kwargs[field], field)
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    noise_type = entry.get("noise_type")
    if noise_type is not None:
        if noise_type not in NOISE_TYPES:
            raise ExperimentError(f"noise_type must be one of {NOISE_TYPES}, got {noise_type!r}")
        std = float(entry.get("noise_std", 0.1))
        noise_class = NormalActionNoise if noise_type == "normal" else OrnsteinUhlenbeckActionNoise
        kwargs["action_noise"] = noise_class(np.zeros(action_dim), std * np.ones(action_dim))
    return kwargs


def build_callbacks(entry: dict[str, Any]) -> list:
    """Callbacks listed under ``callback`` (dotted names, optionally with keyword arguments)."""
    specs = entry.get("callback") or []
    if not isinstance(specs, list):
        specs = [specs]
    callbacks = []
    for spec in specs:
        if isinstance(spec, dict):
            if len(spec) != 1:
                raise ExperimentError(f"callback: each item maps one class name to its kwargs, got {spec}")
            (name, kwargs), = spec.items()
        else:
            name, kwargs = spec, {}
        callback_class = resolve_object(name, "callback")
        try:
            callbacks.append(callback_class(**(kwargs or {})))
        except (TypeError, ValueError) as error:
            raise ExperimentError(f"callback {name}: {error}") from error
    return callbacks
