"""Policy files that cannot run code: weights as tensors, everything else as plain JSON.

Stable-Baselines3's ``model.zip`` pickles classes, spaces and schedules into its ``data`` entry;
``Algorithm.load`` unpickles them, so loading a model file that someone else made runs whatever
code they put there. This module gives two ways to load a policy that never unpickle:

- **the weights-only format** (``.safetensors``, written by :func:`save_policy` and
  ``sb3-graph export``): the policy's ``state_dict`` as safetensors tensors, and in the file's
  header metadata (key :data:`METADATA_KEY`) one JSON document::

      {"format": "sb3-graph-policy", "version": 1,
       "algorithm": "TD3", "policy_class": "GraphPolicy",
       "policy_kwargs": {"encoder_dim": 64, "activation_fn": {"class": "torch.nn.modules.activation.ReLU"}, ...},
       "observation_space": {"type": "GraphSpace", "max_nodes": 64, ...},
       "action_space": {"type": "Box", "shape": [64], "low": -1.0, "high": 1.0, "dtype": "float32"},
       "source": {...}}

  The policy class comes from :data:`POLICY_REGISTRY` (an allow-list per algorithm), classes in
  ``policy_kwargs`` only from :data:`sb3_graph.files.safe_values.ALLOWED_PACKAGES`.
- **SB3 zips, read safely** (:func:`read_sb3_zip`): the ``data`` entry is read as JSON and
  never unpickled. The policy class is read from the *opcodes* of its pickle with
  :mod:`pickletools` (decoded, not run; anything but one plain class reference is refused) and
  must be in the registry; spaces and ``policy_kwargs`` are rebuilt from the plain JSON that SB3
  writes next to each pickle; every other field (schedules, noise, buffers, fields added by
  someone) is ignored. ``policy.pth`` is read with ``torch.load(weights_only=True)``. What cannot
  be rebuilt this way is a :class:`PolicyFileError` that points to ``sb3-graph export``.

:func:`load_policy` picks the reader by suffix; ``trust=True`` restores SB3's full
``Algorithm.load`` for one's own files.
"""

from __future__ import annotations

import base64
import binascii
import importlib
import io
import json
import lzma
import math
import pickletools
import re
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_graph.files.policy_kwargs import check_finite_weights, check_policy_kwargs
from sb3_graph.files.safe_values import UnsafeValueError, check_structure, resolve_name
from sb3_graph.registry import ALGORITHMS

FORMAT = "sb3-graph-policy"
VERSION = 1
SUFFIX = ".safetensors"
METADATA_KEY = "sb3_graph"
# Planner policies by algorithm: algorithm name -> {policy name -> "module:Class"}, the weights-only
# export entries of :data:`sb3_graph.registry.ALGORITHMS`. A policy class outside the package is
# allowed with :func:`register_policy`.
POLICY_REGISTRY: dict[str, dict[str, str]] = {entry.name: dict(entry.file_policies) for entry in ALGORITHMS.values()}
# The algorithm class of each registered algorithm ("module:Class"), used by ``trust=True`` only.
ALGORITHM_CLASSES: dict[str, str] = {entry.name: entry.algorithm_class for entry in ALGORITHMS.values()}
# Largest zip entry read into memory (a model's data and weights are far smaller).
MAX_ENTRY_BYTES = 1 << 30
# Largest sizes of a space read from a file (a space allocates arrays of its size when built).
SPACE_LIMITS = {
    "max_nodes": 1 << 16,
    "node_features": 1 << 12,
    "max_edges": 1 << 22,
    "num_relations": 1 << 12,
    "edge_features": 1 << 12,
}
MAX_BOX_SIZE = 1 << 22
EXPORT_HINT = (
    "convert a model file that you trust once with `sb3-graph export MODEL.zip OUT.safetensors "
    "--trust-planner-files` (or pass --trust-planner-files to load it as SB3 does, running its pickles)"
)


class PolicyFileError(ValueError):
    """A policy file that cannot be loaded safely (the message names the file and the field)."""


