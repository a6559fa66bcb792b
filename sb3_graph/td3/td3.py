"""TD3 whose defaults suit graph observations; training is SB3's own ``TD3.train``."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import TD3 as SB3TD3
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.common.algorithm import GraphAlgorithmMixin
from sb3_graph.common.buffers import GraphReplayBuffer
from sb3_graph.td3.policies import GraphPolicy


class TD3(GraphAlgorithmMixin, SB3TD3):
    """Stable-Baselines3's TD3 with graph defaults:

    - ``"GraphPolicy"`` is a policy alias (:class:`~sb3_graph.GraphPolicy`), next to SB3's aliases;
    - when the observation space is a :class:`~sb3_graph.GraphSpace` and no
      ``replay_buffer_class`` is given, transitions go to :class:`~sb3_graph.GraphReplayBuffer`,
      which stores only real vertices and edges (and computes n-step returns for ``n_steps > 1``);
    - a ``VecNormalize`` that would normalize the graph observation is refused.

    Every argument is SB3's :class:`stable_baselines3.TD3` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **SB3TD3.policy_aliases,
        "GraphPolicy": GraphPolicy,
    }
    graph_buffer_class = GraphReplayBuffer
