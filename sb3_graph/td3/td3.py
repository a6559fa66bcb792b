"""TD3 whose defaults suit graph observations; training is SB3's own ``TD3.train``."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import TD3 as SB3TD3
from stable_baselines3.common.policies import BasePolicy

from sb3_graph.buffers import GraphReplayBuffer
from sb3_graph.policies import GraphPolicy
from sb3_graph.spaces import GraphSpace


class TD3(SB3TD3):
    """Stable-Baselines3's TD3 with two graph defaults:

    - ``"GraphPolicy"`` is a policy alias (:class:`~sb3_graph.GraphPolicy`), next to SB3's aliases;
    - when the observation space is a :class:`~sb3_graph.GraphSpace` and no
      ``replay_buffer_class`` is given, transitions go to :class:`~sb3_graph.GraphReplayBuffer`,
      which stores only real vertices and edges.

    Every argument is SB3's :class:`stable_baselines3.TD3` argument; see its documentation.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **SB3TD3.policy_aliases,
        "GraphPolicy": GraphPolicy,
    }

    def _setup_model(self) -> None:
        if self.replay_buffer_class is None and isinstance(self.observation_space, GraphSpace):
            self.replay_buffer_class = GraphReplayBuffer
        super()._setup_model()
