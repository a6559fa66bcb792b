"""Graph layers of the relational policy networks."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn
from torch_geometric.nn import MessagePassing

from sb3_graph.batching import derived_indices

AGGREGATIONS = ("max", "mean", "sum")


def _max_gradient(messages: Tensor, maxima: Tensor, target: Tensor, grad: Tensor, num_nonempty: int) -> Tensor:
    """Gradient of ``maxima = segment-max(messages, target)`` w.r.t. ``messages`` given ``grad``
    already gathered per message (``grad_out[target]``, modified in place): PyTorch's rule,
    the gradient split evenly among tied maxima."""
    # A float-valued mask: comparisons into bool tensors and bool->float casts are several
    # times slower than float arithmetic on CPU.
    is_max = torch.eq(messages, maxima.index_select(0, target), out=torch.empty_like(messages))
    grad.mul_(is_max)
    # Each non-empty (segment, channel) has one maximum unless tied or NaN (no row equals a NaN
    # maximum, so a tie elsewhere in the batch could make up the count): else split the gradient.
    # A NaN anywhere makes the sum NaN (20x cheaper than isnan().any(); inf - inf only costs the
    # split's extra work).
    if int(is_max.sum()) != num_nonempty * messages.size(1) or bool(maxima.sum().isnan()):
        winners = torch.zeros_like(maxima).index_add_(0, target, is_max)
        grad.div_(winners.index_select(0, target).clamp_(min=1))
    return grad


class SegmentMax(torch.autograd.Function):
    r"""``out[s] = max_{e : target[e] = s} values[source[e]]`` per channel, 0 for an empty segment.

    The same function and gradient as PyG's ``scatter(values[source], target, reduce="max")``
    (``torch.scatter_reduce(..., "amax", include_self=False)``), including the even split of the
    gradient among tied maxima, with a cheaper backward: one equality mask, one gather of the
    output gradient and one ``index_add``; the tie count is computed only when a tie exists.

    Inputs of :meth:`forward`: ``values`` ``(V, C)``, ``source`` ``(E,)`` long rows of ``values``
    (``None``: ``values`` are the messages themselves, ``E = V``), ``target`` ``(E,)`` long
    segment ids, ``num_segments`` ``S`` and ``num_nonempty``, the number of distinct targets.
    Output: ``(S, C)``.

    Without ``source`` (critic max pooling, a convolution with edge features), CPU tensors run in
    the compiled kernels of :class:`_RelationalMax` (one relation, no root term, no bias): the same
    maxima and, since each row is read once, the same gradients to the bit.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, values: Tensor, source: Tensor | None, target: Tensor, num_segments: int, num_nonempty: int
    ) -> Tensor:
        ctx.compiled = source is None and _COMPILED["segment_max"] and _compiled_path(values)
        if ctx.compiled:
            return _compiled_segment_max(ctx, values, target, num_segments)
        messages = values if source is None else values.index_select(0, source)
        out = values.new_zeros(num_segments, values.size(1))
        out.scatter_reduce_(0, target.unsqueeze(-1).expand_as(messages), messages, "amax", include_self=False)
        ctx.save_for_backward(messages, out, source, target)
        ctx.num_values, ctx.num_nonempty = values.size(0), num_nonempty
        return out

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, None, None, None, None]:  # type: ignore[override]
        if not ctx.needs_input_grad[0]:
            return None, None, None, None, None
        if ctx.compiled:
            return _compiled_segment_max_backward(ctx, grad_out), None, None, None, None
        messages, out, source, target = ctx.saved_tensors
        grad = _max_gradient(messages, out, target, grad_out.index_select(0, target), ctx.num_nonempty)
        if source is None:
            return grad, None, None, None, None
        grad_values = grad.new_zeros(ctx.num_values, grad.size(1))
        return grad_values.index_add_(0, source, grad), None, None, None, None


def segment_max(values: Tensor, source: Tensor | None, target: Tensor, num_segments: int, num_nonempty: int) -> Tensor:
    """Functional form of :class:`SegmentMax`.

    :param values: ``(V, C)`` rows
    :param source: ``(E,)`` rows of ``values`` to reduce, or ``None`` for all rows in order
    :param target: ``(E,)`` segment of each reduced row
    :param num_segments: number of segments ``S``
    :param num_nonempty: number of distinct values in ``target``
    :return: ``(S, C)`` maxima, 0 for empty segments
    """
    return SegmentMax.apply(values, source, target, num_segments, num_nonempty)


