"""Autograd functions of the max aggregation: a segment max (:class:`SegmentMax`), the relational
max over every relation row (:class:`_RelationalMax`) and over the compact rows
(:class:`_CompactRelationalConv`), each in PyTorch and, on CPU, in the compiled kernels."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sb3_graph.common.layers.compiled import _COMPILED, _NO_TERMS, _compiled_path, _empty_arrays
from sb3_graph.common.layers.layouts import CompactLayout, RelationalLayout


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
    """:class:`_RelationalMax`'s forward pass with the compiled ``_max_kernel.relational_max_forward``."""
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
