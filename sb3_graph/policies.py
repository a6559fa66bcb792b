"""Backward-compatible home of the TD3 graph policy.

The policies now live beside their algorithms (``sb3_graph/td3/policies.py``,
``sb3_graph/sac/policies.py``, ...) and the GNN pieces that they share in
:mod:`sb3_graph.common.networks`. This module re-exports the names it used to define, so that models saved
with ``sb3_graph.policies.GraphPolicy`` as their policy class (e.g. the repository's shipped
pretrained intersection planner) still load.
"""

from sb3_graph.common.networks import (
    POOLINGS,
    GraphCritic,
    GraphQNetwork,
    GraphTrunk,
    graph_dims,
    stacked_q_forward,
    stacked_trunk_forward,
)
from sb3_graph.td3.policies import GraphActor, GraphPolicy, GraphTD3Policy

__all__ = [
    "POOLINGS",
    "GraphActor",
    "GraphCritic",
    "GraphPolicy",
    "GraphQNetwork",
    "GraphTD3Policy",
    "GraphTrunk",
    "graph_dims",
    "stacked_q_forward",
    "stacked_trunk_forward",
]