class _RelationalMax(torch.autograd.Function):
    """Per vertex: the sum over relations of the maximum per relation, plus the root row.

    Input ``rows`` ``(M * stride, C)`` holds, per vertex, ``R`` relation rows then (if
    ``stride = R + 1``) its root row; output ``(M, C)`` viewed as ``shape``. One custom backward replaces the
    autograd chain (segment max, sum over relations, root slice, gradient accumulation).

    ``bias`` (``(C,)``, or ``(K, C)`` for ``K`` stacked copies) is given only on the compiled path
    (:func:`_compiled_path`), which adds it in the kernel; the PyTorch formulation receives
    ``None`` and rows that already hold it (the matmul added it).
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        rows: Tensor,
        bias: Tensor | None,
        layout: RelationalLayout,
        shape: tuple[int, ...],
        num_relations: int,
        stride: int,
    ) -> Tensor:
        channels = rows.size(1)
        num_vertices = math.prod(shape[:-1])
        ctx.layout, ctx.shape = layout, (num_vertices, num_relations, stride)
        ctx.compiled = bias is not None or _compiled_path(rows)
        if ctx.compiled:
            return _compiled_forward(ctx, rows, bias, layout, shape, num_vertices, num_relations, stride)
        messages = rows.index_select(0, layout.source)
        maxima = rows.new_zeros(num_vertices * num_relations, channels)
        index = layout.target.unsqueeze(-1).expand_as(messages)
        maxima.scatter_reduce_(0, index, messages, "amax", include_self=False)
        # Slice by slice: a sum over the small middle dimension is much slower on CPU.
        per_relation = maxima.view(num_vertices, num_relations, channels)
        out = rows.new_empty(shape)  # written through a flat view: the output must not be a view
        flat = out.view(num_vertices, channels)
        if stride > num_relations:
            torch.add(per_relation[:, 0], rows.view(num_vertices, stride, channels)[:, num_relations], out=flat)
        else:
            flat.copy_(per_relation[:, 0])
        for r in range(1, num_relations):
            flat += per_relation[:, r]
        ctx.save_for_backward(messages, maxima)
        return out

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        layout, (num_vertices, num_relations, stride) = ctx.layout, ctx.shape
        if ctx.compiled:
            return (*_compiled_backward(ctx, grad_out), None, None, None, None)
        messages, maxima = ctx.saved_tensors
        if layout.target_vertex is None or layout.num_nonempty is None:
            raise RuntimeError("_RelationalMax: a forward-only layout (derived without autograd) in a backward pass")
        source_order, sorted_source = layout.source_order, layout.sorted_source
        if source_order is None or sorted_source is None:  # a layout of the compiled path
            source_order = torch.argsort(layout.source)
            sorted_source = layout.source[source_order]
        # Explicit channel counts, never -1: a batch without vertices has 0 elements to infer them from.
        channels = messages.size(1)
        grad_out = grad_out.reshape(num_vertices, channels)
        # d out_i / d maxima_(i, r) = 1 for every relation r: read the gradient of vertex i.
        grad = grad_out.index_select(0, layout.target_vertex)
        grad = _max_gradient(messages, maxima, layout.target, grad, layout.num_nonempty)
        grad_rows = grad.new_zeros(num_vertices * stride, channels)
        if stride > num_relations:
            grad_rows.view(num_vertices, stride, channels)[:, num_relations] = grad_out
        grad = grad.index_select(0, source_order)
        return grad_rows.index_add_(0, sorted_source, grad), None, None, None, None, None


# "segment_max": the kernels also serve SegmentMax (benchmarks switch that alone off to time the
# learner without it, benchmarks/bench_learner.py).
# "compact": compute only the relation rows that some edge reads (:class:`_CompactRelationalConv`).
_COMPILED = {"enabled": True, "kernels": None, "segment_max": True, "compact": True}


# Without autograd, one convolution computes every relation row in one fused matmul (its weights
# fused once per parameter change, see RelationalMaxConv.inference_weights) below this many
# vertices, and only the rows that edges read from it on: per call, fused / compact 0.09 / 0.18 ms
# at 4 vertices (a planner's scene), 0.29 / 0.27 ms at 560, 3.5 / 2.8 ms at 5,238 (a batch of 256
# intersection graphs: the target networks); 1 thread, 64 channels, 2 relations.
_COMPACT_MIN_VERTICES = 256


def use_compiled_kernels(enabled: bool) -> bool:
    """Switch the compiled (numba) CPU kernels of the relational max aggregation on or off.

    Off, every device runs the PyTorch formulation of :class:`_RelationalMax`: the reference that
    the kernels are tested against (same values, gradients equal to float rounding).

    :param enabled: use the kernels for CPU tensors of float32 / float64
    :return: the previous setting
    """
    previous = _COMPILED["enabled"]
    _COMPILED["enabled"] = bool(enabled)
    return bool(previous)


def use_compact_rows(enabled: bool) -> bool:
    """Switch the compact relation rows of the compiled max path on or off
    (:class:`_CompactRelationalConv`: only the relation rows that some edge reads are computed).

    Off, the path computes every vertex's relation and root rows in one fused matmul, as before;
    both give the same values and gradients to float rounding.

    :param enabled: compute only the relation rows that some edge reads (with autograd, for
        stacked convolutions, and for large batches without it)
    :return: the previous setting
    """
    previous = _COMPILED["compact"]
    _COMPILED["compact"] = bool(enabled)
    return bool(previous)


def _kernels(device: torch.device) -> Any:
    """The compiled kernels module (imported on first use) for tensors on ``device``, or ``None``:
    switched off, not a CPU device, or numba missing or broken (then switched off for good)."""
    if not _COMPILED["enabled"] or device.type != "cpu":
        return None
    if _COMPILED["kernels"] is None:
        try:
            from sb3_graph import _max_kernel
        except ImportError:  # numba missing or broken: the PyTorch formulation
            _COMPILED["enabled"] = False
            return None
        _COMPILED["kernels"] = _max_kernel
    return _COMPILED["kernels"]


def _compiled_path(rows: Tensor) -> bool:
    return rows.dtype in (torch.float32, torch.float64) and _kernels(rows.device) is not None


_NO_TERMS = np.empty((0, 2), dtype=np.int64)


def _empty_arrays(like: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Empty ``(0, 0)`` and ``(0, 0, 0)`` arrays of the dtype of ``like``: the kernels' arguments
    for no separate root rows, no edge features and no edge features' weights."""
    dtype = torch.empty(0, dtype=like.dtype).numpy().dtype
    return np.empty((0, 0), dtype), np.empty((0, 0, 0), dtype)