@dataclass
class PolicyDescription:
    """What rebuilds a policy, all plain JSON.

    :param algorithm: key of :data:`POLICY_REGISTRY`, e.g. ``"TD3"``
    :param policy_class: registered policy name, e.g. ``"GraphPolicy"``
    :param policy_kwargs: constructor keyword arguments (classes as ``{"class": "dotted.Name"}``)
    :param observation_space: see :func:`space_to_json`
    :param action_space: see :func:`space_to_json`
    :param source: informative facts (file it came from, steps, versions)
    """

    algorithm: str
    policy_class: str
    policy_kwargs: dict[str, Any]
    observation_space: dict[str, Any]
    action_space: dict[str, Any]
    source: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(
            {
                "format": FORMAT,
                "version": VERSION,
                "algorithm": self.algorithm,
                "policy_class": self.policy_class,
                "policy_kwargs": self.policy_kwargs,
                "observation_space": self.observation_space,
                "action_space": self.action_space,
                "source": self.source,
            },
            allow_nan=False,
            sort_keys=False,
        )

    @classmethod
    def from_json(cls, text: str, source: str) -> PolicyDescription:
        try:
            data = json.loads(text)
        except (TypeError, ValueError, RecursionError) as error:
            raise PolicyFileError(f"{source}: metadata {METADATA_KEY!r} is not JSON ({error})") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise PolicyFileError(f"{source}: metadata {METADATA_KEY!r} is not an {FORMAT!r} document")
        if data.get("version") != VERSION:
            raise PolicyFileError(f"{source}: format version {data.get('version')!r} is not supported (expected 1)")
        for key, kind in (
            ("algorithm", str),
            ("policy_class", str),
            ("policy_kwargs", dict),
            ("observation_space", dict),
            ("action_space", dict),
        ):
            if not isinstance(data.get(key), kind):
                raise PolicyFileError(f"{source}: field {key!r} must be a {kind.__name__}, got {data.get(key)!r}")
        return cls(
            algorithm=data["algorithm"],
            policy_class=data["policy_class"],
            policy_kwargs=data["policy_kwargs"],
            observation_space=data["observation_space"],
            action_space=data["action_space"],
            source=data.get("source") if isinstance(data.get("source"), dict) else {},
        )


def register_policy(algorithm: str, name: str, path: str, algorithm_class: str | None = None) -> None:
    """Allow a policy class in policy files.

    :param algorithm: algorithm name, e.g. ``"SAC"``
    :param name: the policy's name in files, e.g. ``"GraphPolicy"``
    :param path: where it lives, ``"module:Class"``
    :param algorithm_class: ``"module:Class"`` of the algorithm (for ``trust=True`` loading)
    """
    POLICY_REGISTRY.setdefault(algorithm, {})[name] = path
    if algorithm_class is not None:
        ALGORITHM_CLASSES[algorithm] = algorithm_class


def _import(path: str) -> Any:
    module_name, _, attribute = path.partition(":")
    return getattr(importlib.import_module(module_name), attribute)


def registered_policy(algorithm: str, name: str, source: str = "policy file") -> type:
    """The class of a registered policy.

    :raises PolicyFileError: not in :data:`POLICY_REGISTRY`
    """
    path = POLICY_REGISTRY.get(algorithm, {}).get(name)
    if path is None:
        raise PolicyFileError(f"{source}: policy {algorithm}/{name} is not an allowed planner policy ({_allowed()})")
    return _import(path)


def _allowed() -> str:
    return "allowed: " + ", ".join(f"{a} {p}" for a, names in POLICY_REGISTRY.items() for p in names)


def _zip_fields(algorithm: str) -> tuple[str, ...]:
    for entry in ALGORITHMS.values():
        if entry.name == algorithm:
            return entry.zip_fields
    return ()


def _registry_entry(
    policy_class: type, source: str, prefer: str | None = None, zip_data: dict[str, Any] | None = None
) -> tuple[str, str]:
    """``(algorithm, policy name)`` of a registered policy class.

    Several algorithms may share a policy class (TD3 and DDPG, PPO and A2C): ``prefer`` picks that
    algorithm when it is one of them; else the fields of an SB3 zip's ``data`` (``zip_data``) pick the
    algorithm whose :attr:`~sb3_graph.registry.AlgorithmEntry.zip_fields` they hold, the most specific
    first; else the first registered.
    """
    found = [
        (algorithm, name)
        for algorithm, names in POLICY_REGISTRY.items()
        for name, path in names.items()
        if _import(path) is policy_class
    ]
    if not found:
        raise PolicyFileError(
            f"{source}: policy_class {policy_class.__module__}.{policy_class.__qualname__} is not an allowed "
            f"planner policy ({_allowed()})"
        )
    for algorithm, name in found:
        if algorithm == prefer:
            return algorithm, name
    if zip_data is not None:
        fitting = [(a, n) for a, n in found if all(key in zip_data for key in _zip_fields(a))]
        if fitting:
            return max(fitting, key=lambda item: len(_zip_fields(item[0])))
    return found[0]


