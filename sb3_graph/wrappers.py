"""Environments that declare gymnasium's own ``spaces.Graph`` observations, made SB3-ready.

SB3 rejects ``spaces.Graph`` in its VecEnvs, buffers and preprocessing (SB3 issue #2121), before
any policy is built. :class:`GraphObservation` turns each ``GraphInstance`` into the fixed-size
arrays of a :class:`~sb3_graph.GraphSpace`, which every SB3 component accepts::

    from stable_baselines3.common.env_util import make_vec_env
    from sb3_graph import PPO
    from sb3_graph.wrappers import GraphObservation

    env = make_vec_env(MyGraphEnv, n_envs=4, wrapper_class=GraphObservation,
                       wrapper_kwargs=dict(max_nodes=16, max_edges=64))
    model = PPO("GraphPolicy", env)

Wrap the single environment (``wrapper_class``), not the VecEnv. The action space is left as it
is; the graph policies act on ``Box(low, high, (max_nodes,))``: action slot ``i`` belongs to the
``i``-th vertex of ``GraphInstance.nodes``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_graph.common.spaces import GraphSpace

EDGE_MODES = ("relations", "features")


class GraphObservation(gym.ObservationWrapper):
    """Turn ``spaces.Graph`` observations into :class:`~sb3_graph.GraphSpace` observations.

    How gymnasium's ``Graph(node_space, edge_space)`` maps to a ``GraphSpace``:

    - nodes: a ``Box`` node space gives ``prod(shape)`` vertex features (each node flattened), with
      the smallest ``low`` and largest ``high`` as bounds; a ``Discrete(k)`` node space gives a
      one-hot vector of ``k`` features;
    - edges: ``GraphInstance.edge_links[i] = (source, target)`` is edge ``i``, directed from source
      to target (messages flow that way; add both directions in the environment for an
      undirected graph). No edge space: one relation. A ``Discrete(k)`` edge space: ``k`` relations
      (relation ``edges[i] - start``), or, with ``discrete_edges="features"``, one relation and a
      one-hot edge feature vector. A ``Box`` edge space: one relation and ``prod(shape)`` edge
      features.

    :param env: an environment whose observation space is a ``gymnasium.spaces.Graph``
    :param max_nodes: the most vertices an observation may hold (the size of the padded arrays and
        of the policies' action vector)
    :param max_edges: the most edges an observation may hold
    :param discrete_edges: a ``Discrete`` edge space as ``"relations"`` (default) or one-hot ``"features"``
    :raises ValueError: on a space this wrapper cannot map, and at ``reset``/``step`` on an
        observation with more vertices or edges than the maxima
    """

    def __init__(self, env: gym.Env, max_nodes: int, max_edges: int, discrete_edges: str = "relations") -> None:
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, spaces.Graph):
            raise ValueError(f"GraphObservation: the observation space must be a gymnasium Graph, got {space}")
        if discrete_edges not in EDGE_MODES:
            raise ValueError(f"GraphObservation: discrete_edges must be one of {EDGE_MODES}, got {discrete_edges!r}")
        node_space, edge_space = space.node_space, space.edge_space
        if isinstance(node_space, spaces.Box):
            node_features = int(np.prod(node_space.shape))
            low, high = float(np.min(node_space.low)), float(np.max(node_space.high))
        elif isinstance(node_space, spaces.Discrete):
            node_features, low, high = int(node_space.n), 0.0, 1.0
        else:
            raise ValueError(f"GraphObservation: node_space must be a Box or Discrete, got {node_space}")
        num_relations, edge_features, edge_low, edge_high = 1, 0, -np.inf, np.inf
        if isinstance(edge_space, spaces.Discrete):
            if discrete_edges == "relations":
                num_relations = int(edge_space.n)
            else:
                edge_features, edge_low, edge_high = int(edge_space.n), 0.0, 1.0
        elif isinstance(edge_space, spaces.Box):
            edge_features = int(np.prod(edge_space.shape))
            edge_low, edge_high = float(np.min(edge_space.low)), float(np.max(edge_space.high))
        elif edge_space is not None:
            raise ValueError(f"GraphObservation: edge_space must be None, a Box or Discrete, got {edge_space}")
        self.discrete_edges = discrete_edges
        self.observation_space = GraphSpace(
            max_nodes,
            node_features,
            max_edges,
            num_relations,
            low=low if low < high else -np.inf,
            high=high if low < high else np.inf,
            edge_features=edge_features,
            edge_low=edge_low if edge_low < edge_high else -np.inf,
            edge_high=edge_high if edge_low < edge_high else np.inf,
        )

    def observation(self, observation: spaces.GraphInstance) -> dict[str, np.ndarray]:
        """
        :param observation: a ``GraphInstance`` of the wrapped environment
        :return: the padded observation of :attr:`observation_space`
        :raises ValueError: when the graph has more vertices or edges than the maxima
        """
        space: GraphSpace = self.observation_space  # type: ignore[assignment]
        graph_space: spaces.Graph = self.env.observation_space  # type: ignore[assignment]
        nodes = np.asarray(observation.nodes)
        n = nodes.shape[0]
        if n > space.max_nodes:
            raise ValueError(
                f"GraphObservation: the observation has {n} vertices, more than max_nodes={space.max_nodes}; "
                "raise max_nodes"
            )
        if isinstance(graph_space.node_space, spaces.Discrete):
            x = _one_hot(nodes.reshape(n) - graph_space.node_space.start, space.node_features)
        else:
            x = nodes.reshape(n, space.node_features)
        links = observation.edge_links
        links = np.zeros((0, 2), np.int64) if links is None else np.asarray(links).reshape(-1, 2)
        e = links.shape[0]
        if e > space.max_edges:
            raise ValueError(
                f"GraphObservation: the observation has {e} edges, more than max_edges={space.max_edges}; "
                "raise max_edges"
            )
        edge_type, edge_attr = None, None
        edges = observation.edges
        edge_space = graph_space.edge_space
        if isinstance(edge_space, spaces.Discrete):
            ids = np.asarray(edges).reshape(e) - edge_space.start
            if self.discrete_edges == "relations":
                edge_type = ids
            else:
                edge_attr = _one_hot(ids, space.edge_features)
        elif isinstance(edge_space, spaces.Box):
            edge_attr = np.asarray(edges, dtype=np.float32).reshape(e, space.edge_features)
        return space.encode(x, links.T, edge_type, edge_attr)


def _one_hot(ids: np.ndarray, size: int) -> np.ndarray:
    out = np.zeros((len(ids), size), dtype=np.float32)
    out[np.arange(len(ids)), ids.astype(np.int64)] = 1.0
    return out


def wrap_graph_env(env: gym.Env, **kwargs: Any) -> GraphObservation:
    """Functional form of :class:`GraphObservation` (``make_vec_env(..., wrapper_class=wrap_graph_env)``)."""
    return GraphObservation(env, **kwargs)