def _compiled_forward(
    ctx: Any,
    rows: Tensor,
    bias: Tensor | None,
    layout: RelationalLayout,
    shape: tuple[int, ...],
    num_vertices: int,
    num_relations: int,
    stride: int,
) -> Tensor:
    """:class:`_RelationalMax`'s forward pass with :func:`sb3_graph._max_kernel.relational_max_forward`."""
    kernels = _COMPILED["kernels"]
    rows = rows.detach().contiguous()
    channels = rows.size(1)
    out = rows.new_empty(shape)
    maxima = rows.new_empty(num_vertices * num_relations, channels)
    seen = torch.zeros(num_vertices * num_relations, dtype=torch.bool)
    ctx.bias_shape = None if bias is None else bias.shape
    bias_rows = rows.new_empty(0, 0) if bias is None else bias.detach().reshape(-1, channels).to(rows.dtype)
    # The backward pass reads which rows won (recorded on the full layout, sorted by target), not
    # the rows and maxima: far fewer bytes.
    record = layout.target_vertex is not None and any(ctx.needs_input_grad[:2])
    wins = torch.empty((len(layout.source), channels) if record else (0, 0), dtype=torch.uint8)
    _, unique = kernels.relational_max_forward(
        rows.numpy(), layout.source.numpy(), layout.target.numpy(), num_relations, stride,
        bias_rows.contiguous().numpy(), shape[-2], out.view(num_vertices, channels).numpy(), maxima.numpy(),
        seen.numpy(), wins.numpy(), _empty_arrays(rows)[0],
    )  # fmt: skip
    if record:
        ctx.save_for_backward(wins)
        ctx.rows_shape, ctx.dtype = rows.shape, rows.dtype
        ctx.ties = not unique  # a tie, or a NaN maximum that no row equals
    return out


def _compiled_backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor, Tensor | None]:
    """:class:`_RelationalMax`'s backward pass with the kernels (PyTorch's tie rule when a maximum
    is tied) and the bias gradient."""
    kernels = _COMPILED["kernels"]
    layout, (num_vertices, num_relations, stride) = ctx.layout, ctx.shape
    if layout.target_vertex is None:
        raise RuntimeError("_RelationalMax: a forward-only layout (derived without autograd) in a backward pass")
    (wins,) = ctx.saved_tensors
    grad_out = grad_out.reshape(num_vertices, ctx.rows_shape[1]).contiguous().to(ctx.dtype)
    grad_rows = grad_out.new_empty(ctx.rows_shape)  # the kernel writes every row
    no_attr, no_weight = _empty_arrays(grad_out)
    kernels.relational_max_backward(
        grad_out.numpy(), layout.source.numpy(), layout.target.numpy(), wins.numpy(), num_relations, stride,
        ctx.ties, grad_rows.numpy(), no_attr, _NO_TERMS, no_weight,
    )  # fmt: skip
    grad_bias = None
    if ctx.bias_shape is not None and ctx.needs_input_grad[1]:
        copies = 1 if len(ctx.bias_shape) == 1 else ctx.bias_shape[0]
        grad_bias = grad_out.view(copies, -1, grad_out.size(1)).sum(dim=1).view(ctx.bias_shape)
    return grad_rows, grad_bias


def _compiled_segment_max(ctx: Any, values: Tensor, target: Tensor, num_segments: int) -> Tensor:
    """:class:`SegmentMax`'s forward pass over all rows in order (critic max pooling, the messages of
    a convolution with edge features) with the relational kernels: every row is a segment's only
    relation (``R = 1``, no root term, no bias), so the output is the maxima themselves."""
    kernels = _COMPILED["kernels"]
    values = values.detach().contiguous()
    target = target.contiguous()
    source = torch.arange(values.size(0), device=values.device)
    out = values.new_empty(num_segments, values.size(1))
    maxima = values.new_empty(num_segments, values.size(1))
    seen = torch.zeros(num_segments, dtype=torch.bool)
    empty = _empty_arrays(values)[0]  # no bias, no separate root rows
    kernels.relational_max_forward(
        values.numpy(), source.numpy(), target.numpy(), 1, 1, empty, num_segments, out.numpy(), maxima.numpy(),
        seen.numpy(), np.empty((0, 0), dtype=np.uint8), empty,
    )  # fmt: skip
    ctx.save_for_backward(values, source, target, maxima)
    return out


