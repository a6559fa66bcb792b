"""PPO with graph defaults and the actor-critic graph policy (also used by A2C)."""

from sb3_graph.ppo.policies import GraphActorCriticPolicy
from sb3_graph.ppo.ppo import PPO

__all__ = ["PPO", "GraphActorCriticPolicy"]
