"""Small, fast graph environments for tests, examples and tuning smoke runs (like SB3's IdentityEnv).

Importing this module registers ``MaxNeighbourEnv`` with gymnasium as ``GraphMaxNeighbour-v0``
(for rl-zoo3: ``--gym-packages sb3_graph.toy_envs --env GraphMaxNeighbour-v0``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from sb3_graph.common.spaces import GraphSpace


class MaxNeighbourEnv(gym.Env):
    """Each vertex must output the largest first feature among its in-neighbours of relation 0.

    Every step shows a fresh random graph: ``n`` vertices (uniform in ``[min_nodes, max_nodes]``)
    with features uniform in ``[-1, 1]`` and random directed edges of ``num_relations`` types.
    Vertex ``i``'s target is ``max_{j -> i, type 0} x_j[0]`` (0 when it has no such in-neighbour);
    edges of other relations and the other features are distractors, so a policy has to respect
    edge direction and type. The reward of action ``a`` is ``-mean_i |a_i - target_i|`` over the real
    vertices (0 for an empty graph); padded action slots are ignored. A uniformly random policy
    scores about -0.6 per step, a perfect one 0. Episodes are truncated after ``episode_length``
    steps (no terminal states), so the task is a contextual bandit with graph context.

    :param max_nodes: most vertices per graph (size of the action vector)
    :param min_nodes: fewest vertices per graph (0 allows empty graphs)
    :param edges_per_node: mean number of edges per vertex
    :param num_relations: edge types (relation 0 carries the signal), at least 1
    :param node_features: features per vertex, at least 1 (feature 0 carries the signal)
    :param episode_length: steps per episode
    :param render_mode: ``None`` or ``"rgb_array"`` (SB3's ``make_vec_env`` asks for the latter)
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        max_nodes: int = 8,
        min_nodes: int = 1,
        edges_per_node: float = 1.5,
        num_relations: int = 2,
        node_features: int = 3,
        episode_length: int = 8,
        render_mode: str | None = None,
    ) -> None:
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(
                f"MaxNeighbourEnv: render_mode must be one of {[None, *self.metadata['render_modes']]}, "
                f"got {render_mode!r}"
            )
        self.render_mode = render_mode
        if not 0 <= min_nodes <= max_nodes:
            raise ValueError(
                f"MaxNeighbourEnv: min_nodes must lie in [0, max_nodes={max_nodes}], got {min_nodes}"
            )
        if edges_per_node < 0:
            raise ValueError(f"MaxNeighbourEnv: edges_per_node must be >= 0, got {edges_per_node}")
        if episode_length < 1:
            raise ValueError(f"MaxNeighbourEnv: episode_length must be >= 1, got {episode_length}")
        self.min_nodes = min_nodes
        self.edges_per_node = edges_per_node
        self.episode_length = episode_length
        max_edges = int(np.ceil(edges_per_node * max_nodes * 2)) + 1
        self.observation_space = GraphSpace(
            max_nodes, node_features, max_edges, num_relations, low=-1.0, high=1.0
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (max_nodes,), np.float32)
        self._target = np.zeros(0, np.float32)
        self._obs: dict[str, np.ndarray] = {}
        self._steps = 0

    def _new_graph(self) -> dict[str, np.ndarray]:
        space = self.observation_space
        rng = self.np_random
        n = int(rng.integers(self.min_nodes, space.max_nodes + 1))
        x = rng.uniform(-1.0, 1.0, (n, space.node_features)).astype(np.float32)
        e = min(int(rng.poisson(self.edges_per_node * n)), space.max_edges) if n > 1 else 0
        src = rng.integers(0, n, e)
        dst = (src + rng.integers(1, max(n, 2), e)) % max(n, 1)  # no self-loops
        edge_type = rng.integers(0, space.num_relations, e)
        signal = edge_type == 0
        target = np.full(n, -np.inf, dtype=np.float32)
        np.maximum.at(target, dst[signal], x[src[signal], 0])
        self._target = np.where(np.isfinite(target), target, 0.0).astype(np.float32)
        return space.encode(x, np.stack([src, dst]), edge_type)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self._steps = 0
        self._obs = self._new_graph()
        return self._obs, {}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        n = len(self._target)
        error = np.abs(np.clip(np.asarray(action, dtype=np.float32)[:n], -1, 1) - self._target)
        reward = -float(error.mean()) if n else 0.0
        info = {"target": self._target}
        self._steps += 1
        self._obs = self._new_graph()
        return self._obs, reward, False, self._steps >= self.episode_length, info

    def render(self) -> np.ndarray | None:
        """One 8-pixel row per vertex slot: its first feature (left half) and its target (right half)
        as grey levels from -1 (black) to 1 (white); padded slots are red."""
        if self.render_mode != "rgb_array":
            return None
        slots = self.observation_space.max_nodes
        n = len(self._target)
        grey = np.zeros((slots, 2), np.float32)
        if n:
            grey[:n, 0] = self._obs["x"][:n, 0]
            grey[:n, 1] = self._target
        image = np.repeat(((grey + 1.0) * 127.5).astype(np.uint8)[..., None], 3, axis=2)
        image[n:] = (255, 0, 0)
        return np.repeat(np.repeat(image, 8, axis=0), 32, axis=1)


def max_neighbour_expert(obs: dict[str, np.ndarray]) -> np.ndarray:
    """The exact answer of :class:`MaxNeighbourEnv` for a batch of observations (an expert for
    :func:`sb3_graph.behaviour_clone`): each real vertex's largest first feature among its
    in-neighbours of relation 0, 0 without one; 0 in padded slots.

    :param obs: a VecEnv's batched observation dictionary (leading dimension ``n_envs``)
    :return: ``(n_envs, max_nodes)`` float32 actions
    """
    x = np.asarray(obs["x"], dtype=np.float32)
    n_envs, max_nodes = x.shape[:2]
    edge_index = np.asarray(obs["edge_index"]).astype(np.int64)
    signal = np.asarray(obs["edge_mask"]).astype(bool) & (np.asarray(obs["edge_type"]) == 0)
    graph = np.broadcast_to(np.arange(n_envs)[:, None], signal.shape)[signal]
    src, dst = edge_index[:, 0][signal], edge_index[:, 1][signal]
    target = np.full(n_envs * max_nodes, -np.inf, dtype=np.float32)
    np.maximum.at(target, graph * max_nodes + dst, x[graph, src, 0])
    target = np.where(np.isfinite(target), target, 0.0).reshape(n_envs, max_nodes)
    return (target * np.asarray(obs["node_mask"]).reshape(n_envs, max_nodes)).astype(np.float32)


def make_expert(spec: str, env: Any) -> Any:
    """The toy task's experts by name, for ``sb3-graph train --pretrain-from``: ``"exact"``
    (:func:`max_neighbour_expert`).

    :param spec: the expert's name
    :param env: the VecEnv (unused: the exact answer reads the observation only)
    :raises ValueError: another name
    """
    if spec != "exact":
        raise ValueError(f"--pretrain-from: the toy task's expert is 'exact', got {spec!r}")
    return max_neighbour_expert


MAX_NEIGHBOUR_ID = "GraphMaxNeighbour-v0"
if MAX_NEIGHBOUR_ID not in gym.registry:
    gym.register(MAX_NEIGHBOUR_ID, entry_point="sb3_graph.toy_envs:MaxNeighbourEnv")