# ------------------------------------------------------------------ spaces and kwargs as JSON
def _float_json(value: float) -> float | str:
    return value if math.isfinite(value) else ("inf" if value > 0 else "-inf" if value < 0 else "nan")


def _float_from_json(value: Any, what: str) -> float:
    if isinstance(value, str) and value in ("inf", "-inf"):
        return float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        raise ValueError(f"{what} must be a number, 'inf' or '-inf', got {value!r}")
    return float(value)


def _bounds_json(array: np.ndarray) -> Any:
    flat = np.asarray(array, dtype=np.float64).reshape(-1)
    if flat.size and np.all(flat == flat[0]):
        return _float_json(float(flat[0]))
    return [_float_json(float(v)) for v in flat]


def space_to_json(space: spaces.Space) -> dict[str, Any]:
    """A ``GraphSpace`` or ``Box`` as plain JSON.

    :raises PolicyFileError: any other space
    """
    from sb3_graph.common.spaces import GraphSpace

    if isinstance(space, GraphSpace):
        return {
            "type": "GraphSpace",
            "max_nodes": space.max_nodes,
            "node_features": space.node_features,
            "max_edges": space.max_edges,
            "num_relations": space.num_relations,
            "low": _float_json(space.low),
            "high": _float_json(space.high),
            # Only when there are any: files without edge features keep their bytes.
            **(
                {
                    "edge_features": space.edge_features,
                    "edge_low": _float_json(space.edge_low),
                    "edge_high": _float_json(space.edge_high),
                }
                if space.edge_features
                else {}
            ),
        }
    if isinstance(space, spaces.Box):
        return {
            "type": "Box",
            "shape": list(space.shape),
            "dtype": str(space.dtype),
            "low": _bounds_json(space.low),
            "high": _bounds_json(space.high),
        }
    raise PolicyFileError(f"space {space} cannot be written to a policy file (GraphSpace and Box only)")


def _int_field(data: dict[str, Any], key: str, what: str) -> int:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{what}.{key} must be an integer, got {value!r}")
    if not 0 <= value <= SPACE_LIMITS[key]:
        raise ValueError(f"{what}.{key} must be in [0, {SPACE_LIMITS[key]}], got {value}")
    return value


def space_from_json(data: Any, what: str = "space") -> spaces.Space:
    """Inverse of :func:`space_to_json` (strict: a wrong field is a ``ValueError`` naming it)."""
    from sb3_graph.common.spaces import GraphSpace

    if not isinstance(data, dict):
        raise ValueError(f"{what} must be an object, got {data!r}")
    kind = data.get("type")
    if kind == "GraphSpace":
        return GraphSpace(
            max_nodes=_int_field(data, "max_nodes", what),
            node_features=_int_field(data, "node_features", what),
            max_edges=_int_field(data, "max_edges", what),
            num_relations=_int_field(data, "num_relations", what),
            low=_float_from_json(data.get("low", "-inf"), f"{what}.low"),
            high=_float_from_json(data.get("high", "inf"), f"{what}.high"),
            edge_features=_int_field({"edge_features": 0, **data}, "edge_features", what),
            edge_low=_float_from_json(data.get("edge_low", "-inf"), f"{what}.edge_low"),
            edge_high=_float_from_json(data.get("edge_high", "inf"), f"{what}.edge_high"),
        )
    if kind == "Box":
        shape = data.get("shape")
        if (
            not isinstance(shape, list)
            or not 1 <= len(shape) <= 8
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in shape)
            or math.prod(shape) > MAX_BOX_SIZE
        ):
            raise ValueError(f"{what}.shape must be a list of positive integers (at most {MAX_BOX_SIZE} values), "
                             f"got {shape!r}")  # fmt: skip
        if data.get("dtype") not in ("float32", "float64"):
            raise ValueError(f"{what}.dtype must be 'float32' or 'float64', got {data.get('dtype')!r}")
        size = int(np.prod(shape))
        bounds = []
        for key in ("low", "high"):
            value = data.get(key)
            values = value if isinstance(value, list) else [value]
            if isinstance(value, list) and len(value) != size:
                raise ValueError(f"{what}.{key} has {len(value)} values, the shape holds {size}")
            bounds.append(np.array([_float_from_json(v, f"{what}.{key}") for v in values]))
        low, high = (np.broadcast_to(b, (size,)).reshape(shape) for b in bounds)
        if not np.all(low <= high):
            raise ValueError(f"{what}: low must not exceed high")
        dtype = np.dtype(data["dtype"])
        return spaces.Box(low.astype(dtype), high.astype(dtype), tuple(shape), dtype)
    raise ValueError(f"{what}.type must be 'GraphSpace' or 'Box', got {kind!r}")


