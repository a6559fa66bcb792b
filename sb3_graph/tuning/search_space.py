"""What a trial samples: the reward weights (log scales around their defaults) and, optionally, the settings of
the trained algorithm (its registry entry's ``tune_space``).

Parameter names carry a prefix that says where the value goes:

- ``weight.<term>``: the reward weight of ``<term>``, sampled log-uniformly in
  ``[w0 / spread, w0 * spread]`` around its default ``w0``. For the intersection environments the
  defaults are the paper's Table I (velocity 0.03, action 0.01, idle 0.01, proximity 0.2,
  collision 1.0), read from the environment's own ``default_config()["reward_weights"]`` (or from
  the experiment entry's ``env_kwargs``), so this module needs no knowledge of the domain. The
  weights reach the environment as ``env_kwargs["config"]["reward_weights"]`` (highway-env's
  configuration habit).
- ``algo.<key>``: a key of the rl-zoo3 experiment entry (``learning_rate``, ``batch_size``,
  ``gamma``, ``tau``, ``noise_std``, ``policy_delay``; see :data:`ALGO_SPACE`), with ``--tune-algo``.

:func:`entry_with_params` turns a parameter dictionary (a trial's, or the best trial's) back into a
complete experiment entry: the same function serves the trials and the report's YAML.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any

import optuna

from sb3_graph.registry import ALGORITHMS

WEIGHT_PREFIX = "weight."
ALGO_PREFIX = "algo."
# Where the weights go inside the env kwargs: gym.make(env_id, config={"reward_weights": {...}}).
WEIGHTS_KEY = ("config", "reward_weights")
DEFAULT_SPREAD = 10.0

# TD3 settings tuned with --tune-algo: name -> (kind, arguments). Ranges bracket SB3's and rl-zoo3's TD3 defaults.
# Every algorithm's space is its registry entry's ``tune_space`` (sb3_graph.registry).
ALGO_SPACE: dict[str, tuple[str, tuple]] = dict(ALGORITHMS["td3"].tune_space)


def sample_reward_weights(
    trial: optuna.Trial, defaults: Mapping[str, float], spread: float = DEFAULT_SPREAD
) -> dict[str, float]:
    """Sample one weight per reward term, log-uniformly around its default.

    :param trial: the Optuna trial
    :param defaults: ``term -> default weight``; terms with a weight <= 0 are not tuned (no log scale)
    :param spread: factor each way around the default, > 1
    :return: ``term -> weight`` for the tuned terms
    """
    if not spread > 1:
        raise ValueError(f"weight spread must be > 1, got {spread}")
    weights = {}
    for term, default in defaults.items():
        default = float(default)
        if default > 0 and math.isfinite(default):
            weights[term] = trial.suggest_float(f"{WEIGHT_PREFIX}{term}", default / spread, default * spread, log=True)
    return weights


def sample_algo(trial: optuna.Trial, space: Mapping[str, tuple[str, tuple]] | None = None) -> dict[str, Any]:
    """Sample an algorithm's settings.

    :param trial: the Optuna trial
    :param space: setting -> ``(kind, arguments)``, an entry's ``tune_space`` (default: TD3's, :data:`ALGO_SPACE`)
    :return: experiment-entry keys -> values
    """
    values: dict[str, Any] = {}
    for key, (kind, args) in (ALGO_SPACE if space is None else space).items():
        name = f"{ALGO_PREFIX}{key}"
        if kind == "log":
            values[key] = trial.suggest_float(name, *args, log=True)
        elif kind == "float":
            values[key] = trial.suggest_float(name, *args)
        elif kind == "int":
            values[key] = trial.suggest_int(name, *args)
        else:
            values[key] = trial.suggest_categorical(name, *args)
    return values


def split_params(params: Mapping[str, Any]) -> tuple[dict[str, float], dict[str, Any]]:
    """Split a trial's parameters into reward weights and experiment-entry keys.

    :param params: ``{"weight.<term>": ..., "algo.<key>": ...}``
    :return: ``(weights, algo)`` without the prefixes
    :raises ValueError: a parameter with neither prefix
    """
    weights, algo = {}, {}
    for name, value in params.items():
        if name.startswith(WEIGHT_PREFIX):
            weights[name[len(WEIGHT_PREFIX) :]] = float(value)
        elif name.startswith(ALGO_PREFIX):
            algo[name[len(ALGO_PREFIX) :]] = value
        else:
            raise ValueError(f"parameter {name!r}: expected a name starting with {WEIGHT_PREFIX!r} or {ALGO_PREFIX!r}")
    return weights, algo


def entry_with_params(entry: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of an experiment entry with a trial's parameters put in place.

    Weights are merged into ``env_kwargs["config"]["reward_weights"]``; algorithm settings replace the
    entry's keys (a tuned ``noise_std`` turns on ``noise_type: normal`` if the entry has no noise).

    :param entry: rl-zoo3 experiment entry (with its ``env_kwargs``)
    :param params: Optuna parameters (see :func:`split_params`)
    :return: the new entry (the given one is not changed)
    """
    weights, algo = split_params(params)
    new = copy.deepcopy(dict(entry))
    if weights:
        env_kwargs = new.setdefault("env_kwargs", {}) or {}
        new["env_kwargs"] = env_kwargs
        config = env_kwargs.setdefault(WEIGHTS_KEY[0], {}) or {}
        env_kwargs[WEIGHTS_KEY[0]] = config
        config[WEIGHTS_KEY[1]] = {**(config.get(WEIGHTS_KEY[1]) or {}), **weights}
    new.update(algo)
    if "noise_std" in algo and not new.get("noise_type"):
        new["noise_type"] = "normal"
    return new


def weights_in(env_kwargs: Mapping[str, Any]) -> dict[str, float]:
    """The reward weights given in env kwargs (``{}`` when none)."""
    config = env_kwargs.get(WEIGHTS_KEY[0]) or {}
    return dict(config.get(WEIGHTS_KEY[1]) or {}) if isinstance(config, Mapping) else {}