def _compiled_segment_max_backward(ctx: Any, grad_out: Tensor) -> Tensor:
    """:class:`SegmentMax`'s backward pass with the kernels: each row equal to its segment's maximum
    gets the segment's gradient (split evenly among tied rows, PyTorch's rule)."""
    kernels = _COMPILED["kernels"]
    values, source, target, maxima = ctx.saved_tensors
    grad_out = grad_out.contiguous().to(values.dtype)
    grad_values = values.new_empty(values.shape)  # the kernel writes every row
    # Straight to the tie rule: after a ReLU, max pooling nearly always ties (a channel at 0 in
    # several vertices of a graph), and without ties it gives the same gradient (each count is 1).
    arrays = (values.numpy(), source.numpy(), target.numpy(), maxima.numpy(), 1, 1)
    kernels.relational_max_backward_ties(grad_out.numpy(), *arrays, grad_values.numpy())
    return grad_values


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
    :class:`~sb3_graph.batching.DerivedIndexCache`).

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


class _CompactRelationalConv(torch.autograd.Function):
    """:func:`relational_conv` with max aggregation on the compiled CPU path, computing only the
    relation rows that some edge reads (:class:`CompactLayout`): per relation ``x[senders_r] W_r``,
    the root rows ``x W_0`` for every vertex, then the kernels' aggregation (which adds the bias).

    One function with its own backward: the blocks are matmuls into slices of one buffer (no
    concatenation), and the parameters enter unfused (no ``cat`` / ``stack`` nodes in the graph).
    The backward pass is the matmuls' own: ``grad x = grad_out W_0^T`` plus, per relation, the
    compact rows' gradients ``W_r^T`` added back to their senders (``index_add``), and
    ``grad W_r = x[senders_r]^T grad_rows_r``.

    With edge features the message of edge ``j -> i`` of relation ``r`` is ``x_j W_r + e_ji U_r``:
    the kernels add the edge term per edge as they reduce (no ``(E, out)`` tensor of messages) and
    add the gradient of ``U_r`` in their backward pass.

    Inputs of :meth:`forward`: ``x`` ``(N, in)`` or ``(K, N, in)``, the edge features ``(E', D)`` in
    the layout's edge order (``None`` without), the layout, ``K``, whether the convolutions have the
    root term, whether they have edge features, then the ``K`` relation weights ``(R, in, out)``,
    the ``K`` root weights ``(out, in)`` (none without the root term), the ``K`` edge features'
    weights ``(R, D, out)`` (none without edge features) and the ``K`` biases ``(out,)``.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        x: Tensor,
        attr: Tensor | None,
        layout: CompactLayout,
        copies: int,
        has_root: bool,
        has_edges: bool,
        *params: Tensor,
    ) -> Tensor:
        kernels = _COMPILED["kernels"]
        weights, roots = params[:copies], params[copies : copies * (1 + has_root)]
        edge_weights, biases = params[copies * (1 + has_root) : -copies], params[-copies:]
        stacked = x.dim() == 3
        x = x.detach()
        num_nodes, out_channels, relations = x.size(-2), weights[0].size(-1), weights[0].size(0)
        # Stacked: (R, K, in, out), one contiguous (K, in, out) per relation; else (R, in, out).
        weight = torch.stack([w.detach() for w in weights], dim=1) if stacked else weights[0].detach()
        offsets = layout.offsets
        # (K * S, in): relation by relation, each block (K, n_r, in) contiguous.
        x_rows = x.reshape(copies * num_nodes, x.size(-1)).index_select(0, layout.rows)
        rows = x.new_empty(copies * offsets[-1], out_channels)
        for r in range(relations):
            lo, hi = offsets[r], offsets[r + 1]
            if hi == lo:
                continue
            if stacked:
                block = x_rows[copies * lo : copies * hi].view(copies, hi - lo, -1)
                torch.bmm(block, weight[r], out=rows[copies * lo : copies * hi].view(copies, hi - lo, -1))
            else:
                torch.mm(x_rows[lo:hi], weight[r], out=rows[lo:hi])
        root, no_weight = _empty_arrays(x)
        attr_array, edge_weight = root, no_weight
        if has_edges:
            assert attr is not None
            attr_array = attr.detach().numpy()
            edge_weight = torch.cat([u.detach() for u in edge_weights]).numpy()  # (K * R, D, out)
        if has_root:
            if stacked:
                root = torch.bmm(x, torch.stack([w.detach() for w in roots]).transpose(1, 2))
            else:
                root = torch.mm(x, roots[0].detach().t())
            root = root.view(copies * num_nodes, out_channels).numpy()
        bias = torch.stack([b.detach() for b in biases]).to(x.dtype)
        base = layout.base
        num_vertices = copies * num_nodes
        # Written through a flat view: the output itself must not be a view (in-place ReLU).
        out = x.new_empty((copies, num_nodes, out_channels) if stacked else (num_nodes, out_channels))
        maxima = x.new_empty(num_vertices * relations, out_channels)
        seen = torch.zeros(num_vertices * relations, dtype=torch.bool)
        record = base.target_vertex is not None and any(ctx.needs_input_grad)
        wins = torch.empty((len(layout.source), out_channels) if record else (0, 0), dtype=torch.uint8)
        edges = (rows.numpy(), layout.source.numpy(), base.target.numpy(), relations)
        outputs = (
            bias.numpy(), num_nodes, out.view(num_vertices, out_channels).numpy(), maxima.numpy(), seen.numpy(),
            wins.numpy(), root,
        )  # fmt: skip
        if has_edges:  # the compact rows have no stride argument: R rows per sender, the root apart
            terms = layout.terms.numpy()
            _, unique = kernels.relational_max_edge_forward(*edges, *outputs, attr_array, edge_weight, terms)
        else:
            _, unique = kernels.relational_max_forward(*edges, relations, *outputs)
        if record:
            ctx.save_for_backward(x, x_rows, wins, weight, *roots)
            ctx.layout, ctx.ties, ctx.copies, ctx.has_root = layout, not unique, copies, has_root
            ctx.attr = attr_array if has_edges else None  # a numpy view of an observation: no autograd
        return out

    @staticmethod
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        kernels = _COMPILED["kernels"]
        x, x_rows, wins, weight, *roots = ctx.saved_tensors
        layout, copies, has_root = ctx.layout, ctx.copies, ctx.has_root
        base, offsets = layout.base, layout.offsets
        stacked = x.dim() == 3
        relations, in_channels, out_channels = weight.size(0), x.size(-1), grad_out.size(-1)
        num_nodes = x.size(-2)
        if base.target_vertex is None:
            raise RuntimeError("_CompactRelationalConv: a forward-only layout (no autograd) in a backward pass")
        grad_out = grad_out.contiguous().to(x.dtype)
        flat = grad_out.view(copies * num_nodes, out_channels)
        grad_rows = x.new_empty(copies * offsets[-1], out_channels)  # the kernel writes every row
        needs = ctx.needs_input_grad
        # Positions in the inputs: x, attr, layout, K, has_root, has_edges, then the parameters.
        first_root = 6 + copies
        first_edge = first_root + copies * has_root
        attr, grad_edge_weight = _empty_arrays(x)
        edge_weight_grads = ctx.attr is not None and any(needs[first_edge : first_edge + copies])
        if edge_weight_grads:  # (K * R, D, out) zeros, added to by the kernel
            attr = ctx.attr
            grad_edge_weight = np.zeros((copies * relations, attr.shape[1], out_channels), attr.dtype)
        kernels.relational_max_backward(
            flat.numpy(), layout.source.numpy(), base.target.numpy(), wins.numpy(), relations, relations,
            ctx.ties, grad_rows.numpy(), attr, _NO_TERMS if layout.terms is None else layout.terms.numpy(),
            grad_edge_weight,
        )  # fmt: skip
        grad_x = None
        if needs[0]:
            if has_root:
                root = torch.stack(roots) if stacked else roots[0]
                grad_x = torch.matmul(grad_out, root)
            else:
                grad_x = x.new_zeros(x.shape)
        # The compact rows' gradients w.r.t. their x rows, block by block into one buffer, then
        # added to their vertices in one index_add.
        grad_x_rows = None if grad_x is None else x.new_empty(x_rows.shape)
        grad_weight = None
        if any(needs[6:first_root]):  # zeros: a relation without senders has no block
            grad_weight = x.new_zeros((relations, copies, in_channels, out_channels))
        for r in range(relations):
            lo, hi = offsets[r], offsets[r + 1]
            if hi == lo:
                continue
            block = grad_rows[copies * lo : copies * hi]
            if stacked:
                block = block.view(copies, hi - lo, out_channels)
                if grad_x_rows is not None:
                    grad_block = grad_x_rows[copies * lo : copies * hi].view(copies, hi - lo, in_channels)
                    torch.bmm(block, weight[r].transpose(1, 2), out=grad_block)
                if grad_weight is not None:
                    x_block = x_rows[copies * lo : copies * hi].view(copies, hi - lo, in_channels)
                    torch.bmm(x_block.transpose(1, 2), block, out=grad_weight[r])
            else:
                if grad_x_rows is not None:
                    torch.mm(block, weight[r].t(), out=grad_x_rows[lo:hi])
                if grad_weight is not None:
                    torch.mm(x_rows[lo:hi].t(), block, out=grad_weight[r, 0])
        if grad_x is not None and grad_x_rows is not None:
            grad_x.view(copies * num_nodes, in_channels).index_add_(0, layout.rows, grad_x_rows)
        grads: list[Tensor | None] = [grad_x, None, None, None, None, None]
        grads += [None if grad_weight is None else grad_weight[:, k] for k in range(copies)]
        if has_root:
            grad_root = None
            if any(needs[first_root:first_edge]):
                grad_root = torch.matmul(grad_out.transpose(-1, -2), x)
            grads += [None if grad_root is None else (grad_root[k] if stacked else grad_root) for k in range(copies)]
        if ctx.attr is not None:
            grad_edges = torch.from_numpy(grad_edge_weight).view(copies, relations, -1, out_channels)
            grads += [grad_edges[k] if edge_weight_grads else None for k in range(copies)]
        grad_bias = grad_out.sum(dim=-2) if any(needs[-copies:]) else None
        grads += [None if grad_bias is None else (grad_bias[k] if stacked else grad_bias) for k in range(copies)]
        return tuple(grads)


class RelationalMaxConv(MessagePassing):
    r"""Relational graph convolution that aggregates *transformed* messages per relation
    (Klimke et al., IEEE IV 2022, section "Network Architecture"):

    .. math::
        \mathbf{x}^{\prime}_i = \mathbf{W}_0 \mathbf{x}_i + \mathbf{b}
        + \sum_{r \in \mathcal{R}} \bigoplus_{j \in \mathcal{N}_r(i)} \mathbf{W}_r \mathbf{x}_j

    and, with edge features :math:`\mathbf{e}_{ji}` (``edge_dim > 0``), the message of edge
    :math:`j \to i` is :math:`\mathbf{W}_r \mathbf{x}_j + \mathbf{U}_r \mathbf{e}_{ji}`, still
    reduced after the transform (the maximum over these messages, per relation),

    where :math:`\bigoplus` is the element-wise maximum (or mean / sum) over the in-neighbours
    :math:`\mathcal{N}_r(i)` of vertex :math:`i` along edges of relation :math:`r`, and an empty
    neighbourhood contributes :math:`\mathbf{0}`: a vertex without incoming edges reduces to a
    dense layer on itself. Unlike :class:`torch_geometric.nn.conv.RGCNConv` with ``aggr="max"``,
    which computes :math:`\mathbf{W}_r \max_j \mathbf{x}_j`, the maximum is taken after the
    relation weight is applied. No activation is applied (PyG style): the model applies it.

    The relation transforms and the root transform are one matmul to ``(N, (R + 1) * out)``; each
    edge then reads the row of its own relation and the messages are reduced into ``N * R``
    segments ``target * R + relation`` (:func:`relational_conv`, which also runs several
    convolutions of the same shape at once, e.g. twin critics). On the compiled CPU path with
    autograd, for stacked convolutions and for batches of 256 vertices or more, only the relation
    rows that some edge reads are computed (:class:`_CompactRelationalConv`, :func:`use_compact_rows`).

    :param in_channels: size of each input vertex feature
    :param out_channels: size of each output vertex feature
    :param num_relations: number of edge types :math:`R`
    :param aggr: aggregation within one relation: ``"max"`` (paper), ``"mean"`` or ``"sum"``
    :param root_weight: add the root term :math:`\mathbf{W}_0 \mathbf{x}_i`
    :param bias: add a learnable bias :math:`\mathbf{b}`
    :param edge_dim: number of edge features :math:`D` (0: messages read vertex features only)

    Shapes:
        - **input:** vertex features :math:`(|\mathcal{V}|, F_{in})`, edge indices
          :math:`(2, |\mathcal{E}|)` with rows ``(source, target)``, edge types
          :math:`(|\mathcal{E}|)`, edge features :math:`(|\mathcal{E}|, D)` when ``edge_dim > 0``
        - **output:** vertex features :math:`(|\mathcal{V}|, F_{out})`

    Without edge features, repeated edges are merged for the maximum and the aggregation runs
    over per-vertex rows (a message is a row of :math:`\mathbf{x} \mathbf{W}_r`); with them, every
    edge carries its own message. On CPU the max aggregation runs in compiled kernels
    (:mod:`sb3_graph._max_kernel`, numba), which also add the bias and, with edge features, form
    each edge's message as they reduce; :func:`use_compiled_kernels` switches them off for the
    PyTorch formulation, the reference they are tested against (with edge features it builds the
    ``(E, F_out)`` messages and reduces them with :func:`segment_max`).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        num_relations: int,
        aggr: str = "max",
        root_weight: bool = True,
        bias: bool = True,
        edge_dim: int = 0,
    ) -> None:
        if edge_dim < 0:
            raise ValueError(f"RelationalMaxConv: edge_dim must be >= 0, got {edge_dim}")
        if aggr not in AGGREGATIONS:
            raise ValueError(f"RelationalMaxConv: aggr must be one of {AGGREGATIONS}, got {aggr!r}")
        if num_relations < 1:
            raise ValueError(f"RelationalMaxConv: num_relations must be >= 1, got {num_relations}")
        super().__init__(aggr=aggr, node_dim=0)
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.num_relations = num_relations
        self.weight = nn.Parameter(torch.empty(num_relations, in_channels, out_channels))
        self.root = nn.Linear(in_channels, out_channels, bias=False) if root_weight else None
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.edge_dim = int(edge_dim)
        self.edge_weight = (
            nn.Parameter(torch.empty(num_relations, edge_dim, out_channels)) if edge_dim else None
        )
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        # Same scale as nn.Linear's default for each relation matrix.
        bound = 1.0 / math.sqrt(self.in_channels)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.root is not None:
            self.root.reset_parameters()
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)
        if self.edge_weight is not None:
            edge_bound = 1.0 / math.sqrt(self.edge_dim)
            nn.init.uniform_(self.edge_weight, -edge_bound, edge_bound)

    def forward(self, x: Tensor, edge_index: Tensor, edge_type: Tensor, edge_attr: Tensor | None = None) -> Tensor:
        """
        :param x: ``(N, in_channels)`` vertex features
        :param edge_index: ``(2, E)`` long ``(source, target)`` rows
        :param edge_type: ``(E,)`` long relation ids in ``[0, num_relations)``
        :param edge_attr: ``(E, edge_dim)`` edge features (required iff ``edge_dim > 0``)
        :return: ``(N, out_channels)`` vertex features
        """
        return relational_conv([self], x, edge_index, edge_type, edge_attr)

    def inference_weights(self) -> tuple[Tensor, Tensor | None]:
        """The fused weight and bias of :func:`relational_conv` for this convolution alone, for
        use without autograd (their values, not a graph to the parameters).

        Fusing is ~10 small tensor operations, as costly as the layer's matmul at intersection
        sizes (~13 vertices), so the result is kept until a parameter changes: another tensor
        (assignment), an in-place update (version counter: optimizer steps, Polyak updates,
        ``load_state_dict``) or new storage, type or device (``.to()``, ``.double()``).

        :return: as :func:`_fused_weights` with ``stacked=False``
        """
        params = [self.weight] + ([self.root.weight] if self.root is not None else []) + [self.bias]
        key = tuple(None if p is None else (id(p), p._version, p.data_ptr(), p.dtype, p.device) for p in params)
        cached = self.__dict__.get("_inference_weights")
        if cached is None or cached[0] != key:
            # Plain tensors even when called in inference mode: usable in any later no-grad pass.
            with torch.inference_mode(False), torch.no_grad():
                fused = _fused_weights([self], stacked=False)
            # The parameters themselves are held so that their ids stay theirs while cached.
            cached = (key, fused, params)
            self.__dict__["_inference_weights"] = cached
        return cached[1]

    def message(self, x_j: Tensor) -> Tensor:
        return x_j

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
            f"num_relations={self.num_relations}, aggr={self.aggr!r}"
            + (f", edge_dim={self.edge_dim})" if self.edge_dim else ")")
        )


