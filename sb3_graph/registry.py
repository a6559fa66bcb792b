"""Every algorithm of the package, one entry each: what ``train``, ``export``, the weights-only
policy files (:mod:`sb3_graph.files.policy_files`), ``tune`` and a learned planner need to know about it.

An entry names its parts as ``"module:attribute"`` strings, so that reading the registry imports
no algorithm (``sb3-graph --help`` stays fast). A new algorithm is its folder (``<algo>/<algo>.py``
and ``<algo>/policies.py``, as sb3-contrib) plus one line in :data:`ALGORITHMS`.

The *deterministic action* of every registered policy is what SB3's ``predict(obs,
deterministic=True)`` returns: TD3's and DDPG's actor output, the squashed mean ``tanh(mu)`` of
SAC's, TQC's and CrossQ's Gaussian (then unscaled to the action bounds), the mean of PPO's and
A2C's Gaussian (then clipped to the bounds). :func:`deterministic_vertex_actions` computes it per
real vertex straight from a :class:`~sb3_graph.GraphBatch`, without the padded observation.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

#: ``--tune-algo`` search spaces (see ``AlgorithmEntry.tune_space``). Ranges bracket SB3's and
#: rl-zoo3's defaults of each algorithm.
_OFF_POLICY_SPACE: dict[str, tuple[str, tuple]] = {
    "learning_rate": ("log", (1e-4, 3e-3)),
    "batch_size": ("categorical", ((64, 128, 256),)),
    "gamma": ("categorical", ((0.9, 0.95, 0.98, 0.99, 0.995),)),
    "tau": ("log", (1e-3, 2e-2)),
}
_TD3_SPACE = {**_OFF_POLICY_SPACE, "noise_std": ("float", (0.05, 0.5)), "policy_delay": ("int", (1, 4))}
_CROSSQ_SPACE = {key: _OFF_POLICY_SPACE[key] for key in ("learning_rate", "batch_size", "gamma")}
_ON_POLICY_SPACE: dict[str, tuple[str, tuple]] = {
    "learning_rate": ("log", (1e-4, 3e-3)),
    "gamma": ("categorical", ((0.9, 0.95, 0.98, 0.99, 0.995),)),
    "gae_lambda": ("categorical", ((0.9, 0.95, 0.98, 1.0),)),
    "ent_coef": ("log", (1e-6, 1e-2)),
}
_PPO_SPACE = {**_ON_POLICY_SPACE, "batch_size": ("categorical", ((32, 64, 128),))}


@dataclass(frozen=True)
class AlgorithmEntry:
    """What the package knows about one algorithm.

    :param name: its class name: the ``algorithm`` field of policy files, the TensorBoard log name
    :param algorithm_class: ``"module:Class"`` of the ``sb3_graph`` alias (graph buffer by default)
    :param policy: ``"module:Class"`` of its graph policy (the class behind its ``"GraphPolicy"`` alias)
    :param buffer: ``"module:Class"`` of the graph buffer it uses for a ``GraphSpace``
    :param file_policies: the weights-only export entry: policy names allowed in policy files of
        this algorithm -> ``"module:Class"`` (the first is the name written)
    :param vertex_actions: ``"module:function"`` of ``(policy, graphs) -> (N,)`` deterministic
        action of each real vertex before unscaling or clipping (see the module docstring)
    :param on_policy: a rollout-buffer algorithm (PPO, A2C)
    :param zip_fields: fields of an SB3 ``model.zip``'s ``data`` that only this algorithm writes, to
        tell it from another algorithm with the same policy class (PPO from A2C)
    :param tune_space: its defaults for tuning: the settings that ``sb3-graph tune --tune-algo``
        samples, setting -> ``(kind, arguments)`` (kinds ``log``, ``float``, ``int``, ``categorical``)
    """

    name: str
    algorithm_class: str
    policy: str
    buffer: str
    file_policies: Mapping[str, str]
    vertex_actions: str
    on_policy: bool = False
    zip_fields: tuple[str, ...] = ()
    tune_space: Mapping[str, tuple[str, tuple]] = field(default_factory=dict)

    def load_class(self) -> type:
        """The algorithm class (imports it)."""
        return import_object(self.algorithm_class)

    def policy_class(self) -> type:
        """The graph policy class (imports it)."""
        return import_object(self.policy)


_REPLAY = "sb3_graph.common.buffers:GraphReplayBuffer"
_ROLLOUT = "sb3_graph.common.buffers:GraphRolloutBuffer"
_ACTOR = "sb3_graph.registry:actor_vertex_actions"
_SQUASHED = "sb3_graph.registry:squashed_mean_vertex_actions"
_MEAN = "sb3_graph.registry:mean_vertex_actions"

#: rl-zoo3's ``--algo`` name -> entry, in the order of ``--algo``'s choices.
ALGORITHMS: dict[str, AlgorithmEntry] = {
    "td3": AlgorithmEntry(
        "TD3", "sb3_graph.td3:TD3", "sb3_graph.td3.policies:GraphPolicy", _REPLAY,
        {"GraphPolicy": "sb3_graph.policies:GraphPolicy"}, _ACTOR, tune_space=_TD3_SPACE,
    ),
    "ddpg": AlgorithmEntry(
        "DDPG", "sb3_graph.ddpg:DDPG", "sb3_graph.td3.policies:GraphPolicy", _REPLAY,
        {"GraphPolicy": "sb3_graph.policies:GraphPolicy"}, _ACTOR,
        tune_space={**_OFF_POLICY_SPACE, "noise_std": _TD3_SPACE["noise_std"]},
    ),
    "sac": AlgorithmEntry(
        "SAC", "sb3_graph.sac:SAC", "sb3_graph.sac.policies:GraphSACPolicy", _REPLAY,
        {"GraphSACPolicy": "sb3_graph.sac.policies:GraphSACPolicy"}, _SQUASHED, tune_space=_OFF_POLICY_SPACE,
    ),
    "tqc": AlgorithmEntry(
        "TQC", "sb3_graph.tqc:TQC", "sb3_graph.tqc.policies:GraphTQCPolicy", _REPLAY,
        {"GraphTQCPolicy": "sb3_graph.tqc.policies:GraphTQCPolicy"}, _SQUASHED, tune_space=_OFF_POLICY_SPACE,
    ),
    "crossq": AlgorithmEntry(
        "CrossQ", "sb3_graph.crossq:CrossQ", "sb3_graph.crossq.policies:GraphCrossQPolicy", _REPLAY,
        {"GraphCrossQPolicy": "sb3_graph.crossq.policies:GraphCrossQPolicy"}, _SQUASHED, tune_space=_CROSSQ_SPACE,
    ),
    "ppo": AlgorithmEntry(
        "PPO", "sb3_graph.ppo:PPO", "sb3_graph.ppo.policies:GraphActorCriticPolicy", _ROLLOUT,
        {"GraphActorCriticPolicy": "sb3_graph.ppo.policies:GraphActorCriticPolicy"}, _MEAN, on_policy=True,
        zip_fields=("clip_range", "n_epochs"), tune_space=_PPO_SPACE,
    ),
    "a2c": AlgorithmEntry(
        "A2C", "sb3_graph.a2c:A2C", "sb3_graph.ppo.policies:GraphActorCriticPolicy", _ROLLOUT,
        {"GraphActorCriticPolicy": "sb3_graph.ppo.policies:GraphActorCriticPolicy"}, _MEAN, on_policy=True,
        tune_space=_ON_POLICY_SPACE,
    ),
}  # fmt: skip


def import_object(path: str) -> Any:
    """The attribute named by ``"module:attribute"`` (imports the module)."""
    module_name, _, attribute = path.partition(":")
    return getattr(importlib.import_module(module_name), attribute)


def algorithm_entry(algo: str) -> AlgorithmEntry:
    """The entry of an ``--algo`` name (``"td3"``) or a class name (``"TD3"``).

    :raises KeyError: an unknown algorithm, naming the known ones
    """
    if algo in ALGORITHMS:
        return ALGORITHMS[algo]
    for entry in ALGORITHMS.values():
        if entry.name == algo:
            return entry
    raise KeyError(f"unknown algorithm {algo!r} (known: {', '.join(ALGORITHMS)})")


def entry_of_policy(policy: Any) -> AlgorithmEntry | None:
    """The first entry whose graph policy class is exactly ``type(policy)`` (``None``: not registered)."""
    for entry in ALGORITHMS.values():
        if type(policy) is entry.policy_class():
            return entry
    return None


# ------------------------------------------------------------------ deterministic actions per vertex
def actor_vertex_actions(policy: Any, graphs: Any) -> Any:
    """TD3's and DDPG's deterministic actor: ``tanh(head(h_i))`` of each real vertex, in ``[-1, 1]``."""
    return policy.actor.vertex_actions(graphs)


def squashed_mean_vertex_actions(policy: Any, graphs: Any) -> Any:
    """SAC's, TQC's and CrossQ's deterministic action: ``tanh`` of each vertex's Gaussian mean."""
    import torch

    return torch.tanh(policy.actor.vertex_distribution(graphs)[0])


def mean_vertex_actions(policy: Any, graphs: Any) -> Any:
    """PPO's and A2C's deterministic action: each vertex's Gaussian mean (SB3 then clips it)."""
    return policy.vertex_distribution(graphs)[0]


def deterministic_vertex_actions(policy: Any, graphs: Any) -> Any:
    """``(N,)`` deterministic action of each real vertex of ``graphs`` in the policy's own units:
    SB3's ``predict(obs, deterministic=True)`` is this, padded, then unscaled (``squash_output``)
    or clipped to the action bounds.

    :param policy: a policy whose class is a registered graph policy (exactly, not a subclass)
    :param graphs: a :class:`~sb3_graph.GraphBatch`
    :raises TypeError: an unregistered policy class
    """
    entry = entry_of_policy(policy)
    if entry is None:
        raise TypeError(f"{type(policy).__qualname__} is not a registered graph policy")
    return import_object(entry.vertex_actions)(policy, graphs)
