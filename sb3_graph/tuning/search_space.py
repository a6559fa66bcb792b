"""What a trial samples: the reward weights (log scales around their defaults), optionally keys of the
environment's config (``--tune-config``) and the settings of the trained algorithm (its registry entry's
``tune_space``).

Parameter names carry a prefix that says where the value goes:

- ``weight.<term>``: the reward weight of ``<term>``, sampled log-uniformly in
  ``[w0 / spread, w0 * spread]`` around its default ``w0``. The defaults are the weights of the
  environment that the study's entry makes, read from its ``config["reward_weights"]`` (for the
  intersection: the preset that ``config["reward"]`` selects, the task reward's by default, the
  paper's Table I for ``reward: paper``, with the entry's own ``reward_weights`` over it), so this
  module needs no knowledge of the domain. The weights reach the environment as
  ``env_kwargs["config"]["reward_weights"]`` (highway-env's configuration habit).
- ``config.<key>``: a number in the environment's config, sampled in ``[low, high]`` (log or
  linear, :func:`parse_config_space`), e.g. the intersection's ``residual_scale`` for a residual
  policy; it reaches the environment as ``env_kwargs["config"][key]``.
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
CONFIG_PREFIX = "config."
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


def parse_config_space(specs: list[str] | tuple[str, ...]) -> dict[str, tuple[float, float, bool]]:
    """``["residual_scale:0.25:2"]`` -> ``{"residual_scale": (0.25, 2.0, False)}`` (``KEY:LOW:HIGH[:log]``).

    :param specs: one ``KEY:LOW:HIGH`` or ``KEY:LOW:HIGH:log`` per key
    :return: key -> ``(low, high, log)``
    :raises ValueError: a malformed spec, ``low >= high``, a non-positive bound on a log scale, a key twice
    """
    space: dict[str, tuple[float, float, bool]] = {}
    for spec in specs:
        parts = str(spec).split(":")
        if len(parts) not in (3, 4) or not parts[0] or (len(parts) == 4 and parts[3] not in ("log", "linear")):
            raise ValueError(f"expected KEY:LOW:HIGH or KEY:LOW:HIGH:log, got {spec!r}")
        key = parts[0]
        try:
            low, high = float(parts[1]), float(parts[2])
        except ValueError:
            raise ValueError(f"{spec!r}: LOW and HIGH must be numbers") from None
        log = len(parts) == 4 and parts[3] == "log"
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f"{spec!r}: expected finite LOW < HIGH")
        if log and low <= 0:
            raise ValueError(f"{spec!r}: a log scale needs LOW > 0")
        if key in space:
            raise ValueError(f"{spec!r}: key {key!r} given twice")
        space[key] = (low, high, log)
    return space


def sample_config(trial: optuna.Trial, space: Mapping[str, tuple[float, float, bool]]) -> dict[str, float]:
    """Sample the environment-config keys of ``space`` (see :func:`parse_config_space`)."""
    return {
        key: trial.suggest_float(f"{CONFIG_PREFIX}{key}", low, high, log=log) for key, (low, high, log) in space.items()
    }


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
    """Split a trial's parameters into reward weights and experiment-entry keys (``config.*`` ones:
    :func:`config_params`).

    :param params: ``{"weight.<term>": ..., "config.<key>": ..., "algo.<key>": ...}``
    :return: ``(weights, algo)`` without the prefixes
    :raises ValueError: a parameter with none of the prefixes
    """
    weights, algo = {}, {}
    for name, value in params.items():
        if name.startswith(WEIGHT_PREFIX):
            weights[name[len(WEIGHT_PREFIX) :]] = float(value)
        elif name.startswith(ALGO_PREFIX):
            algo[name[len(ALGO_PREFIX) :]] = value
        elif not name.startswith(CONFIG_PREFIX) or name == CONFIG_PREFIX:
            raise ValueError(
                f"parameter {name!r}: expected a name starting with {WEIGHT_PREFIX!r}, {CONFIG_PREFIX!r} or "
                f"{ALGO_PREFIX!r}"
            )
    return weights, algo


def config_params(params: Mapping[str, Any]) -> dict[str, float]:
    """The environment-config keys among a trial's parameters (``config.<key>``), without the prefix."""
    return {
        name[len(CONFIG_PREFIX) :]: float(value)
        for name, value in params.items()
        if name.startswith(CONFIG_PREFIX) and name != CONFIG_PREFIX
    }


def entry_with_params(entry: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of an experiment entry with a trial's parameters put in place.

    Weights are merged into ``env_kwargs["config"]["reward_weights"]``, config keys set in
    ``env_kwargs["config"]``; algorithm settings replace the
    entry's keys (a tuned ``noise_std`` turns on ``noise_type: normal`` if the entry has no noise).

    :param entry: rl-zoo3 experiment entry (with its ``env_kwargs``)
    :param params: Optuna parameters (see :func:`split_params`)
    :return: the new entry (the given one is not changed)
    """
    weights, algo = split_params(params)
    settings = config_params(params)
    new = copy.deepcopy(dict(entry))
    if weights or settings:
        env_kwargs = new.setdefault("env_kwargs", {}) or {}
        new["env_kwargs"] = env_kwargs
        config = env_kwargs.setdefault(WEIGHTS_KEY[0], {}) or {}
        env_kwargs[WEIGHTS_KEY[0]] = config
        config.update(settings)
        if weights:
            config[WEIGHTS_KEY[1]] = {**(config.get(WEIGHTS_KEY[1]) or {}), **weights}
    new.update(algo)
    if "noise_std" in algo and not new.get("noise_type"):
        new["noise_type"] = "normal"
    return new


def weights_in(env_kwargs: Mapping[str, Any]) -> dict[str, float]:
    """The reward weights given in env kwargs (``{}`` when none)."""
    config = env_kwargs.get(WEIGHTS_KEY[0]) or {}
    return dict(config.get(WEIGHTS_KEY[1]) or {}) if isinstance(config, Mapping) else {}