def relational_conv(
    convs: Sequence[RelationalMaxConv],
    x: Tensor,
    edge_index: Tensor,
    edge_type: Tensor,
    edge_attr: Tensor | None = None,
) -> Tensor:
    """Apply one convolution, or ``K`` convolutions of the same shape each to its own input, on one
    graph batch: one (batched) matmul and one aggregation for all of them (the ``K`` copies are
    ``K`` disjoint graphs).

    :param convs: ``K`` convolutions with equal channels, relations, aggregation, root, bias and
        edge features
    :param x: ``(N, in_channels)`` input of the single convolution (``K = 1``), or
        ``(K, N, in_channels)`` input of each convolution
    :param edge_index: ``(2, E)`` long ``(source, target)`` rows
    :param edge_type: ``(E,)`` relation ids
    :param edge_attr: ``(E, edge_dim)`` edge features, required iff the convolutions have ``edge_dim > 0``
    :return: ``(N, out_channels)`` or ``(K, N, out_channels)``, as ``x``
    """
    first = convs[0]
    stacked = x.dim() == 3
    copies, num_nodes = len(convs), x.size(-2)
    if not stacked and copies != 1:
        raise ValueError(f"relational_conv: x must be (K, N, in_channels) for {copies} convolutions")
    r, out, has_root = first.num_relations, first.out_channels, first.root is not None
    stride = r + 1 if has_root else r
    compiled = first.aggr == "max" and first.bias is not None and _compiled_path(x)
    large = stacked or torch.is_grad_enabled() or num_nodes >= _COMPACT_MIN_VERTICES
    if first.edge_dim:
        if edge_attr is None or edge_attr.shape != (edge_index.size(1), first.edge_dim):
            got = None if edge_attr is None else tuple(edge_attr.shape)
            raise ValueError(
                f"relational_conv: edge_attr of shape ({edge_index.size(1)}, {first.edge_dim}) is required, got {got}"
            )
        # The kernels add each edge's term as they reduce; features that need a gradient take the
        # PyTorch formulation (observations never do), and so does a planner's scene without
        # autograd (0.92 against 0.66 ms per call at 19 vertices, see _COMPACT_MIN_VERTICES).
        if compiled and _COMPILED["compact"] and large and not edge_attr.requires_grad:
            compact = compact_layout(edge_index, edge_type, num_nodes, r, stride, copies, per_edge=True)
            order = compact.base.edge_order
            attr = (edge_attr if order is None else edge_attr.index_select(0, order)).to(x.dtype).contiguous()
            return _compact_conv(convs, x, compact, attr)
        if stacked:
            return torch.stack(
                [_edge_conv(c, x[k], edge_index, edge_type, edge_attr) for k, c in enumerate(convs)]
            )
        return _edge_conv(first, x, edge_index, edge_type, edge_attr)
    if compiled and _COMPILED["compact"] and large:
        return _compact_conv(convs, x, compact_layout(edge_index, edge_type, num_nodes, r, stride, copies), None)
    if stacked or torch.is_grad_enabled():
        # The kernel adds the bias itself: no fused bias to build on the compiled path.
        weight, bias = _fused_weights(convs, stacked, with_bias=not compiled)
    else:  # inference: the same tensors, fused once per change of the parameters
        weight, bias = first.inference_weights()
    layout = relational_layout(edge_index, edge_type, num_nodes, r, stride, first.aggr, copies)
    shape = (copies, num_nodes, out) if stacked else (num_nodes, out)
    if compiled:
        # The kernel adds the bias: a plain matmul spares addmm's pass that first copies the
        # broadcast bias into its (N, (R + 1) * out) result.
        kernel_bias = first.bias if not stacked else torch.stack([c.bias for c in convs])
        rows = torch.matmul(x, weight).view(copies * num_nodes * stride, out)
        return _RelationalMax.apply(rows, kernel_bias, layout, shape, r, stride)
    if bias is None or not has_root:
        transformed = torch.matmul(x, weight)
    else:
        transformed = torch.addmm(bias, x, weight) if not stacked else torch.baddbmm(bias, x, weight)
    rows = transformed.view(copies * num_nodes * stride, out)
    if first.aggr == "max":
        result = _RelationalMax.apply(rows, None, layout, shape, r, stride)
    else:
        aggregated = rows.new_zeros(copies * num_nodes * r, out)
        aggregated = aggregated.index_add(0, layout.target, rows.index_select(0, layout.source))
        if first.aggr == "mean":
            aggregated = aggregated / layout.counts.clamp(min=1).unsqueeze(-1).to(aggregated.dtype)
        result = aggregated.view(*shape[:-1], r, out).sum(dim=-2)
        if has_root:
            return result + transformed.view(*shape[:-1], stride, out)[..., r, :]
    return result + bias if bias is not None and not has_root else result


