"""DDPG with graph defaults (TD3's graph policy with one critic)."""

from sb3_graph.ddpg.ddpg import DDPG
from sb3_graph.td3.policies import GraphPolicy as GraphDDPGPolicy

__all__ = ["DDPG", "GraphDDPGPolicy"]
