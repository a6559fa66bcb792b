"""A gymnasium space for graphs with one row per vertex, padded to a fixed size.

SB3 rejects gymnasium's ``Graph`` space in its VecEnvs, buffers and preprocessing, so a graph
travels through gym and SB3 as a ``Dict`` of fixed-size arrays with explicit masks. Real vertices
and edges always occupy the leading slots (canonical layout): slot ``i < num_nodes`` is vertex
``i``, and the environment's action slot ``i`` belongs to the same vertex.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

# Keys of the padded observation dictionary.
X = "x"
NODE_MASK = "node_mask"
EDGE_INDEX = "edge_index"
EDGE_TYPE = "edge_type"
EDGE_MASK = "edge_mask"
EDGE_ATTR = "edge_attr"
#: Keys of every graph observation; ``edge_attr`` is added when the space has edge features.
GRAPH_KEYS = (X, NODE_MASK, EDGE_INDEX, EDGE_TYPE, EDGE_MASK)


class GraphSpace(spaces.Dict):
    """Directed multi-relational graphs with up to ``max_nodes`` vertices and ``max_edges`` edges.

    An observation is a dictionary of fixed-size arrays:

    - ``x``: ``(max_nodes, node_features)`` float32 vertex features, zero in padded rows,
    - ``node_mask``: ``(max_nodes,)`` int8, ``1`` for the first ``num_nodes`` slots,
    - ``edge_index``: ``(2, max_edges)`` int32, rows ``(source, target)``: messages flow from
      source to target,
    - ``edge_type``: ``(max_edges,)`` int32 relation id in ``[0, num_relations)``,
    - ``edge_mask``: ``(max_edges,)`` int8, ``1`` for the first ``num_edges`` slots,
    - ``edge_attr`` (only when ``edge_features > 0``): ``(max_edges, edge_features)`` float32 edge
      features, zero in padded rows.

    An isolated vertex is a real vertex, not padding: only the masks tell them apart.

    :param max_nodes: the most vertices one graph may hold
    :param node_features: number of features per vertex
    :param max_edges: the most edges one graph may hold
    :param num_relations: number of edge types
    :param low: lower bound of the vertex features (scalar)
    :param high: upper bound of the vertex features (scalar)
    :param seed: seed for :meth:`sample`
    :param edge_features: number of features per edge (0: no ``edge_attr`` entry)
    :param edge_low: lower bound of the edge features (scalar)
    :param edge_high: upper bound of the edge features (scalar)
    """

    # Class defaults: spaces pickled before edge features existed (e.g. in saved models) load as
    # spaces without them.
    edge_features = 0
    edge_low = -np.inf
    edge_high = np.inf

    def __init__(
        self,
        max_nodes: int,
        node_features: int,
        max_edges: int,
        num_relations: int = 1,
        low: float = -np.inf,
        high: float = np.inf,
        seed: int | None = None,
        edge_features: int = 0,
        edge_low: float = -np.inf,
        edge_high: float = np.inf,
    ) -> None:
        for name, value, minimum in (
            ("max_nodes", max_nodes, 1),
            ("node_features", node_features, 1),
            ("max_edges", max_edges, 0),
            ("num_relations", num_relations, 1),
            ("edge_features", edge_features, 0),
        ):
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
                raise ValueError(f"GraphSpace: {name} must be an integer >= {minimum}, got {value!r}")
        if max_nodes > np.iinfo(np.int32).max:
            raise ValueError(f"GraphSpace: max_nodes must be < 2**31, got {max_nodes}")
        if not low < high:
            raise ValueError(f"GraphSpace: low must be < high, got low={low}, high={high}")
        if not edge_low < edge_high:
            raise ValueError(f"GraphSpace: edge_low must be < edge_high, got {edge_low}, {edge_high}")
        self.max_nodes = int(max_nodes)
        self.node_features = int(node_features)
        self.max_edges = int(max_edges)
        self.num_relations = int(num_relations)
        self.low = float(low)
        self.high = float(high)
        self.edge_features = int(edge_features)
        self.edge_low = float(edge_low)
        self.edge_high = float(edge_high)
        # One slot at least, so that max_edges=0 still gives arrays SB3 can flatten.
        edge_slots = max(self.max_edges, 1)
        entries = {
            X: spaces.Box(self.low, self.high, (self.max_nodes, self.node_features), np.float32),
            NODE_MASK: spaces.Box(0, 1, (self.max_nodes,), np.int8),
            EDGE_INDEX: spaces.Box(0, self.max_nodes - 1, (2, edge_slots), np.int32),
            EDGE_TYPE: spaces.Box(0, self.num_relations - 1, (edge_slots,), np.int32),
            EDGE_MASK: spaces.Box(0, 1, (edge_slots,), np.int8),
        }
        if self.edge_features:
            entries[EDGE_ATTR] = spaces.Box(
                self.edge_low, self.edge_high, (edge_slots, self.edge_features), np.float32
            )
        super().__init__(entries, seed=seed)

    # ------------------------------------------------------------------ encode / decode
    def encode(
        self,
        x: np.ndarray,
        edge_index: np.ndarray | None = None,
        edge_type: np.ndarray | None = None,
        edge_attr: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Pad one graph into the fixed layout of this space.

        :param x: ``(num_nodes, node_features)`` vertex features
        :param edge_index: ``(2, num_edges)`` integer ``(source, target)`` rows; ``None`` for no edges
        :param edge_type: ``(num_edges,)`` relation ids; ``None`` means relation 0 everywhere
        :param edge_attr: ``(num_edges, edge_features)`` edge features; required when the space has
            edge features, refused when it has none
        :return: the padded observation
        :raises ValueError: on a shape, a count or an index outside what the space holds
        """
        x = np.asarray(x, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.node_features:
            raise ValueError(
                f"GraphSpace.encode: x must have shape (num_nodes, {self.node_features}), got {x.shape}"
            )
        n = x.shape[0]
        if n > self.max_nodes:
            raise ValueError(f"GraphSpace.encode: {n} vertices exceed max_nodes={self.max_nodes}")
        if edge_index is None:
            edge_index = np.zeros((2, 0), dtype=np.int64)
        edge_index = np.asarray(edge_index)
        if edge_index.ndim != 2 or edge_index.shape[0] != 2:
            raise ValueError(
                f"GraphSpace.encode: edge_index must have shape (2, num_edges), got {edge_index.shape}"
            )
        if edge_index.size and not np.issubdtype(edge_index.dtype, np.integer):
            raise ValueError(
                f"GraphSpace.encode: edge_index must hold integers, got dtype {edge_index.dtype}"
            )
        e = edge_index.shape[1]
        if e > self.max_edges:
            raise ValueError(f"GraphSpace.encode: {e} edges exceed max_edges={self.max_edges}")
        if e and (edge_index.min() < 0 or edge_index.max() >= n):
            raise ValueError(
                f"GraphSpace.encode: edge_index must point at real vertices in [0, {n}), "
                f"got values in [{edge_index.min()}, {edge_index.max()}]"
            )
        if edge_type is None:
            edge_type = np.zeros(e, dtype=np.int64)
        edge_type = np.asarray(edge_type)
        if edge_type.shape != (e,):
            raise ValueError(f"GraphSpace.encode: edge_type must have shape ({e},), got {edge_type.shape}")
        if e and (edge_type.min() < 0 or edge_type.max() >= self.num_relations):
            raise ValueError(
                f"GraphSpace.encode: edge_type must lie in [0, {self.num_relations}) (num_relations), "
                f"got values in [{edge_type.min()}, {edge_type.max()}]"
            )
        if self.edge_features:
            if edge_attr is None:
                raise ValueError(
                    f"GraphSpace.encode: edge_attr of shape ({e}, {self.edge_features}) is required "
                    f"(edge_features={self.edge_features})"
                )
            edge_attr = np.asarray(edge_attr, dtype=np.float32)
            if edge_attr.shape != (e, self.edge_features):
                raise ValueError(
                    f"GraphSpace.encode: edge_attr must have shape ({e}, {self.edge_features}), "
                    f"got {edge_attr.shape}"
                )
        elif edge_attr is not None:
            raise ValueError("GraphSpace.encode: edge_attr given, but the space has edge_features=0")
        obs = self._empty()
        if self.edge_features:
            obs[EDGE_ATTR][:e] = edge_attr
        obs[X][:n] = x
        obs[NODE_MASK][:n] = 1
        obs[EDGE_INDEX][:, :e] = edge_index
        obs[EDGE_TYPE][:e] = edge_type
        obs[EDGE_MASK][:e] = 1
        return obs

    def decode(self, obs: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """Exact inverse of :meth:`encode`: the real vertices and edges, padding dropped.

        :param obs: one padded observation of this space
        :return: ``x`` ``(n, F)`` float32, ``edge_index`` ``(2, e)`` int64, ``edge_type`` ``(e,)``
            int64, and, only when the space has edge features, ``edge_attr`` ``(e, edge_features)``
            float32 (the arguments of :meth:`encode`, in its order)
        """
        n = int(np.asarray(obs[NODE_MASK]).sum())
        e = int(np.asarray(obs[EDGE_MASK]).sum())
        x = np.asarray(obs[X], dtype=np.float32)[:n].copy()
        edge_index = np.asarray(obs[EDGE_INDEX])[:, :e].astype(np.int64)
        edge_type = np.asarray(obs[EDGE_TYPE])[:e].astype(np.int64)
        if not self.edge_features:
            return x, edge_index, edge_type
        return x, edge_index, edge_type, np.asarray(obs[EDGE_ATTR], dtype=np.float32)[:e].copy()

    def num_nodes(self, obs: dict[str, np.ndarray]) -> np.ndarray | int:
        """Number of real vertices of one observation (int) or of a batch (array)."""
        counts = np.asarray(obs[NODE_MASK]).sum(axis=-1)
        return int(counts) if np.ndim(counts) == 0 else counts.astype(np.int64)

    def _empty(self) -> dict[str, np.ndarray]:
        return {key: np.zeros(space.shape, dtype=space.dtype) for key, space in self.spaces.items()}

    # ------------------------------------------------------------------ gymnasium API
    def sample(self, mask: Any = None, probability: Any = None) -> dict[str, np.ndarray]:
        """A random valid graph: uniform vertex count, features in the bounds (standard normal where
        unbounded), random edges between distinct real vertices with random relations."""
        if mask is not None or probability is not None:
            raise ValueError("GraphSpace.sample does not support mask or probability")
        rng = self.np_random
        n = int(rng.integers(0, self.max_nodes + 1))
        if np.isfinite(self.low) and np.isfinite(self.high):
            x = rng.uniform(self.low, self.high, (n, self.node_features))
        else:
            x = np.clip(rng.standard_normal((n, self.node_features)), self.low, self.high)
        e = int(rng.integers(0, min(self.max_edges, n * (n - 1)) + 1)) if n > 1 else 0
        src = rng.integers(0, n, e) if e else np.zeros(0, np.int64)
        # Offsets in [1, n) keep source and target distinct.
        dst = (src + rng.integers(1, n, e)) % n if e else np.zeros(0, np.int64)
        edge_type = rng.integers(0, self.num_relations, e)
        edge_attr = None
        if self.edge_features:
            shape = (e, self.edge_features)
            if np.isfinite(self.edge_low) and np.isfinite(self.edge_high):
                edge_attr = rng.uniform(self.edge_low, self.edge_high, shape)
            else:
                edge_attr = np.clip(rng.standard_normal(shape), self.edge_low, self.edge_high)
        return self.encode(x, np.stack([src, dst]), edge_type, edge_attr)

    def contains(self, x: Any) -> bool:
        """True for a padded graph in canonical layout whose edges join real vertices."""
        if not isinstance(x, dict) or set(x) != set(self.spaces):
            return False
        if not super().contains(x):
            return False
        node_mask = np.asarray(x[NODE_MASK])
        edge_mask = np.asarray(x[EDGE_MASK])
        n, e = int(node_mask.sum()), int(edge_mask.sum())
        # Real slots first: a mask must be ones followed by zeros.
        if not (node_mask[:n].all() and edge_mask[:e].all()):
            return False
        edge_index = np.asarray(x[EDGE_INDEX])[:, :e]
        return bool(e == 0 or edge_index.max() < n)

    def __eq__(self, other: Any) -> bool:
        return isinstance(other, GraphSpace) and self._params() == other._params()

    def __hash__(self) -> int:
        return hash(self._params())

    def _params(self) -> tuple:
        return (
            self.max_nodes,
            self.node_features,
            self.max_edges,
            self.num_relations,
            self.low,
            self.high,
            self.edge_features,
            self.edge_low,
            self.edge_high,
        )

    def __repr__(self) -> str:
        edges = f", edge_features={self.edge_features}" if self.edge_features else ""
        return (
            f"GraphSpace(max_nodes={self.max_nodes}, node_features={self.node_features}, "
            f"max_edges={self.max_edges}, num_relations={self.num_relations}{edges})"
        )


def graph_dims(observation_space: spaces.Space, action_space: spaces.Space | None = None) -> tuple[int, int, int]:
    """``(max_nodes, node_features, num_relations)`` of a graph observation space, checked against
    the action space (one action per vertex slot) when one is given.

    :param observation_space: a :class:`GraphSpace` (or a ``Dict`` with its layout)
    :param action_space: ``Box`` of shape ``(max_nodes,)``, or ``None`` to skip that check
    :return: the dimensions
    :raises ValueError: when the spaces do not fit together
    """
    keys = set(getattr(observation_space, "spaces", {}) or {})
    if not isinstance(observation_space, spaces.Dict) or keys not in (set(GRAPH_KEYS), {*GRAPH_KEYS, EDGE_ATTR}):
        raise ValueError(
            f"sb3_graph: observation_space must be a GraphSpace (Dict with keys {GRAPH_KEYS}, and "
            f"{EDGE_ATTR!r} with edge features), got {observation_space}"
        )
    max_nodes, node_features = observation_space[X].shape
    num_relations = getattr(observation_space, "num_relations", None)
    if num_relations is None:
        num_relations = int(np.max(observation_space[EDGE_TYPE].high)) + 1
    if action_space is not None and (
        not isinstance(action_space, spaces.Box) or action_space.shape != (max_nodes,)
    ):
        raise ValueError(
            f"sb3_graph: action_space must be a Box of shape (max_nodes,) = ({max_nodes},), one action per "
            f"vertex slot, got {action_space}"
        )
    return int(max_nodes), int(node_features), int(num_relations)


def edge_dims(observation_space: spaces.Dict) -> int:
    """Number of edge features of a graph observation space (0 without ``edge_attr``)."""
    entry = observation_space.spaces.get(EDGE_ATTR)
    return 0 if entry is None else int(entry.shape[-1])