def _compact_conv(
    convs: Sequence[RelationalMaxConv], x: Tensor, compact: CompactLayout, attr: Tensor | None
) -> Tensor:
    """:class:`_CompactRelationalConv` of ``K`` convolutions (``attr``: the edge features in the
    layout's edge order, ``None`` without)."""
    has_root, has_edges = convs[0].root is not None, attr is not None
    params = [c.weight for c in convs] + ([c.root.weight for c in convs] if has_root else [])
    params += [c.edge_weight for c in convs] if has_edges else []
    params += [c.bias for c in convs]
    return _CompactRelationalConv.apply(x, attr, compact, len(convs), has_root, has_edges, *params)


def _fused_weights(
    convs: Sequence[RelationalMaxConv], stacked: bool, with_bias: bool = True
) -> tuple[Tensor, Tensor | None]:
    """Weight and bias of :func:`relational_conv`'s one matmul for ``K`` convolutions.

    :param convs: ``K`` convolutions of the same shape, without edge features
    :param stacked: ``(K, in, R * out [+ out])`` and ``(K, 1, ...)`` for a batched matmul; else
        (``K = 1``) ``(in, ...)`` and ``(...,)``
    :param with_bias: build the fused bias (``False``: ``None``, for the compiled path)
    :return: the weight (relation blocks, then the root block) and the bias (0 on the relation
        blocks: it joins the root block, so the matmul adds it), ``None`` without bias
    """
    first = convs[0]
    copies, r, out, has_root = len(convs), first.num_relations, first.out_channels, first.root is not None
    if not stacked:
        # A plain matmul for one convolution: cheaper than a batched one, and 2-D results let the
        # caller apply an in-place activation without autograd's view bookkeeping. Built directly
        # (not as copy 0 of the stacked weight): the same values with fewer tensor operations and
        # autograd nodes, which weigh at small batches.
        weight = first.weight.permute(1, 0, 2).reshape(first.in_channels, r * out)
        if has_root:
            weight = torch.cat((weight, first.root.weight.t()), dim=1)
        if not with_bias or first.bias is None:
            return weight, None
        return weight, torch.cat((first.bias.new_zeros(r * out), first.bias)) if has_root else first.bias
    bias = torch.stack([c.bias for c in convs]).unsqueeze(1) if with_bias and first.bias is not None else None
    weight = torch.stack([c.weight for c in convs]).permute(0, 2, 1, 3).reshape(copies, -1, r * out)
    if has_root:
        weight = torch.cat((weight, torch.stack([c.root.weight for c in convs]).transpose(1, 2)), dim=2)
        if bias is not None:
            bias = torch.cat((bias.new_zeros(copies, 1, r * out), bias), dim=2)
    return weight, bias


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


