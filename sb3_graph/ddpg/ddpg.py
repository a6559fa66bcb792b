"""DDPG whose defaults suit graph observations; training is SB3's own (TD3's) ``train``."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import DDPG as SB3DDPG
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.common.algorithm import GraphAlgorithmMixin
from sb3_graph.common.buffers import GraphReplayBuffer
from sb3_graph.td3.policies import GraphPolicy


class DDPG(GraphAlgorithmMixin, SB3DDPG):
    """Stable-Baselines3's DDPG with the graph defaults of :class:`sb3_graph.TD3`.

    SB3's DDPG is TD3 with one critic, no policy delay and no target smoothing, and uses TD3's
    policy class: ``"GraphPolicy"`` is :class:`~sb3_graph.GraphPolicy` (DDPG sets ``n_critics=1``).

    Every argument is SB3's :class:`stable_baselines3.DDPG` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **SB3DDPG.policy_aliases,
        "GraphPolicy": GraphPolicy,
    }
    graph_buffer_class = GraphReplayBuffer
