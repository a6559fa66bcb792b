"""rl-zoo3 style experiment files: read one entry, check it, and turn it into SB3 objects.

The YAML format is rl-zoo3's (one top-level entry per environment id), so the same file runs
with ``python -m rl_zoo3.train -conf FILE`` and with ``sb3-graph train --config FILE``. Values
that rl-zoo3 evaluates as Python (``policy_kwargs``, ``replay_buffer_class``) are *not*
evaluated here: :mod:`sb3_graph.files.safe_values` reads the subset that experiment files need
(literals, ``dict(...)``, dotted class names inside an allow-list of packages), so an experiment
file cannot run code through ``sb3-graph``. (rl-zoo3 itself still ``eval``s these strings: run
files from others with ``sb3-graph train``, or read them first.)
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.buffers import BaseBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.utils import LinearSchedule

from sb3_graph.files.policy_kwargs import PolicyKwargsError, check_policy_kwargs
from sb3_graph.files.safe_values import UnsafeValueError, load_yaml, parse_value, read_text_file

# Keys the trainer consumes itself; all others go to the algorithm's constructor.
TRAINER_KEYS = {"n_timesteps", "n_envs", "env_kwargs", "noise_type", "noise_std", "callback", "policy"}
# Keys of behaviour cloning before training (sb3-graph train --pretrain-from; see sb3_graph.behaviour_clone).
PRETRAIN_KEYS = {
    "pretrain_from", "pretrain_transitions", "pretrain_steps", "pretrain_critic_steps", "pretrain_rounds",
    "pretrain_beta",
}  # fmt: skip
TRAINER_KEYS |= PRETRAIN_KEYS
# Keys of rl-zoo3 that this trainer does not implement: refused rather than silently ignored.
UNSUPPORTED_KEYS = {"normalize", "frame_stack", "env_wrapper", "vec_env_wrapper", "monitor_kwargs"}
# Keys that would choose where a run writes: paths come from the command line only (train writes
# its TensorBoard logs into OUT/tb).
PATH_KEYS = {"tensorboard_log"}
# Largest experiment file read (an entry is a few hundred bytes).
MAX_FILE_BYTES = 1 << 20
# Bounds of the counts of an entry (docs/security.md): beyond them a run cannot fit in
# memory or end, so they are refused before anything is built.
MAX_TIMESTEPS = 10**9
MAX_ENVS = 256
MAX_BUFFER = 10**7
MAX_BATCH = 1 << 16
MAX_STEPS_PER_UPDATE = 10_000
NOISE_TYPES = ("normal", "ornstein-uhlenbeck")
# What a class named in an entry must be, by field (and by key inside policy_kwargs).
CLASS_BASES: dict[str, type] = {
    "policy": BasePolicy,
    "replay_buffer_class": BaseBuffer,
    "callback": BaseCallback,
    "activation_fn": th.nn.Module,
    "optimizer_class": th.optim.Optimizer,
    "features_extractor_class": BaseFeaturesExtractor,
}


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
    if not path.exists():
        raise ExperimentError(f"config file {str(path)!r} does not exist")
    try:
        content = load_yaml(read_text_file(path, "config file", MAX_FILE_BYTES), f"config file {str(path)!r}")
    except UnsafeValueError as error:
        raise ExperimentError(str(error)) from None
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
    if not all(isinstance(key, str) for key in entry):
        raise ExperimentError(f"entry {env_id!r}: every key must be a string, got {sorted(map(repr, entry))}")
    if "n_timesteps" not in entry:
        raise ExperimentError(f"entry {env_id!r}: n_timesteps is required")
    return dict(entry)


def resolve_object(value: Any, field: str) -> Any:
    """Turn an rl-zoo3 string into an object without evaluating it (see :mod:`sb3_graph.files.safe_values`).

    :param value: a dotted class name, a ``dict(...)``/literal expression, or any non-string (kept)
    :param field: the entry's field; a class named for a field of :data:`CLASS_BASES` (also
        inside ``policy_kwargs``) must subclass that field's base
    :return: the value
    :raises ExperimentError: naming the field, for anything outside the safe subset
    """
    if not isinstance(value, str):
        return value
    try:
        result = parse_value(value, field)
    except UnsafeValueError as error:
        raise ExperimentError(str(error)) from None
    _check_classes(result, field)
    return result


def _check_classes(value: Any, field: str) -> None:
    checks = [(field, value)]
    if isinstance(value, dict):
        checks += [(f"{field}.{key}", item) for key, item in value.items() if key in CLASS_BASES]
    for name, item in checks:
        base = CLASS_BASES.get(name.rpartition(".")[2])
        if base is not None and isinstance(item, type) and not issubclass(item, base):
            raise ExperimentError(f"{name}: {item.__module__}.{item.__qualname__} is not a {base.__name__}")
        if base is not None and name == field and not isinstance(item, type):
            raise ExperimentError(f"{field}: expected a class name such as a dotted path, got {item!r}")


def _schedule(value: Any, field: str) -> Any:
    """rl-zoo3 schedules (``learning_rate``, PPO's ``clip_range`` and ``clip_range_vf``):
    ``lin_<start>`` decays linearly to 0 over training."""
    if isinstance(value, str):
        start = _lin_start(value)
        if start is None:
            raise ExperimentError(f"{field}: expected a positive number or 'lin_<number>', got {value!r}")
        return LinearSchedule(start, 0.0, 1.0)
    return value


def _lin_start(value: str) -> float | None:
    if not value.startswith("lin_"):
        return None
    try:
        start = float(value[4:])
    except ValueError:
        return None
    return start if math.isfinite(start) and start > 0 else None


def _is_number(value: Any) -> bool:
    if not isinstance(value, (int, float, np.number)) or isinstance(value, (bool, np.bool_)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond float range (YAML and JSON integers have no size limit)
        return False


def _integer(minimum: int, maximum: int, also: tuple[int, ...] = ()) -> tuple[Any, str]:
    def check(value: Any) -> bool:
        return _is_number(value) and float(value).is_integer() and (minimum <= value <= maximum or value in also)

    extra = "".join(f" or {v}" for v in also)
    return check, f"an integer in [{minimum}, {maximum}]{extra}"


def _number(low: float, high: float = math.inf, low_open: bool = False) -> tuple[Any, str]:
    def check(value: Any) -> bool:
        return _is_number(value) and (value > low if low_open else value >= low) and value <= high

    bracket = "(" if low_open else "["
    upper = "inf)" if math.isinf(high) else f"{high:g}]"
    return check, f"a number in {bracket}{low:g}, {upper}"


def _train_freq(value: Any) -> bool:
    if isinstance(value, (list, tuple)):
        return len(value) == 2 and _integer(1, MAX_TIMESTEPS)[0](value[0]) and value[1] in ("step", "episode")
    return _integer(1, MAX_TIMESTEPS)[0](value)


# Checked before anything is built, so that a wrong value fails at once and names its field
# (not after training has started). Keys not listed go to the algorithm's constructor as they are.
ENTRY_RULES: dict[str, tuple[Any, str]] = {
    "n_timesteps": _integer(1, MAX_TIMESTEPS),
    "n_envs": _integer(1, MAX_ENVS),
    "buffer_size": _integer(1, MAX_BUFFER),
    "batch_size": _integer(1, MAX_BATCH),
    "n_steps": _integer(1, MAX_BUFFER),
    "n_epochs": _integer(1, MAX_STEPS_PER_UPDATE),
    "learning_starts": _integer(0, MAX_TIMESTEPS),
    "gradient_steps": _integer(1, MAX_STEPS_PER_UPDATE, also=(-1,)),
    "policy_delay": _integer(1, MAX_STEPS_PER_UPDATE),
    "gamma": _number(0.0, 1.0),
    "tau": _number(0.0, 1.0),
    "target_policy_noise": _number(0.0, 1e6),
    "target_noise_clip": _number(0.0, 1e6),
    "noise_std": _number(0.0, 1e6),
    "learning_rate": (
        lambda v: _number(0.0, low_open=True)[0](v) or (isinstance(v, str) and _lin_start(v) is not None),
        "a number > 0 or 'lin_<number>'",
    ),
    "train_freq": (_train_freq, "an integer >= 1 or [integer, 'step' or 'episode']"),
    "pretrain_from": (lambda v: v is None or (isinstance(v, str) and v.strip() != ""), "a planner word (string)"),
    "pretrain_transitions": _integer(1, MAX_BUFFER),
    "pretrain_steps": _integer(0, MAX_TIMESTEPS),
    "pretrain_critic_steps": _integer(0, MAX_TIMESTEPS),
    "pretrain_rounds": _integer(1, 1000),
    "pretrain_beta": _number(0.0, 1.0),
    "bc_coef": (
        lambda v: _number(0.0)[0](v) or (isinstance(v, str) and _lin_start(v) is not None),
        "a number >= 0 or 'lin_<number>'",
    ),
    "env_kwargs": (lambda v: v is None or isinstance(v, dict), "a mapping (of gym.make keyword arguments)"),
}


# Fields of a run record (``run.json``) that --resume reads: what each must be.
_RECORD_FIELDS: dict[str, tuple[Any, str]] = {
    "seed": (lambda v: _integer(0, 2**32 - 1)[0](v) and isinstance(v, int), "an integer in [0, 2**32 - 1]"),
    "wall_time_s": (lambda v: _is_number(v) and v >= 0, "a number >= 0"),
    "num_timesteps": (lambda v: isinstance(v, int) and _integer(0, MAX_TIMESTEPS)[0](v), "an integer >= 0"),
    "best_mean_reward": (
        lambda v: v is None or _is_number(v) or (isinstance(v, float) and v == -math.inf),
        "a finite number, null (no validation yet) or -Infinity",
    ),
    "sessions": (
        lambda v: isinstance(v, list)
        and all(isinstance(s, dict) and all(_is_number(x) for x in s.values()) for s in v),
        "a list of objects of numbers",
    ),
}


def check_run_record(record: Any, algorithms: list[str], source: str) -> dict[str, Any]:
    """Check the fields of a run record that ``--resume`` reads, before anything is trained.

    :param record: the parsed ``run.json``
    :param algorithms: the allowed values of ``algo``
    :param source: the file, for messages
    :return: ``record``
    :raises ExperimentError: ``<source>: field <name> must be <allowed>, got <value>``
    """
    if not isinstance(record, dict):
        raise ExperimentError(f"{source}: must be a JSON object, got {type(record).__name__}")
    if "algo" in record and record["algo"] not in algorithms:
        raise ExperimentError(f"{source}: field 'algo' must be one of {algorithms}, got {record['algo']!r}")
    for key, (check, allowed) in _RECORD_FIELDS.items():
        if key in record and not check(record[key]):
            raise ExperimentError(f"{source}: field {key!r} must be {allowed}, got {str(record[key])[:80]!r}")
    if "seed" not in record:
        raise ExperimentError(f"{source}: field 'seed' is missing")
    return record


def merge_env_kwargs(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    """Merge ``gym.make`` keyword arguments one level deep: a dict value (highway-env's
    ``config``) is updated key by key instead of replaced.

    :param base: e.g. the entry's ``env_kwargs``
    :param update: e.g. ``--env-kwargs``
    :return: a new dictionary
    """
    merged = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged


def check_entry(entry: dict[str, Any]) -> dict[str, Any]:
    """Check the values of :data:`ENTRY_RULES` in an entry; whole floats become ints (``!!float 2e5``).

    :param entry: hyperparameters (as read, with overrides applied)
    :return: a new dictionary
    :raises ExperimentError: ``<key> must be <allowed>, got <value>``, for the first wrong value
    """
    checked = dict(entry)
    paths = sorted(PATH_KEYS & set(checked))
    if paths:
        raise ExperimentError(
            f"{paths[0]}: an experiment file does not choose where a run writes (train writes OUT/tb; tune none)"
        )
    for key, (check, allowed) in ENTRY_RULES.items():
        if key in checked and not check(checked[key]):
            raise ExperimentError(f"{key} must be {allowed}, got {checked[key]!r}")
        value = checked.get(key)
        if allowed.startswith("an integer") and isinstance(value, (float, np.number)):
            checked[key] = int(value)
    return checked


def check_algorithm_keys(kwargs: dict[str, Any], algorithm_class: type, where: str = "") -> None:
    """Refuse a keyword that the algorithm's constructor does not take (a typo such as ``learnig_rate``), naming
    it and the closest keyword, before anything is built (a tuning study would otherwise fail every trial).

    :param kwargs: :func:`build_algorithm_kwargs`' output (or the entry's keys that reach the constructor)
    :param algorithm_class: the algorithm class (its ``__init__`` signature; one with ``**kwargs`` accepts any key)
    :param where: where the keys come from, for the message (e.g. ``"--trial-hyperparams"``)
    :raises ExperimentError: ``<key>: not a hyperparameter of <Algorithm> (did you mean <closest>?)``
    """
    import difflib
    import inspect

    # A constructor that passes **kwargs on (the graph mixin's, for its own keys such as bc_coef) takes
    # its own names plus those of the next constructor up the MRO, down to one without **kwargs.
    parameters: dict[str, inspect.Parameter] = {}
    for klass in algorithm_class.__mro__:
        if "__init__" not in vars(klass):
            continue
        try:
            own = inspect.signature(klass.__init__).parameters
        except (TypeError, ValueError):  # a constructor without a signature: nothing to check against
            return
        parameters.update({name: p for name, p in own.items() if p.kind is not inspect.Parameter.VAR_KEYWORD})
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in own.values()):
            break
    else:
        return  # every constructor takes **kwargs: any key may be right
    known = sorted(name for name in parameters if name not in ("self", "policy", "env", "args"))
    for key in kwargs:
        if key not in parameters:
            close = difflib.get_close_matches(key, known, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"its hyperparameters: {', '.join(known)}"
            source = f" ({where})" if where else ""
            raise ExperimentError(f"{key}{source}: not a hyperparameter of {algorithm_class.__name__}; {hint}")


def build_algorithm_kwargs(entry: dict[str, Any], action_dim: int) -> dict[str, Any]:
    """Constructor keyword arguments for the algorithm from one experiment entry.

    :param entry: hyperparameters as read by :func:`read_experiment`
    :param action_dim: size of the flat action space (for the exploration noise)
    :return: keyword arguments (``policy`` not included)
    :raises ExperimentError: a value of :data:`ENTRY_RULES` out of range, or an unsafe expression
    """
    entry = check_entry(entry)
    kwargs = {key: value for key, value in entry.items() if key not in TRAINER_KEYS}
    for field in ("policy_kwargs", "replay_buffer_class", "replay_buffer_kwargs"):
        if field in kwargs:
            kwargs[field] = resolve_object(kwargs[field], field)
    if "policy_kwargs" in kwargs:
        try:
            kwargs["policy_kwargs"] = check_policy_kwargs(kwargs["policy_kwargs"])
        except PolicyKwargsError as error:
            raise ExperimentError(str(error)) from None
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


#: folder of a run that holds what its experiment-file callbacks write (their path arguments are re-rooted there)
CALLBACK_FOLDER = "callbacks"
# Callback arguments that are paths (SB3: save_path, log_path, best_model_save_path) or parts of file names
# (name_prefix), by the end of their name.
_PATH_ARGUMENT = re.compile(r"(^|_)(path|dir|directory|folder|file|filename|log)$")
_NAME_ARGUMENT = re.compile(r"(^|_)(prefix|suffix|name)$")


def build_callbacks(entry: dict[str, Any], root: str | Path | None = None) -> list:
    """Callbacks listed under ``callback`` (dotted names, optionally with keyword arguments).

    No file chooses where a run writes: an argument that is a path (``save_path``, ``log_path``, any
    name ending in ``_path``, ``_dir``, ``_file`` ...) must be a relative path without ``..`` and is
    re-rooted under ``root / CALLBACK_FOLDER`` (the run folder's ``callbacks/``); without a ``root``
    (``tune``) it is refused. A name part (``name_prefix``) and every other string argument must not
    hold a path separator or ``..``.

    :param entry: the experiment entry
    :param root: the run folder, or ``None`` where there is none
    :return: the callbacks
    :raises ExperimentError: naming the callback and its argument
    """
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
        if not isinstance(name, str):
            raise ExperimentError(f"callback: expected a dotted class name, got {name!r}")
        if kwargs is not None and not isinstance(kwargs, dict):
            raise ExperimentError(f"callback {name}: keyword arguments must be a mapping, got {kwargs!r}")
        callback_class = resolve_object(name, "callback")
        kwargs = _rooted_arguments(name, kwargs or {}, root)
        try:
            callbacks.append(callback_class(**kwargs))
        except (TypeError, ValueError) as error:
            raise ExperimentError(f"callback {name}: {error}") from error
    return callbacks


def _rooted_arguments(name: str, kwargs: dict[str, Any], root: str | Path | None) -> dict[str, Any]:
    """The callback's keyword arguments with every path under ``root/callbacks`` (see :func:`build_callbacks`)."""
    rooted = {}
    for key, value in kwargs.items():
        field = f"callback {name}: argument {key!r}"
        if not isinstance(key, str):
            raise ExperimentError(f"callback {name}: argument names must be strings, got {key!r}")
        if _PATH_ARGUMENT.search(key) and value is not None:
            if root is None:
                raise ExperimentError(f"{field} is a path; this command has no run folder to put it in")
            if not isinstance(value, str) or not _relative_inside(value):
                raise ExperimentError(
                    f"{field} must be a relative path without '..' (it is put under the run's "
                    f"{CALLBACK_FOLDER}/ folder), got {value!r}"
                )
            target = Path(root) / CALLBACK_FOLDER / value
            if not target.resolve().is_relative_to(Path(root).resolve()):  # a link in the run folder
                raise ExperimentError(f"{field}: {value!r} leads out of the run folder (through a symbolic link)")
            rooted[key] = str(target)
            continue
        for text in _strings(value):
            if "/" in text or "\\" in text or ".." in text or (_NAME_ARGUMENT.search(key) and text.startswith(".")):
                raise ExperimentError(f"{field} must not name a path (no '/', '\\' or '..'), got {text!r}")
        rooted[key] = value
    return rooted


def _relative_inside(text: str) -> bool:
    path = Path(text)
    return bool(text.strip()) and not path.is_absolute() and ".." not in path.parts and "\\" not in text


def _strings(value: Any) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [text for item in [*value.keys(), *value.values()] for text in _strings(item)]
    if isinstance(value, (list, tuple)):
        return [text for item in value for text in _strings(item)]
    return []