def _edge_conv(
    conv: RelationalMaxConv, x: Tensor, edge_index: Tensor, edge_type: Tensor, edge_attr: Tensor
) -> Tensor:
    """One convolution with edge features in the PyTorch formulation (the reference of the compiled
    path, and the path of other devices, other aggregations and features that need a gradient):
    message ``W_r x_j + U_r e_ji`` per edge, reduced per ``(target, relation)`` segment, summed over
    relations, plus root and bias (plain autograd around :func:`segment_max`)."""
    r, out, num_nodes = conv.num_relations, conv.out_channels, x.size(0)
    layout = edge_layout(edge_index, edge_type, num_nodes, r)
    relation_rows = torch.matmul(x, conv.weight.permute(1, 0, 2).reshape(conv.in_channels, r * out))
    messages = relation_rows.view(num_nodes * r, out).index_select(0, layout.source)
    edge_terms = torch.matmul(edge_attr.to(x.dtype), conv.edge_weight.permute(1, 0, 2).reshape(conv.edge_dim, r * out))
    if r == 1:
        messages = messages + edge_terms
    else:
        index = edge_type.long().view(-1, 1, 1).expand(-1, 1, out)
        messages = messages + edge_terms.view(-1, r, out).gather(1, index).squeeze(1)
    if conv.aggr == "max":
        aggregated = segment_max(messages, None, layout.segment, num_nodes * r, layout.num_nonempty)
    else:
        aggregated = messages.new_zeros(num_nodes * r, out).index_add(0, layout.segment, messages)
        if conv.aggr == "mean":
            aggregated = aggregated / layout.counts.clamp(min=1).unsqueeze(-1).to(aggregated.dtype)
    result = aggregated.view(num_nodes, r, out).sum(dim=1)
    if conv.root is not None:
        result = result + conv.root(x)
    return result if conv.bias is None else result + conv.bias
