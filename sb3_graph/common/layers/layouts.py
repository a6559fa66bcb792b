"""Kernel layouts of the relational convolution: the aggregation indices of a batch, derived once per
batch (and cached with :data:`sb3_graph.common.batching.derived_indices`) for
:func:`~sb3_graph.common.layers.relational_conv`: every relation row (:class:`RelationalLayout`),
only the rows that some edge reads (:class:`CompactLayout`) and per edge, with edge features
(:class:`EdgeLayout`)."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from sb3_graph.common.batching import derived_indices
from sb3_graph.common.layers.compiled import _kernels


class RelationalLayout(NamedTuple):
    """Aggregation indices of a batch for :func:`relational_conv` (derived once per batch).

    ``K`` stacked copies of the graph (e.g. twin critics) are laid out as ``K`` disjoint graphs.

    :param source: ``(E',)`` row ``(k * N + j) * stride + r`` of the transformed features read by
        each edge ``j -> i`` of relation ``r`` in copy ``k``
    :param target: ``(E',)`` segment ``(k * N + i) * R + r`` it is aggregated into
    :param target_vertex: ``(E',)`` vertex ``k * N + i`` of each target segment
    :param source_order: ``(E',)`` permutation that sorts ``source`` (gradients are accumulated
        in source order: ``index_add`` with a sorted index is ~2x faster on CPU); ``None`` on the
        compiled CPU path, whose kernels do not read it
    :param sorted_source: ``source[source_order]`` (``None`` with it)
    :param counts: ``(K * N * R,)`` edges per segment (mean only; else ``None``)
    :param num_nonempty: number of non-empty segments
    :param edge_order: ``(E,)`` the input edge of each of copy 0's edges, for a layout that keeps
        every edge (``per_edge``: a convolution with edge features, whose repeated edges carry
        their own messages) and sorts them by target; ``None``: the input order (forward-only) or
        repeated edges merged

    A forward-only layout (max aggregation without autograd, see :func:`relational_layout`)
    holds ``source`` and ``target`` only, every edge kept and unsorted; the other fields, which
    only the backward pass reads, are ``None``.
    """

    source: Tensor
    target: Tensor
    target_vertex: Tensor | None
    source_order: Tensor | None
    sorted_source: Tensor | None
    counts: Tensor | None
    num_nonempty: int | None
    edge_order: Tensor | None = None


def check_edges(edge_index: Tensor, edge_type: Tensor, num_nodes: int, num_relations: int) -> None:
    """Raise a ``ValueError`` when an edge names a vertex outside ``[0, num_nodes)`` or a relation
    outside ``[0, num_relations)`` (either would silently read another vertex's row). One host
    sync; layouts call it once per batch.

    :param edge_index: ``(2, E)`` long ``(source, target)`` rows
    :param edge_type: ``(E,)`` relation ids
    :param num_nodes: number of vertices ``N``
    :param num_relations: number of relations ``R``
    """
    if edge_index.size(1) == 0:
        return
    lo_v, hi_v, lo_r, hi_r = torch.stack(
        (edge_index.min(), edge_index.max(), edge_type.min().long(), edge_type.max().long())
    ).tolist()
    if lo_r < 0 or hi_r >= num_relations:
        raise ValueError(
            f"sb3_graph: edge_type holds relation ids in [{lo_r}, {hi_r}], outside [0, num_relations={num_relations})"
        )
    if lo_v < 0 or hi_v >= num_nodes:
        raise ValueError(f"sb3_graph: edge_index holds vertex ids in [{lo_v}, {hi_v}], outside [0, {num_nodes})")


def _base_layout(
    edge_index: Tensor,
    edge_type: Tensor,
    num_nodes: int,
    num_relations: int,
    stride: int,
    aggr: str,
    per_edge: bool = False,
) -> RelationalLayout:
    check_edges(edge_index, edge_type, num_nodes, num_relations)
    edge_type = edge_type.long()
    source = edge_index[0] * stride + edge_type
    target = edge_index[1] * num_relations + edge_type
    counts, edge_order = None, None
    kernels = _kernels(edge_index.device) if aggr == "max" else None
    if kernels is not None:
        # A counting sort over the bounded segment ids (the PyTorch formulation below sorts
        # 64-bit keys: about a tenth of a training step at intersection sizes). Same order.
        order, num_nonempty = kernels.segment_order(
            target.numpy(), source.numpy(), num_nodes * num_relations, not per_edge
        )
        order = torch.from_numpy(order)
        source, target = source[order], target[order]
        edge_order = order if per_edge else None
        # The compiled kernels read neither the source order nor the counts.
        return RelationalLayout(source, target, target // num_relations, None, None, None, num_nonempty, edge_order)
    if per_edge:  # every edge is its own message: sorted by target, none merged
        edge_order = torch.argsort(target, stable=True)
        source, target = source[edge_order], target[edge_order]
        num_nonempty = int(torch.count_nonzero(target[1:] != target[:-1])) + 1 if len(target) else 0
    elif aggr == "max":
        # A repeated edge repeats a message and cannot change a maximum (its gradient is split
        # among the copies, which all read the same row): keep one. Sorting also groups targets.
        rows = num_nodes * stride
        key = torch.unique(target * rows + source)
        target, source = key // rows, key % rows
        num_nonempty = int(torch.count_nonzero(target[1:] != target[:-1])) + 1 if len(key) else 0
    else:
        counts = torch.bincount(target, minlength=num_nodes * num_relations)
        num_nonempty = int(torch.count_nonzero(counts))
    source_order = torch.argsort(source)
    return RelationalLayout(
        source, target, target // num_relations, source_order, source[source_order], counts, num_nonempty, edge_order
    )


def _forward_layout(
    edge_index: Tensor, edge_type: Tensor, num_nodes: int, num_relations: int, stride: int
) -> RelationalLayout:
    check_edges(edge_index, edge_type, num_nodes, num_relations)
    edge_type = edge_type.long()
    source = edge_index[0] * stride + edge_type
    target = edge_index[1] * num_relations + edge_type
    return RelationalLayout(source, target, None, None, None, None, None)


def relational_layout(
    edge_index: Tensor,
    edge_type: Tensor,
    num_nodes: int,
    num_relations: int,
    stride: int,
    aggr: str = "max",
    copies: int = 1,
    per_edge: bool = False,
) -> RelationalLayout:
    """Aggregation indices of :func:`relational_conv`, cached per batch (see
    :class:`~sb3_graph.common.batching.DerivedIndexCache`).

    :param edge_index: ``(2, E)`` long ``(source, target)`` rows
    :param edge_type: ``(E,)`` relation ids
    :param num_nodes: number of vertices ``N``
    :param num_relations: number of relations ``R``
    :param stride: rows of transformed features per vertex (``R``, or ``R + 1`` with the root term)
    :param aggr: ``max``, ``mean`` or ``sum``
    :param copies: number ``K`` of stacked networks
    :param per_edge: max aggregation of per-edge messages (edge features): keep every edge (see
        :attr:`RelationalLayout.edge_order`)
    :return: the layout; forward-only (see :class:`RelationalLayout`) for the maximum without
        autograd: a repeated edge cannot change a maximum and the order of the edges does not
        matter to it, so the deduplication, sorting and counting that the backward pass needs
        (half of a small batch's layer time at inference) are skipped. It is cached apart from
        the full layout of the same batch.
    """
    forward_only = aggr == "max" and not torch.is_grad_enabled()
    compiled = _kernels(edge_index.device) is not None  # a layout of its own (no source order)
    extra = (num_nodes, num_relations, stride, aggr, forward_only, per_edge, compiled)

    def base() -> RelationalLayout:
        if forward_only:
            return _forward_layout(edge_index, edge_type, num_nodes, num_relations, stride)
        return _base_layout(edge_index, edge_type, num_nodes, num_relations, stride, aggr, per_edge)

    layout = derived_indices.get((edge_index, edge_type), ("relational", *extra, 1), base)
    if copies == 1:
        return layout

    def stacked() -> RelationalLayout:
        k = torch.arange(copies, device=edge_index.device).unsqueeze(-1)
        source = (layout.source + k * (num_nodes * stride)).view(-1)
        target = (layout.target + k * (num_nodes * num_relations)).view(-1)
        if forward_only:
            return RelationalLayout(source, target, None, None, None, None, None)
        assert layout.target_vertex is not None and layout.num_nonempty is not None
        source_order, sorted_source = layout.source_order, layout.sorted_source
        if source_order is not None and sorted_source is not None:
            source_order = (source_order + k * len(layout.source)).view(-1)
            sorted_source = (sorted_source + k * (num_nodes * stride)).view(-1)
        return RelationalLayout(
            source=source,
            target=target,
            target_vertex=(layout.target_vertex + k * num_nodes).view(-1),
            source_order=source_order,
            sorted_source=sorted_source,
            counts=None if layout.counts is None else layout.counts.repeat(copies),
            num_nonempty=layout.num_nonempty * copies,
            edge_order=layout.edge_order,
        )

    return derived_indices.get((edge_index, edge_type), ("relational", *extra, copies), stacked)


class CompactLayout(NamedTuple):
    """Which relation rows of :func:`relational_conv` some edge reads, and where (derived once per
    batch from a :class:`RelationalLayout`, for the compiled max path).

    A vertex's relation-``r`` row ``W_r x_j`` is read only if the vertex sends along an edge of
    relation ``r`` (about 69 % of the vertices per relation on intersection graphs), so only those
    rows are computed: per relation ``r`` the block ``x[senders_r] W_r``. With ``K`` stacked copies
    the blocks are laid out relation by relation, each ``(K, n_r, out)``, so that every block is
    one contiguous batched matmul: copy ``k``'s row ``c`` of relation ``r`` is row
    ``K * offsets[r] + k * n_r + c``.

    :param senders: ``(S,)`` per relation the sorted vertices that send along it, concatenated
    :param offsets: ``R + 1`` block boundaries in ``senders`` (relation ``r``: ``offsets[r]:offsets[r + 1]``)
    :param source: ``(E',)`` compact row read by each edge of the base layout (all ``K`` copies)
    :param base: the layout of the ``K`` copies whose ``target`` (and backward fields) the compact
        rows are aggregated with
    :param rows: ``(K * S,)`` the vertex ``k * N + j`` of every compact row (the rows of ``x`` viewed
        as ``(K * N, in)`` that the blocks read, and that their gradients return to)
    :param terms: ``(E', 2)`` with edge features (``per_edge``): each edge's row of the features
        (in the layout's edge order) and of the edge weights ``(K * R, D, out)`` (``k * R + r``);
        else ``None``
    """

    senders: Tensor
    offsets: tuple[int, ...]
    source: Tensor
    base: RelationalLayout
    rows: Tensor
    terms: Tensor | None = None


def compact_layout(
    edge_index: Tensor,
    edge_type: Tensor,
    num_nodes: int,
    num_relations: int,
    stride: int,
    copies: int = 1,
    per_edge: bool = False,
) -> CompactLayout:
    """The :class:`CompactLayout` of a batch for max aggregation, cached per batch like
    :func:`relational_layout` (with or without autograd: it remaps that layout's edges).

    :param edge_index: ``(2, E)`` long ``(source, target)`` rows
    :param edge_type: ``(E,)`` relation ids
    :param num_nodes: number of vertices ``N``
    :param num_relations: number of relations ``R``
    :param stride: ``R``, or ``R + 1`` with the root term (the base layout's row numbering)
    :param copies: number ``K`` of stacked networks
    :param per_edge: every edge kept (edge features, see :func:`relational_layout`)
    :return: the compact layout
    """
    forward_only = not torch.is_grad_enabled()

    def compute() -> CompactLayout:
        base, single = (
            relational_layout(edge_index, edge_type, num_nodes, num_relations, stride, "max", k, per_edge)
            for k in (copies, 1)
        )
        vertex, relation = single.source // stride, single.source % stride
        # The (relation, vertex) pairs that some edge reads, in order, and each edge's rank among
        # them: its compact row for one copy (torch.unique with return_inverse, without a sort).
        keys = relation * num_nodes + vertex
        present = torch.zeros(num_relations * num_nodes, dtype=torch.bool, device=keys.device)
        present[keys] = True
        key = torch.nonzero(present).view(-1)
        row = (torch.cumsum(present, 0) - 1)[keys]
        sizes = torch.bincount(key // num_nodes, minlength=num_relations)
        starts = torch.cumsum(sizes, 0) - sizes
        offsets = (0, *torch.cumsum(sizes, 0).tolist())
        senders = key % num_nodes
        rows = senders
        if copies > 1:  # copy k: K * offsets[r] + k * n_r + (row - offsets[r])
            k = torch.arange(copies, device=row.device).unsqueeze(-1)
            row = (row + (copies - 1) * starts[relation] + k * sizes[relation]).view(-1)
            blocks = [senders[lo:hi] + k * num_nodes for lo, hi in zip(offsets[:-1], offsets[1:], strict=True)]
            rows = torch.cat([b.view(-1) for b in blocks])
        terms = None
        if per_edge:  # copy k repeats copy 0's edges (and features) after them
            edge = torch.arange(len(single.target), device=row.device).repeat(copies)
            copy, relation = base.target // (num_nodes * num_relations), base.target % num_relations
            terms = torch.stack((edge, copy * num_relations + relation), dim=1)
        return CompactLayout(senders, offsets, row, base, rows, terms)

    extra = ("compact", num_nodes, num_relations, stride, forward_only, copies, per_edge)
    return derived_indices.get((edge_index, edge_type), extra, compute)


class EdgeLayout(NamedTuple):
    """Per-edge aggregation indices of a convolution with edge features (derived once per batch).

    :param source: ``(E,)`` row ``j * R + r`` of the relation transforms read by edge ``j -> i``
    :param segment: ``(E,)`` segment ``i * R + r`` it is reduced into
    :param counts: ``(N * R,)`` edges per segment
    :param num_nonempty: number of non-empty segments
    """

    source: Tensor
    segment: Tensor
    counts: Tensor
    num_nonempty: int


def edge_layout(edge_index: Tensor, edge_type: Tensor, num_nodes: int, num_relations: int) -> EdgeLayout:
    """Indices of :func:`_edge_conv`, cached per batch like :func:`relational_layout`."""

    def compute() -> EdgeLayout:
        check_edges(edge_index, edge_type, num_nodes, num_relations)
        edge_type_long = edge_type.long()
        segment = edge_index[1] * num_relations + edge_type_long
        counts = torch.bincount(segment, minlength=num_nodes * num_relations)
        return EdgeLayout(
            edge_index[0] * num_relations + edge_type_long, segment, counts, int(torch.count_nonzero(counts))
        )

    return derived_indices.get((edge_index, edge_type), ("edges", num_nodes, num_relations), compute)
