"""TQC (sb3-contrib) whose defaults suit graph observations; training is sb3-contrib's own ``TQC.train``."""

from __future__ import annotations

from typing import ClassVar

from sb3_contrib import TQC as ContribTQC
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.common.algorithm import GraphAlgorithmMixin, VertexEntropyMixin
from sb3_graph.common.buffers import GraphReplayBuffer
from sb3_graph.tqc.policies import GraphTQCPolicy


class TQC(GraphAlgorithmMixin, VertexEntropyMixin, ContribTQC):
    """sb3-contrib's TQC with the graph defaults of :class:`sb3_graph.SAC`: the ``"GraphPolicy"``
    alias (:class:`~sb3_graph.GraphTQCPolicy`), :class:`~sb3_graph.GraphReplayBuffer` by default,
    an entropy target of ``-1`` per real vertex for ``target_entropy="auto"``, and graph
    ``VecNormalize`` refused.

    Every argument is sb3-contrib's :class:`sb3_contrib.TQC` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **ContribTQC.policy_aliases,
        "GraphPolicy": GraphTQCPolicy,
    }
    graph_buffer_class = GraphReplayBuffer
