"""A2C with graph defaults (the actor-critic graph policy of PPO)."""

from sb3_graph.a2c.a2c import A2C

__all__ = ["A2C"]
