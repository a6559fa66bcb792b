"""The relational max kernels as of commit de36e62 (issue #27's first round), kept so that
``bench_learner.py`` can time the learner before the second round in turns with today's, in one
process: its backward pass reads the rows and maxima back (today: a one-byte record of the winning
rows, see ``sb3_graph/_max_kernel.py``). A copy of that commit's ``_max_kernel.py`` kernels and of
``sb3_graph.layers``' wrappers around them; not used by the library.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from sb3_graph import layers


@numba.njit(cache=True)
def relational_max_forward(
    rows: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    num_relations: int,
    stride: int,
    bias: np.ndarray,
    num_nodes: int,
    out: np.ndarray,
    maxima: np.ndarray,
    seen: np.ndarray,
) -> int:
    """Per vertex ``i`` of copy ``k``: ``out[i] = sum_r maxima[i * R + r] (+ rows[i * stride + R])
    (+ bias[k])``, with ``maxima[s] = max_{e : target[e] = s} rows[source[e]]`` per channel (0 for
    an empty segment; a NaN propagates, as in ``scatter_reduce("amax")``). The additions run in the
    order of the PyTorch formulation: with the root term ``(maxima_0 + (root + bias)) + maxima_1 +
    ...``, else ``(maxima_0 + maxima_1 + ...) + bias``.

    :param rows: ``(M * stride, C)`` transformed rows (per vertex ``R`` relation rows, then the root
        row when ``stride = R + 1``)
    :param source: ``(E,)`` row read by each edge
    :param target: ``(E,)`` segment ``i * R + r`` of each edge (any order)
    :param num_relations: ``R``
    :param stride: rows per vertex
    :param bias: ``(K, C)`` bias of each of the ``K`` stacked copies, or ``(0, 0)`` for none
    :param num_nodes: vertices per copy (``M = K * num_nodes``)
    :param out: ``(M, C)`` output, written
    :param maxima: ``(M * R, C)``, written with the maxima
    :param seen: ``(M * R,)`` False, set for the non-empty segments
    :return: number of non-empty segments
    """
    channels = rows.shape[1]
    has_bias = bias.shape[0] > 0
    nonempty = 0
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        if not seen[t]:
            seen[t] = True
            nonempty += 1
            for c in range(channels):
                maxima[t, c] = rows[s, c]
            continue
        for c in range(channels):  # branch-free: the channel loop vectorizes
            v, m = rows[s, c], maxima[t, c]
            maxima[t, c] = v if (v > m) | (v != v) else m
    for t in range(seen.shape[0]):
        if not seen[t]:
            for c in range(channels):
                maxima[t, c] = 0.0
    for i in range(out.shape[0]):
        base, k = i * num_relations, i // max(num_nodes, 1)
        if stride > num_relations:
            root = i * stride + num_relations
            if has_bias:
                for c in range(channels):
                    out[i, c] = maxima[base, c] + (rows[root, c] + bias[k, c])
            else:
                for c in range(channels):
                    out[i, c] = maxima[base, c] + rows[root, c]
        else:
            for c in range(channels):
                out[i, c] = maxima[base, c]
        for r in range(1, num_relations):
            for c in range(channels):
                out[i, c] += maxima[base + r, c]
        if has_bias and stride == num_relations:
            for c in range(channels):
                out[i, c] += bias[k, c]
    return nonempty


@numba.njit(cache=True)
def relational_max_backward(
    grad_out: np.ndarray,
    rows: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    maxima: np.ndarray,
    num_relations: int,
    stride: int,
    grad_rows: np.ndarray,
) -> int:
    """Gradient of :func:`relational_max_forward` w.r.t. ``rows`` when every maximum is unique:
    each row equal to its segment's maximum gets the output gradient of the segment's vertex.

    :param grad_out: ``(M, C)`` output gradient
    :param rows: ``(M * stride, C)`` the forward pass's rows
    :param source: ``(E,)`` row read by each edge (no repeated ``(source, target)`` pair)
    :param target: ``(E,)`` segment of each edge
    :param maxima: ``(M * R, C)`` the forward pass's maxima
    :param num_relations: ``R``
    :param stride: rows per vertex
    :param grad_rows: ``(M * stride, C)`` zeros, written
    :return: the number of (edge, channel) pairs equal to their maximum: when it exceeds the
        number of non-empty (segment, channel) pairs, a maximum is tied (or a NaN took none) and the
        gradient must come from :func:`relational_max_backward_ties`
    """
    channels = grad_out.shape[1]
    if stride > num_relations:
        for i in range(grad_out.shape[0]):
            root = i * stride + num_relations
            for c in range(channels):
                grad_rows[root, c] = grad_out[i, c]
    winners = 0
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        i = t // num_relations
        for c in range(channels):  # branch-free: the channel loop vectorizes
            is_max = rows[s, c] == maxima[t, c]
            grad_rows[s, c] += grad_out[i, c] if is_max else 0.0
            winners += is_max
    return winners


@numba.njit(cache=True)
def relational_max_backward_ties(
    grad_out: np.ndarray,
    rows: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    maxima: np.ndarray,
    num_relations: int,
    stride: int,
    grad_rows: np.ndarray,
) -> None:
    """The same gradient with PyTorch's rule for ties: each row equal to its segment's maximum
    gets the output gradient divided by the number of such rows (a NaN maximum passes none).

    :param grad_out: ``(M, C)`` output gradient
    :param rows: ``(M * stride, C)`` the forward pass's rows
    :param source: ``(E,)`` row read by each edge (no repeated ``(source, target)`` pair)
    :param target: ``(E,)`` segment of each edge
    :param maxima: ``(M * R, C)`` the forward pass's maxima
    :param num_relations: ``R``
    :param stride: rows per vertex
    :param grad_rows: ``(M * stride, C)`` zeros, written
    """
    channels = grad_out.shape[1]
    counts = np.zeros_like(maxima)  # float: the division stays in the rows' precision
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        for c in range(channels):
            if rows[s, c] == maxima[t, c]:
                counts[t, c] += 1
    if stride > num_relations:
        for i in range(grad_out.shape[0]):
            root = i * stride + num_relations
            for c in range(channels):
                grad_rows[root, c] = grad_out[i, c]
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        i = t // num_relations
        for c in range(channels):
            if rows[s, c] == maxima[t, c]:
                grad_rows[s, c] += grad_out[i, c] / counts[t, c]


def _compiled_forward(
    ctx: Any,
    rows: Tensor,
    bias: Tensor | None,
    layout: Any,
    shape: tuple[int, ...],
    num_vertices: int,
    num_relations: int,
    stride: int,
) -> Tensor:
    rows = rows.detach().contiguous()
    channels = rows.size(1)
    out = rows.new_empty(shape)
    maxima = rows.new_empty(num_vertices * num_relations, channels)
    seen = torch.zeros(num_vertices * num_relations, dtype=torch.bool)
    ctx.bias_shape = None if bias is None else bias.shape
    bias_rows = rows.new_empty(0, 0) if bias is None else bias.detach().reshape(-1, channels).to(rows.dtype)
    ctx.num_nonempty = relational_max_forward(
        rows.numpy(), layout.source.numpy(), layout.target.numpy(), num_relations, stride,
        bias_rows.contiguous().numpy(), shape[-2], out.view(num_vertices, channels).numpy(), maxima.numpy(),
        seen.numpy(),
    )  # fmt: skip
    if layout.target_vertex is not None and any(ctx.needs_input_grad[:2]):
        ctx.save_for_backward(rows, maxima)
    return out


def _compiled_backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor, Tensor | None]:
    layout, (num_vertices, num_relations, stride) = ctx.layout, ctx.shape
    rows, maxima = ctx.saved_tensors
    grad_out = grad_out.reshape(num_vertices, rows.size(1)).contiguous().to(rows.dtype)
    grad_rows = rows.new_zeros(rows.shape)
    arrays = (rows.numpy(), layout.source.numpy(), layout.target.numpy(), maxima.numpy(), num_relations, stride)
    winners = relational_max_backward(grad_out.numpy(), *arrays, grad_rows.numpy())
    if winners != ctx.num_nonempty * rows.size(1):
        grad_rows.zero_()
        relational_max_backward_ties(grad_out.numpy(), *arrays, grad_rows.numpy())
    grad_bias = None
    if ctx.bias_shape is not None and ctx.needs_input_grad[1]:
        copies = 1 if len(ctx.bias_shape) == 1 else ctx.bias_shape[0]
        grad_bias = grad_out.view(copies, -1, grad_out.size(1)).sum(dim=1).view(ctx.bias_shape)
    return grad_rows, grad_bias


@contextlib.contextmanager
def previous_kernels() -> Iterator[None]:
    """Within the block, the relational layers run de36e62's kernels and the critics' max pooling
    the PyTorch formulation (as at de36e62)."""
    saved = layers._compiled_forward, layers._compiled_backward
    layers._compiled_forward, layers._compiled_backward = _compiled_forward, _compiled_backward
    layers._COMPILED["segment_max"] = False
    try:
        yield
    finally:
        layers._compiled_forward, layers._compiled_backward = saved
        layers._COMPILED["segment_max"] = True
