"""TD3 with graph defaults: ``GraphReplayBuffer`` for graph spaces and the ``GraphPolicy`` alias."""

from sb3_graph.td3.policies import GraphActor, GraphPolicy, GraphTD3Policy
from sb3_graph.td3.td3 import TD3

__all__ = ["TD3", "GraphActor", "GraphPolicy", "GraphTD3Policy"]