def kwargs_to_json(kwargs: dict[str, Any], what: str = "policy_kwargs") -> dict[str, Any]:
    """Constructor keyword arguments as plain JSON; classes become ``{"class": "module.Name"}``.

    :raises PolicyFileError: a value that is neither JSON nor a class inside the allow-list
    """

    def encode(value: Any, where: str) -> Any:
        if value is None or isinstance(value, (bool, int, str)):
            return value
        if isinstance(value, float):
            if not math.isfinite(value):
                raise PolicyFileError(f"{where}: {value} cannot be written")
            return value
        if isinstance(value, (list, tuple)):
            return [encode(item, f"{where}[{k}]") for k, item in enumerate(value)]
        if isinstance(value, dict):
            if not all(isinstance(key, str) for key in value):
                raise PolicyFileError(f"{where}: only string keys can be written")
            return {key: encode(item, f"{where}.{key}") for key, item in value.items()}
        if isinstance(value, type):
            dotted = f"{value.__module__}.{value.__qualname__}"
            try:
                resolve_name(dotted, where)
            except UnsafeValueError as error:
                raise PolicyFileError(str(error)) from None
            return {"class": dotted}
        raise PolicyFileError(f"{where}: a {type(value).__name__} cannot be written to a policy file")

    return {key: encode(value, f"{what}.{key}") for key, value in kwargs.items()}


def kwargs_from_json(data: dict[str, Any], what: str = "policy_kwargs") -> dict[str, Any]:
    """Inverse of :func:`kwargs_to_json` (classes resolved inside the allow-list only)."""

    def decode(value: Any, where: str) -> Any:
        if isinstance(value, list):
            return [decode(item, f"{where}[{k}]") for k, item in enumerate(value)]
        if isinstance(value, dict):
            if set(value) == {"class"} and isinstance(value["class"], str):
                return resolve_name(value["class"], where)
            return {key: decode(item, f"{where}.{key}") for key, item in value.items()}
        return value

    return {key: decode(value, f"{what}.{key}") for key, value in data.items()}


