"""Ragged batches of graphs: the padded gym/SB3 layout becomes one disjoint graph by index arithmetic.

Padding exists only at the gym/SB3 boundary. Inside the networks and the replay buffer, a batch of
``B`` graphs is one big disjoint graph (:class:`GraphBatch`), the layout PyTorch Geometric uses:
compute grows with the vertices really present, not with ``max_nodes``.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import torch
from torch import Tensor

from sb3_graph.common.spaces import EDGE_ATTR, EDGE_INDEX, EDGE_MASK, EDGE_TYPE, NODE_MASK, X


class GraphBatch(NamedTuple):
    """``num_graphs`` graphs as one disjoint graph.

    ``torch.cat([a, b])`` of two batches is their disjoint union (graphs of ``a``, then those of
    ``b``), so SB3 code that concatenates observation batches (e.g. CrossQ's joint forward pass of
    observations and next observations) works on graph batches unchanged.

    :param x: ``(N, F)`` float vertex features of all graphs, graph after graph
    :param edge_index: ``(2, E)`` long ``(source, target)`` rows indexing into ``x``
    :param edge_type: ``(E,)`` long relation ids
    :param batch: ``(N,)`` long id of each vertex's graph in ``[0, num_graphs)``
    :param node_slot: ``(N,)`` long slot of each vertex in its padded graph (= its action slot)
    :param num_graphs: number of graphs ``B`` (graphs may be empty)
    :param max_nodes: size of the padded layout, the action dimension
    :param edge_attr: ``(E, D)`` float edge features, or ``None`` for a space without them
    """

    x: Tensor
    edge_index: Tensor
    edge_type: Tensor
    batch: Tensor
    node_slot: Tensor
    num_graphs: int
    max_nodes: int
    edge_attr: Tensor | None = None

    @property
    def num_nodes(self) -> int:
        return self.x.size(0)

    @property
    def num_edges(self) -> int:
        return self.edge_index.size(1)

    def to(self, device: torch.device | str) -> GraphBatch:
        """The same batch with every tensor on ``device``."""
        return self._replace(
            x=self.x.to(device),
            edge_index=self.edge_index.to(device),
            edge_type=self.edge_type.to(device),
            batch=self.batch.to(device),
            node_slot=self.node_slot.to(device),
            edge_attr=None if self.edge_attr is None else self.edge_attr.to(device),
        )

    @classmethod
    def __torch_function__(cls, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        # Only torch.cat along dim 0 is defined for graph batches: their disjoint union.
        kwargs = kwargs or {}
        if func is torch.cat:
            tensors = args[0] if args else kwargs.get("tensors")
            dim = args[1] if len(args) > 1 else kwargs.get("dim", 0)
            if dim == 0 and tensors and all(isinstance(t, GraphBatch) for t in tensors):
                return concat_graph_batches(list(tensors))
        return NotImplemented


def concat_graph_batches(batches: list[GraphBatch]) -> GraphBatch:
    """Disjoint union of graph batches: the graphs of ``batches[0]``, then those of ``batches[1]``...

    :param batches: batches with the same ``max_nodes`` and all with or all without edge features
    :return: one batch of ``sum(b.num_graphs)`` graphs
    """
    if len({b.max_nodes for b in batches}) != 1:
        raise ValueError(f"concat_graph_batches: max_nodes differ: {[b.max_nodes for b in batches]}")
    with_attr = [b.edge_attr is not None for b in batches]
    if any(with_attr) and not all(with_attr):
        raise ValueError("concat_graph_batches: some batches have edge features and some do not")
    node_offset, graph_offset = 0, 0
    edge_index, batch = [], []
    for b in batches:
        edge_index.append(b.edge_index + node_offset)
        batch.append(b.batch + graph_offset)
        node_offset += b.num_nodes
        graph_offset += b.num_graphs
    return GraphBatch(
        x=torch.cat([b.x for b in batches]),
        edge_index=torch.cat(edge_index, dim=1),
        edge_type=torch.cat([b.edge_type for b in batches]),
        batch=torch.cat(batch),
        node_slot=torch.cat([b.node_slot for b in batches]),
        num_graphs=graph_offset,
        max_nodes=batches[0].max_nodes,
        edge_attr=torch.cat([b.edge_attr for b in batches]) if all(with_attr) else None,
    )


def padded_to_batch(obs: Mapping[str, Tensor]) -> GraphBatch:
    """Convert a padded batch of observations of a :class:`~sb3_graph.GraphSpace` to a
    :class:`GraphBatch` with the masks' nonzero entries and a vertex-id lookup table: no loop over
    samples.

    SB3's preprocessing casts every entry to float; index entries are cast back to long here.
    An unbatched observation (no leading batch dimension) is treated as a batch of one.

    :param obs: dictionary with ``x`` ``(B, M, F)``, ``node_mask`` ``(B, M)``, ``edge_index``
        ``(B, 2, E)``, ``edge_type`` ``(B, E)``, ``edge_mask`` ``(B, E)`` and, with edge features,
        ``edge_attr`` ``(B, E, D)``
    :return: the ragged batch
    :raises ValueError: when a mask holds values other than 0 and 1, or a real edge points at a
        padded slot, outside the graph or has a negative relation id (it would otherwise be wired
        silently into another vertex or graph)
    """
    x = obs[X]
    if x.dim() == 2:
        obs = {key: value.unsqueeze(0) for key, value in obs.items()}
        x = obs[X]
    num_graphs, max_nodes = x.shape[:2]
    node_mask, edge_mask = obs[NODE_MASK], obs[EDGE_MASK]
    _check_masks(node_mask, edge_mask)
    # Only the real entries are touched after the masks: (graph, slot) pairs of vertices and edges.
    node_graph, node_slot = node_mask.nonzero(as_tuple=True)
    edge_graph, edge_slot = edge_mask.nonzero(as_tuple=True)
    # Global id of each real vertex; edges read their endpoints' ids from it.
    global_id = torch.zeros((num_graphs, max_nodes), dtype=torch.long, device=x.device)
    global_id[node_graph, node_slot] = torch.arange(len(node_graph), device=x.device)
    edge_index = obs[EDGE_INDEX]
    src_slot = edge_index[edge_graph, 0, edge_slot].long()
    dst_slot = edge_index[edge_graph, 1, edge_slot].long()
    edge_type = obs[EDGE_TYPE][edge_graph, edge_slot].long()
    _check_edges(node_mask, edge_graph, src_slot, dst_slot, edge_type)
    edge_attr = obs.get(EDGE_ATTR)
    return GraphBatch(
        x=x[node_graph, node_slot].float(),
        edge_index=torch.stack((global_id[edge_graph, src_slot], global_id[edge_graph, dst_slot])),
        edge_type=edge_type,
        batch=node_graph,
        node_slot=node_slot,
        num_graphs=int(num_graphs),
        max_nodes=int(max_nodes),
        edge_attr=None if edge_attr is None else edge_attr[edge_graph, edge_slot].float(),
    )


def _check_masks(node_mask: Tensor, edge_mask: Tensor) -> None:
    for name, mask in ((NODE_MASK, node_mask), (EDGE_MASK, edge_mask)):
        if bool(((mask != 0) & (mask != 1)).any()):
            raise ValueError(
                f"sb3_graph: {name} holds values other than 0 and 1; was the graph observation normalized "
                "(VecNormalize(norm_obs=True) cannot be used with a GraphSpace)?"
            )


def _check_edges(node_mask: Tensor, graph: Tensor, src: Tensor, dst: Tensor, edge_type: Tensor) -> None:
    """Every real edge joins two real vertices of its own graph and has a relation id >= 0."""
    if not len(graph):
        return
    max_nodes = node_mask.size(1)
    outside = (src < 0) | (src >= max_nodes) | (dst < 0) | (dst >= max_nodes)
    if bool(outside.any()):
        raise ValueError(
            f"sb3_graph: edge_index holds slots outside [0, max_nodes={max_nodes}) in real edges"
        )
    padded = (node_mask[graph, src] == 0) | (node_mask[graph, dst] == 0)
    if bool(padded.any()):
        k = int(padded.nonzero()[0, 0])
        raise ValueError(
            f"sb3_graph: a real edge points at a padded vertex slot (graph {int(graph[k])}: "
            f"{int(src[k])} -> {int(dst[k])}); edges must join real vertices (node_mask 1)"
        )
    if bool((edge_type < 0).any()):
        raise ValueError("sb3_graph: edge_type holds negative relation ids in real edges")


def as_graph_batch(obs: GraphBatch | Mapping[str, Tensor]) -> GraphBatch:
    """Accept a :class:`GraphBatch` (from :class:`~sb3_graph.GraphReplayBuffer`) or a padded
    dictionary of tensors (from SB3's ``predict`` or ``DictReplayBuffer``).

    A padded batch is converted once while its tensors live unchanged (see
    :class:`DerivedIndexCache`).

    :param obs: the observation batch
    :return: the ragged batch
    """
    if isinstance(obs, GraphBatch):
        return obs
    if isinstance(obs, Mapping):
        # TD3 feeds the same padded batch to several networks: convert it once (and so also share
        # the layers' derived indices, which are cached per GraphBatch tensors).
        keys = (X, NODE_MASK, EDGE_INDEX, EDGE_TYPE, EDGE_MASK) + ((EDGE_ATTR,) if EDGE_ATTR in obs else ())
        tensors = tuple(obs[key] for key in keys)
        return derived_indices.get(tensors, ("padded_to_batch",), lambda: padded_to_batch(obs))
    raise TypeError(f"expected a GraphBatch or a dict of padded tensors, got {type(obs).__name__}")


def batch_to_padded(values: Tensor, graphs: GraphBatch, fill_value: float = 0.0) -> Tensor:
    """Scatter per-vertex values back into the padded layout (differentiable).

    :param values: ``(N,)`` or ``(N, K)`` per-vertex values
    :param graphs: the batch the vertices belong to
    :param fill_value: value of padded slots
    :return: ``(B, max_nodes)`` or ``(B, max_nodes, K)``
    """
    out = values.new_full((graphs.num_graphs, graphs.max_nodes, *values.shape[1:]), fill_value)
    return out.index_put((graphs.batch, graphs.node_slot), values)


def gather_vertex_values(padded: Tensor, graphs: GraphBatch) -> Tensor:
    """Read one value per real vertex from a padded ``(B, max_nodes, ...)`` tensor; padded slots
    are never read.

    :param padded: ``(B, max_nodes)`` or ``(B, max_nodes, K)`` values, e.g. actions
    :param graphs: the batch
    :return: ``(N,)`` or ``(N, K)`` values of the real vertices
    """
    return padded[graphs.batch, graphs.node_slot]


class DerivedIndexCache:
    """Small LRU cache of index tensors derived from a batch's index tensors (e.g. a layer's
    aggregation layout), keyed by the identity and version of the tensors they derive from.

    One TD3 gradient step feeds the same sampled batch to several networks (critic, actor,
    ``q1_forward``; target actor and target critics): each derived index is then computed once
    per batch instead of once per forward. An entry holds references to its source tensors, so
    their ids cannot be reused while it lives, and their version counters invalidate it after an
    in-place change. Inference-mode tensors (no version counter) are never cached.

    :param size: number of entries kept (least recently used first out)
    """

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self._entries: OrderedDict[tuple, tuple[tuple[Tensor, ...], Any]] = OrderedDict()

    def get(self, sources: tuple[Tensor, ...], extra: tuple, compute: Callable[[], Any]) -> Any:
        """The value derived from ``sources`` (and the hashable ``extra``), computed on a miss.

        :param sources: the tensors the value is derived from
        :param extra: other hashable inputs of ``compute``
        :param compute: computes the value
        :return: the cached or new value
        """
        if any(t.is_inference() for t in sources):
            return compute()
        key = (tuple((id(t), t._version) for t in sources), extra)
        entry = self._entries.get(key)
        if entry is not None and all(a is b for a, b in zip(entry[0], sources)):
            self._entries.move_to_end(key)
            return entry[1]
        value = compute()
        self._entries[key] = (sources, value)
        self._entries.move_to_end(key)
        while len(self._entries) > self.size:
            self._entries.popitem(last=False)
        return value

    def clear(self) -> None:
        """Drop every entry."""
        self._entries.clear()


#: Process-wide cache used by the graph layers and policies.
derived_indices = DerivedIndexCache()
