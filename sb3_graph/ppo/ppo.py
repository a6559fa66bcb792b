"""PPO whose defaults suit graph observations; training is SB3's own ``PPO.train``."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import PPO as SB3PPO
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.common.algorithm import GraphAlgorithmMixin
from sb3_graph.common.buffers import GraphRolloutBuffer
from sb3_graph.ppo.policies import GraphActorCriticPolicy


class PPO(GraphAlgorithmMixin, SB3PPO):
    """Stable-Baselines3's PPO with graph defaults:

    - ``"GraphPolicy"`` is a policy alias (:class:`~sb3_graph.GraphActorCriticPolicy`: per-vertex
      Gaussian, value from the pooled graph);
    - when the observation space is a :class:`~sb3_graph.GraphSpace` and no
      ``rollout_buffer_class`` is given, rollouts go to :class:`~sb3_graph.GraphRolloutBuffer`
      (real vertices and edges only; a minibatch of ``batch_size`` graphs is one disjoint graph);
    - a ``VecNormalize`` that would normalize the graph observation is refused.

    Advantage normalization (per minibatch, ``normalize_advantage=True``), clipping and the
    entropy bonus are SB3's; the entropy of a graph's action is the sum over its real vertices.

    Every argument is SB3's :class:`stable_baselines3.PPO` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **SB3PPO.policy_aliases,
        "GraphPolicy": GraphActorCriticPolicy,
    }
    graph_buffer_class = GraphRolloutBuffer
    buffer_class_attribute = "rollout_buffer_class"
