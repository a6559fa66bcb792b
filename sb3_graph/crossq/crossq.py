"""CrossQ (sb3-contrib) whose defaults suit graph observations; training is sb3-contrib's own ``CrossQ.train``."""

from __future__ import annotations

from typing import ClassVar

from sb3_contrib import CrossQ as ContribCrossQ
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.common.algorithm import GraphAlgorithmMixin, VertexEntropyMixin
from sb3_graph.common.buffers import GraphReplayBuffer
from sb3_graph.crossq.policies import GraphCrossQPolicy


class CrossQ(GraphAlgorithmMixin, VertexEntropyMixin, ContribCrossQ):
    """sb3-contrib's CrossQ with the graph defaults of :class:`sb3_graph.SAC`: the ``"GraphPolicy"``
    alias (:class:`~sb3_graph.GraphCrossQPolicy`), :class:`~sb3_graph.GraphReplayBuffer` by default
    (required: see :mod:`sb3_graph.crossq.policies`), an entropy target of ``-1`` per real vertex
    for ``target_entropy="auto"``, and graph ``VecNormalize`` refused.

    Every argument is sb3-contrib's :class:`sb3_contrib.CrossQ` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **ContribCrossQ.policy_aliases,
        "GraphPolicy": GraphCrossQPolicy,
    }
    graph_buffer_class = GraphReplayBuffer
