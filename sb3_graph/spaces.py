"""Backward-compatible home of :mod:`sb3_graph.common.spaces`.

Models saved before the move name ``sb3_graph.spaces.GraphSpace`` in their pickled observation
space (e.g. the repository's shipped pretrained planners): this module keeps them loading.
"""

from sb3_graph.common.spaces import (
    EDGE_ATTR,
    EDGE_INDEX,
    EDGE_MASK,
    EDGE_TYPE,
    GRAPH_KEYS,
    NODE_MASK,
    GraphSpace,
    X,
    edge_dims,
    graph_dims,
)

__all__ = [
    "EDGE_ATTR",
    "EDGE_INDEX",
    "EDGE_MASK",
    "EDGE_TYPE",
    "GRAPH_KEYS",
    "NODE_MASK",
    "X",
    "GraphSpace",
    "edge_dims",
    "graph_dims",
]
