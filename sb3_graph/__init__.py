"""sb3-graph: graph neural network policies, compact graph buffers and graph defaults for
Stable-Baselines3 and sb3-contrib algorithms (TD3, DDPG, SAC, TQC, CrossQ, PPO, A2C).

The public names load on first use (PEP 562 ``__getattr__``), so that ``import sb3_graph`` (and with it
the ``sb3-graph`` command line, whose ``--help`` needs no network) does not import torch and
Stable-Baselines3; ``from sb3_graph import TD3`` works as before.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from sb3_graph.toy_envs import MAX_NEIGHBOUR_ID  # registers the toy task: gym.make("GraphMaxNeighbour-v0")

__version__ = "0.1.0"

# public name -> the module that defines it (imported on first access)
_LAZY = {
    "A2C": "sb3_graph.a2c",
    "GraphBatch": "sb3_graph.common.batching",
    "batch_to_padded": "sb3_graph.common.batching",
    "padded_to_batch": "sb3_graph.common.batching",
    "GraphReplayBuffer": "sb3_graph.common.buffers",
    "GraphRolloutBuffer": "sb3_graph.common.buffers",
    "behaviour_clone": "sb3_graph.common.cloning",
    "Demonstrations": "sb3_graph.common.cloning",
    "CrossQ": "sb3_graph.crossq",
    "GraphCrossQCritic": "sb3_graph.crossq",
    "GraphCrossQPolicy": "sb3_graph.crossq",
    "DDPG": "sb3_graph.ddpg",
    "RelationalMaxConv": "sb3_graph.common.layers",
    "GraphCritic": "sb3_graph.common.networks",
    "GraphQNetwork": "sb3_graph.common.networks",
    "GraphTrunk": "sb3_graph.common.networks",
    "PPO": "sb3_graph.ppo",
    "GraphActorCriticPolicy": "sb3_graph.ppo",
    "SAC": "sb3_graph.sac",
    "GraphSACActor": "sb3_graph.sac",
    "GraphSACPolicy": "sb3_graph.sac",
    "GraphSpace": "sb3_graph.common.spaces",
    "TD3": "sb3_graph.td3",
    "GraphActor": "sb3_graph.td3",
    "GraphPolicy": "sb3_graph.td3",
    "GraphTD3Policy": "sb3_graph.td3",
    "TQC": "sb3_graph.tqc",
    "GraphQuantileCritic": "sb3_graph.tqc",
    "GraphTQCPolicy": "sb3_graph.tqc",
}

if TYPE_CHECKING:  # what type checkers and IDEs see: the eager imports of before
    from sb3_graph.a2c import A2C
    from sb3_graph.common.batching import GraphBatch, batch_to_padded, padded_to_batch
    from sb3_graph.common.buffers import GraphReplayBuffer, GraphRolloutBuffer
    from sb3_graph.common.cloning import Demonstrations, behaviour_clone
    from sb3_graph.common.layers import RelationalMaxConv
    from sb3_graph.common.networks import GraphCritic, GraphQNetwork, GraphTrunk
    from sb3_graph.common.spaces import GraphSpace
    from sb3_graph.crossq import CrossQ, GraphCrossQCritic, GraphCrossQPolicy
    from sb3_graph.ddpg import DDPG
    from sb3_graph.ppo import PPO, GraphActorCriticPolicy
    from sb3_graph.sac import SAC, GraphSACActor, GraphSACPolicy
    from sb3_graph.td3 import TD3, GraphActor, GraphPolicy, GraphTD3Policy
    from sb3_graph.tqc import TQC, GraphQuantileCritic, GraphTQCPolicy

    POLICY_CLASSES: tuple[type, ...]


def __getattr__(name: str) -> Any:
    """Import a public name's module on first access (and keep the name in the package namespace)."""
    if name == "POLICY_CLASSES":
        # Every graph policy class of the package (e.g. for an allow-list of classes that a saved planner may name).
        policies = ("GraphPolicy", "GraphSACPolicy", "GraphTQCPolicy", "GraphCrossQPolicy", "GraphActorCriticPolicy")
        value: Any = tuple(__getattr__(policy) for policy in policies)
    elif name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "A2C",
    "DDPG",
    "PPO",
    "POLICY_CLASSES",
    "SAC",
    "TD3",
    "TQC",
    "CrossQ",
    "GraphActor",
    "GraphActorCriticPolicy",
    "GraphBatch",
    "GraphCritic",
    "GraphCrossQCritic",
    "GraphCrossQPolicy",
    "GraphPolicy",
    "GraphQNetwork",
    "GraphQuantileCritic",
    "GraphReplayBuffer",
    "GraphRolloutBuffer",
    "GraphSACActor",
    "GraphSACPolicy",
    "GraphSpace",
    "GraphTD3Policy",
    "GraphTQCPolicy",
    "GraphTrunk",
    "MAX_NEIGHBOUR_ID",
    "RelationalMaxConv",
    "__version__",
    "batch_to_padded",
    "behaviour_clone",
    "Demonstrations",
    "padded_to_batch",
]
