"""SAC whose defaults suit graph observations; training is SB3's own ``SAC.train``."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import SAC as SB3SAC
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.common.algorithm import GraphAlgorithmMixin, VertexEntropyMixin
from sb3_graph.common.buffers import GraphReplayBuffer
from sb3_graph.sac.policies import GraphSACPolicy


class SAC(GraphAlgorithmMixin, VertexEntropyMixin, SB3SAC):
    """Stable-Baselines3's SAC with graph defaults:

    - ``"GraphPolicy"`` is a policy alias (:class:`~sb3_graph.GraphSACPolicy`);
    - :class:`~sb3_graph.GraphReplayBuffer` by default for a :class:`~sb3_graph.GraphSpace`;
    - ``target_entropy="auto"`` is ``-1`` per real vertex (``-n_b`` for a graph of ``n_b``
      vertices) instead of SB3's ``-max_nodes`` for every graph (see
      :class:`~sb3_graph.common.algorithm.VertexEntropyMixin`); a number keeps SB3's meaning;
    - a ``VecNormalize`` that would normalize the graph observation is refused.

    Every argument is SB3's :class:`stable_baselines3.SAC` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **SB3SAC.policy_aliases,
        "GraphPolicy": GraphSACPolicy,
    }
    graph_buffer_class = GraphReplayBuffer
