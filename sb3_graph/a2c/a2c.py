"""A2C whose defaults suit graph observations; training is SB3's own ``A2C.train``."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import A2C as SB3A2C
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.common.algorithm import GraphAlgorithmMixin
from sb3_graph.common.buffers import GraphRolloutBuffer
from sb3_graph.ppo.policies import GraphActorCriticPolicy


class A2C(GraphAlgorithmMixin, SB3A2C):
    """Stable-Baselines3's A2C with the graph defaults of :class:`sb3_graph.PPO`: the
    ``"GraphPolicy"`` alias (:class:`~sb3_graph.GraphActorCriticPolicy`),
    :class:`~sb3_graph.GraphRolloutBuffer` by default (A2C takes the whole rollout as one batch of
    graphs), and graph ``VecNormalize`` refused.

    Every argument is SB3's :class:`stable_baselines3.A2C` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **SB3A2C.policy_aliases,
        "GraphPolicy": GraphActorCriticPolicy,
    }
    graph_buffer_class = GraphRolloutBuffer
    buffer_class_attribute = "rollout_buffer_class"