# ------------------------------------------------------------------ building a policy
def build_policy(description: PolicyDescription, state: dict[str, th.Tensor], source: str, device: str = "cpu"):
    """A policy rebuilt from its description and loaded with ``state`` (strictly: every tensor).

    :raises PolicyFileError: an unregistered class, bad spaces or kwargs, or weights that do not fit
    """
    policy_class = registered_policy(description.algorithm, description.policy_class, source)
    try:
        observation_space = space_from_json(description.observation_space, "observation_space")
        action_space = space_from_json(description.action_space, "action_space")
        raw_kwargs = check_structure(description.policy_kwargs, "policy_kwargs", max_depth=8)
        kwargs = check_policy_kwargs(kwargs_from_json(raw_kwargs), "policy_kwargs", observation_space)
        check_finite_weights(state, "policy weights")
    except ValueError as error:  # UnsafeValueError and PolicyKwargsError included
        raise PolicyFileError(f"{source}: {error}") from None
    try:
        policy = policy_class(observation_space, action_space, lambda _: 0.0, **kwargs)
    except (TypeError, ValueError) as error:
        name = description.policy_class
        raise PolicyFileError(f"{source}: cannot build {name} from its policy_kwargs: {error}") from None
    try:
        policy.load_state_dict(state, strict=True)
    except (RuntimeError, ValueError, TypeError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise PolicyFileError(f"{source}: the weights do not fit {description.policy_class}: {first}") from None
    policy.set_training_mode(False)
    return policy.to(device)


def describe_policy(policy, algorithm: str, source: dict[str, Any] | None = None) -> PolicyDescription:
    """The description of a policy object (its registered name, kwargs and spaces)."""
    found_algorithm, name = _registry_entry(type(policy), "policy", prefer=algorithm)
    if found_algorithm != algorithm and algorithm in POLICY_REGISTRY:
        raise PolicyFileError(f"policy {name} is registered for {found_algorithm}, not {algorithm}")
    params = dict(policy._get_constructor_parameters())
    for key in ("observation_space", "action_space", "lr_schedule"):
        params.pop(key, None)
    return PolicyDescription(
        algorithm=found_algorithm,
        policy_class=name,
        policy_kwargs=kwargs_to_json(params),
        observation_space=space_to_json(policy.observation_space),
        action_space=space_to_json(policy.action_space),
        source=dict(source or {}),
    )


def resize_graph_policy(
    loaded: LoadedPolicy, max_nodes: int | None, max_edges: int | None, source: str
) -> LoadedPolicy:
    """The same network on graphs of another size: the observation space's ``max_nodes`` and
    ``max_edges`` and the per-vertex action space changed, the weights kept.

    A graph network's weights do not depend on the number of vertices or edges (the GNN of
    :class:`sb3_graph.GraphPolicy` shares them across vertices), so a policy trained on small graphs
    (a tuning preset) can run on scenes with more vehicles. A policy whose weights do depend on it
    (an MLP over the padded graph) does not fit and is refused.

    :param loaded: the policy
    :param max_nodes: the new ``max_nodes`` (``None``: unchanged)
    :param max_edges: the new ``max_edges`` (``None``: unchanged)
    :param source: the file's name, for errors
    :raises PolicyFileError: not a graph policy with one action row per vertex, or weights that
        depend on the graph's size
    """
    description = loaded.description
    obs, act = dict(description.observation_space), dict(description.action_space)
    if obs.get("type") != "GraphSpace":
        raise PolicyFileError(f"{source}: --max-nodes/--max-edges need a GraphSpace observation, got {obs.get('type')}")
    old_nodes = obs["max_nodes"]
    obs["max_nodes"] = old_nodes if max_nodes is None else int(max_nodes)
    obs["max_edges"] = obs["max_edges"] if max_edges is None else int(max_edges)
    if max_nodes is not None:
        if act.get("type") != "Box" or not act.get("shape") or act["shape"][0] != old_nodes:
            raise PolicyFileError(f"{source}: --max-nodes needs an action space with one row per vertex "
                                  f"(shape [{old_nodes}, ...]), got {act.get('shape')}")  # fmt: skip
        for key in ("low", "high"):
            if isinstance(act[key], list):  # one bound per vertex row: the rows must agree
                rows = np.asarray(act[key], dtype=object).reshape(old_nodes, -1)
                if not all((row == rows[0]).all() for row in rows):
                    raise PolicyFileError(f"{source}: action_space.{key} differs between vertices")
                act[key] = list(rows[0]) * obs["max_nodes"] if rows.shape[1] > 1 else rows[0, 0]
        act["shape"] = [obs["max_nodes"], *act["shape"][1:]]
    resized = PolicyDescription(
        algorithm=description.algorithm,
        policy_class=description.policy_class,
        policy_kwargs=description.policy_kwargs,
        observation_space=obs,
        action_space=act,
        source={**description.source, "resized_from": {"max_nodes": old_nodes,
                                                        "max_edges": description.observation_space["max_edges"]}},
    )  # fmt: skip
    state = {key: value.detach().to("cpu") for key, value in loaded.policy.state_dict().items()}
    return LoadedPolicy(build_policy(resized, state, source), resized)


# ------------------------------------------------------------------ the weights-only format
def save_policy(policy, path: str | Path, algorithm: str, source: dict[str, Any] | None = None) -> Path:
    """Write a policy in the weights-only format.

    :param policy: a policy whose class is in :data:`POLICY_REGISTRY`
    :param path: the ``.safetensors`` file to write (replaced if it exists)
    :param algorithm: the algorithm it belongs to, e.g. ``"TD3"``
    :param source: informative facts stored with it
    :return: the path
    """
    from safetensors.torch import save_file

    path = Path(path)
    description = describe_policy(policy, algorithm, source)
    tensors = {key: value.detach().to("cpu").contiguous().clone() for key, value in policy.state_dict().items()}
    save_file(tensors, str(path), metadata={METADATA_KEY: description.to_json()})
    return path


def read_weights_file(path: str | Path) -> tuple[PolicyDescription, dict[str, th.Tensor]]:
    """Read a weights-only policy file without building anything.

    :raises PolicyFileError: not a safetensors file, or metadata that is not this format
    """
    from safetensors import safe_open

    source = str(path)
    try:
        with safe_open(source, framework="pt", device="cpu") as handle:
            metadata = handle.metadata() or {}
            state = {key: handle.get_tensor(key) for key in handle.keys()}
    except Exception as error:  # noqa: BLE001 - the parser's own errors on a foreign file, all alike
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise PolicyFileError(f"{source}: not a {SUFFIX} policy file ({first})") from None
    if METADATA_KEY not in metadata:
        raise PolicyFileError(
            f"{source}: safetensors file without the {METADATA_KEY!r} metadata; write it with `sb3-graph export`"
        )
    return PolicyDescription.from_json(metadata[METADATA_KEY], source), state


# ------------------------------------------------------------------ SB3 zips without unpickling
_CLASS_REPR = re.compile(r"^<class '([A-Za-z_][\w.]*)'>$")
_NUMBER = re.compile(r"-?inf|nan|-?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?", re.IGNORECASE)


def pickled_class_reference(encoded: str) -> tuple[str, str] | None:
    """``(module, name)`` if a base64 pickle is exactly one reference to a global, else ``None``.

    The opcodes are decoded with :func:`pickletools.genops`, which runs nothing.
    """
    try:
        payload = base64.b64decode(encoded, validate=True)
        ops = [(op.name, arg) for op, arg, _ in pickletools.genops(payload)]
    except (binascii.Error, ValueError, TypeError):
        return None
    bookkeeping = ("PROTO", "FRAME", "MEMOIZE", "PUT", "BINPUT", "LONG_BINPUT")
    ops = [(name, arg) for name, arg in ops if name not in bookkeeping]
    strings = ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE")
    if len(ops) == 4 and ops[0][0] in strings and ops[1][0] in strings and ops[2][0] == "STACK_GLOBAL":
        if ops[3][0] == "STOP":
            return str(ops[0][1]), str(ops[1][1])
    if len(ops) == 2 and ops[0][0] == "GLOBAL" and ops[1][0] == "STOP":
        module, _, name = str(ops[0][1]).partition(" ")
        return module, name
    return None


def _zip_entry(archive: zipfile.ZipFile, name: str, source: str) -> bytes:
    try:
        info = archive.getinfo(name)
    except KeyError:
        raise PolicyFileError(
            f"{source}: no {name!r} in the zip; not a model saved by Stable-Baselines3 (model.save)"
        ) from None
    if info.file_size > MAX_ENTRY_BYTES:
        raise PolicyFileError(f"{source}: zip entry {name!r} is {info.file_size} bytes, more than a model holds")
    try:
        return archive.read(name)
    except (zipfile.BadZipFile, OSError, RuntimeError, EOFError, ValueError, lzma.LZMAError, zlib.error) as error:
        raise PolicyFileError(f"{source}: cannot read {name!r} from the zip ({error})") from None


# How SB3 names a GraphSpace in a model.zip: where the class lives, and where it lived when the
# shipped models were saved (``sb3_graph.spaces``, now a re-export of :mod:`sb3_graph.common.spaces`).
_GRAPH_SPACE_TYPES = ("<class 'sb3_graph.common.spaces.GraphSpace'>", "<class 'sb3_graph.spaces.GraphSpace'>")


def _rebuilt_space(value: Any, key: str, source: str) -> dict[str, Any]:
    """A space field of SB3's ``data`` as :func:`space_to_json` JSON, from its plain attributes."""
    if not isinstance(value, dict) or not isinstance(value.get(":type:"), str):
        raise PolicyFileError(f"{source}: field {key!r} is not a space saved by SB3")
    kind = value[":type:"]
    if kind in _GRAPH_SPACE_TYPES:
        names = ["max_nodes", "node_features", "max_edges", "num_relations", "low", "high"]
        names += ["edge_features", "edge_low", "edge_high"] if value.get("edge_features") else []
        rebuilt = {"type": "GraphSpace"}
        for name in names:
            rebuilt[name] = _float_json(value[name]) if isinstance(value.get(name), float) else value.get(name)
        return rebuilt
    if kind == "<class 'gymnasium.spaces.box.Box'>":
        shape = value.get("_shape")
        rebuilt = {"type": "Box", "shape": shape, "dtype": value.get("dtype")}
        for name in ("low", "high"):
            text = value.get(name)
            if not isinstance(text, str) or "..." in text:
                raise PolicyFileError(f"{source}: field {key!r}: its {name} is not stored in full; {EXPORT_HINT}")
            numbers = [float(token) for token in _NUMBER.findall(text)]
            rebuilt[name] = _bounds_json(np.array(numbers)) if numbers else None
        return rebuilt
    raise PolicyFileError(f"{source}: field {key!r} holds a {kind}; only GraphSpace and Box are read safely")


def _rebuilt_kwargs(value: Any, source: str) -> dict[str, Any]:
    """``policy_kwargs`` of SB3's ``data`` as :func:`kwargs_to_json` JSON, from its plain parts."""
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise PolicyFileError(f"{source}: field 'policy_kwargs' must be an object, got {type(value).__name__}")
    if ":serialized:" in value and value.get(":type:") != "<class 'dict'>":
        raise PolicyFileError(f"{source}: field 'policy_kwargs' holds a {value.get(':type:')}, not a dict")
    rebuilt = {}
    for key, item in value.items():
        if key in (":type:", ":serialized:"):
            continue
        match = _CLASS_REPR.match(item) if isinstance(item, str) else None
        rebuilt[key] = {"class": match.group(1)} if match else item
    return rebuilt


def read_sb3_zip(path: str | Path) -> tuple[PolicyDescription, dict[str, th.Tensor]]:
    """Read the policy of an SB3 ``model.zip`` without unpickling anything (see the module docstring).

    :raises PolicyFileError: not a zip, no ``data``/``policy.pth``, a policy class that is not a
        plain reference to a registered policy, or spaces/kwargs that cannot be rebuilt
    """
    source = str(path)
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as error:
        raise PolicyFileError(f"{source}: not a zip file written by model.save ({error})") from None
    with archive:
        raw = _zip_entry(archive, "data", source)
        weights = _zip_entry(archive, "policy.pth", source)
        version = None
        if "_stable_baselines3_version" in archive.namelist():
            version = _zip_entry(archive, "_stable_baselines3_version", source)[:40].decode(errors="replace").strip()
    try:
        data = json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError) as error:
        raise PolicyFileError(f"{source}: entry 'data' is not JSON ({error})") from None
    if not isinstance(data, dict):
        raise PolicyFileError(f"{source}: entry 'data' is not a JSON object")

    reference = data.get("policy_class")
    if not isinstance(reference, dict) or not isinstance(reference.get(":serialized:"), str):
        raise PolicyFileError(f"{source}: field 'policy_class' is missing or not a saved class")
    named = pickled_class_reference(reference[":serialized:"])
    if named is None:
        raise PolicyFileError(
            f"{source}: field 'policy_class' is not a plain class reference (it would run code when unpickled); "
            + EXPORT_HINT
        )
    try:
        policy_class = resolve_name(".".join(named), "policy_class")
    except UnsafeValueError as error:
        raise PolicyFileError(f"{source}: {error} ({_allowed()})") from None
    algorithm, name = _registry_entry(policy_class, source, zip_data=data)
    for key in ("observation_space", "action_space"):
        if key not in data:
            raise PolicyFileError(f"{source}: field {key!r} is missing")
    description = PolicyDescription(
        algorithm=algorithm,
        policy_class=name,
        policy_kwargs=_rebuilt_kwargs(data.get("policy_kwargs"), source),
        observation_space=_rebuilt_space(data["observation_space"], "observation_space", source),
        action_space=_rebuilt_space(data["action_space"], "action_space", source),
        source={
            "file": Path(source).name,
            "num_timesteps": data.get("num_timesteps") if isinstance(data.get("num_timesteps"), int) else None,
            "stable_baselines3": version,
        },
    )
    try:
        state = th.load(io.BytesIO(weights), map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - torch's restricted unpickler refuses in many ways
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise PolicyFileError(f"{source}: policy.pth is not a tensor file ({first[:300]})") from None
    if not isinstance(state, dict) or not all(isinstance(v, th.Tensor) for v in state.values()):
        raise PolicyFileError(f"{source}: policy.pth is not a state dict of tensors")
    return description, state


# ------------------------------------------------------------------ tensors into a policy that exists
def read_policy_tensors(path: str | Path) -> tuple[PolicyDescription, dict[str, th.Tensor]]:
    """The tensors of a policy file, without building a policy: a ``.safetensors`` policy file, or
    an SB3 ``.zip`` read without unpickling (:func:`read_sb3_zip`).

    :raises PolicyFileError: no such file, another suffix, a file that cannot be read safely, or
        weights with NaN or infinite values
    """
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise PolicyFileError(f"{source}: file not found")
    if path.suffix == SUFFIX:
        description, state = read_weights_file(path)
    elif path.suffix == ".zip":
        description, state = read_sb3_zip(path)
    else:
        raise PolicyFileError(f"{source}: expected a {SUFFIX} policy file or a model .zip")
    try:
        check_finite_weights(state, source)
    except ValueError as error:
        raise PolicyFileError(str(error)) from None
    return description, state


def load_policy_tensors(policy, state: dict[str, th.Tensor], source: str, algorithm: str | None = None) -> None:
    """Copy a state dict into a policy whose architecture must be the file's: the same tensor names
    and shapes, every one (fine-tuning; the policy's optimizer is left as it is).

    :param policy: the policy of a model just built (e.g. a tuning trial's)
    :param state: the tensors (:func:`read_policy_tensors`)
    :param source: the file, for messages
    :param algorithm: the file's algorithm, named in the message when the tensors do not fit
    :raises PolicyFileError: one line naming the first tensor that is missing, extra or of another shape
    """
    own = policy.state_dict()
    missing = sorted(set(own) - set(state))
    extra = sorted(set(state) - set(own))
    shapes = [key for key in sorted(set(own) & set(state)) if tuple(own[key].shape) != tuple(state[key].shape)]
    if missing or extra or shapes:
        if shapes:
            key = shapes[0]
            first = f"{key} is {list(state[key].shape)} in the file, {list(own[key].shape)} in the policy"
        elif missing:
            first = f"the file has no {missing[0]}"
        else:
            first = f"the policy has no {extra[0]}"
        counts = f"{len(shapes)} shapes differ, {len(missing)} tensors missing, {len(extra)} extra"
        mine = type(policy).__name__
        held = f"a {algorithm} policy" if algorithm else "a policy"
        raise PolicyFileError(
            f"{source}: {held} of another architecture than the {mine} to train ({first}; {counts}): "
            "the policy_kwargs of the experiment entry and the observation's features must be the file's"
        )
    policy.load_state_dict(state, strict=True)


def init_from_file(policy, path: str | Path) -> PolicyDescription:
    """Start a policy just built from the tensors of a policy file (fine-tuning; nothing unpickled):
    :func:`read_policy_tensors`, then :func:`load_policy_tensors`.

    :return: the file's description
    :raises PolicyFileError: an unreadable file or another architecture (one line)
    """
    description, state = read_policy_tensors(path)
    load_policy_tensors(policy, state, str(path), description.algorithm)
    return description


# ------------------------------------------------------------------ one entry point
@dataclass
class LoadedPolicy:
    """A policy loaded from a file.

    :param policy: the SB3 policy (``predict``, ``observation_space``, ``action_space``)
    :param description: what rebuilt it
    """

    policy: Any
    description: PolicyDescription


def load_policy(path: str | Path, device: str = "cpu", trust: bool = False) -> LoadedPolicy:
    """Load a policy from a ``.safetensors`` policy file or an SB3 ``.zip``, never unpickling
    unless ``trust`` is set.

    :param path: the file
    :param device: torch device
    :param trust: load an SB3 zip with its algorithm's full ``load`` (runs its pickles: only for
        one's own files)
    :raises PolicyFileError: a file that cannot be loaded safely, naming the file and the field
    """
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise PolicyFileError(f"{source}: file not found")
    if path.suffix == SUFFIX:
        description, state = read_weights_file(path)
        return LoadedPolicy(build_policy(description, state, source, device), description)
    if path.suffix != ".zip":
        raise PolicyFileError(f"{source}: expected a {SUFFIX} policy file or a model .zip")
    if trust:
        return _load_trusted(path, device)
    description, state = read_sb3_zip(path)
    return LoadedPolicy(build_policy(description, state, source, device), description)


def _load_trusted(path: Path, device: str) -> LoadedPolicy:
    algorithm = "TD3"
    try:  # the registry entry when the file names one; SB3 checks the rest
        algorithm = read_sb3_zip(path)[0].algorithm
    except PolicyFileError:
        pass
    algorithm_class: Callable = _import(ALGORITHM_CLASSES[algorithm])
    try:
        model = algorithm_class.load(str(path), device=device)
    except Exception as error:  # noqa: BLE001 - SB3 raises many kinds on a foreign file
        raise PolicyFileError(f"{path}: {algorithm}.load failed: {type(error).__name__}: {error}") from None
    try:
        check_finite_weights(model.policy, str(path))
    except ValueError as error:
        raise PolicyFileError(str(error)) from None
    source = {"file": path.name, "num_timesteps": int(model.num_timesteps)}
    description = describe_policy(model.policy, algorithm, source)
    model.policy.set_training_mode(False)
    return LoadedPolicy(model.policy, description)
