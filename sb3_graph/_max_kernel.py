"""The relational max aggregation of :class:`~sb3_graph.layers.RelationalMaxConv` on CPU, compiled
with numba (used by ``sb3_graph.layers._RelationalMax``; the PyTorch formulation there stays the
reference and serves every other device).

Why compiled: per layer, the PyTorch formulation makes about ten passes over an ``(E, C)`` tensor
of messages (gather, ``scatter_reduce``; in the backward pass a gather of the maxima, an equality
mask, a gather of the output gradient, a product, a permutation and an ``index_add``), and on
CPU each pass costs about as much as the layer's matmul at intersection sizes. Here the forward
pass is one pass over the edges (a branch-free maximum per channel, which vectorizes) and one over
the vertices (sum over relations, root term, bias); the backward pass is one pass over the edges
that adds each output gradient to the rows equal to their segment's maximum and counts them.

The forward pass also adds the layer's bias (in the PyTorch formulation ``addmm`` adds it to
the root block, which first copies the broadcast bias into its whole ``(N, (R + 1) * out)``
result). The maxima are those of the PyTorch formulation and the output's additions run in its
order; only the bias joins after the matmul instead of inside it, so outputs agree to float
rounding. The gradients are PyTorch's rule, the gradient split evenly among tied maxima: when the
count of rows equal to a maximum exceeds one per non-empty (segment, channel), the gradient is
recomputed with :func:`relational_max_backward_ties`, which splits as PyTorch does. Only the order
in which the gradients of one row are added differs (edges by target instead of by source), so
the gradients agree to float rounding (tests/test_layers.py, tests/test_learner_updates.py).

No ``fastmath``: no reassociation, so the forward sums are PyTorch's. ``cache=True`` stores the
machine code next to this file (or in numba's cache directory), so only the first process of an
installation compiles (a few seconds).
"""

from __future__ import annotations

import numba
import numpy as np


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
def _root_gradients(grad_out: np.ndarray, num_relations: int, stride: int, grad_rows: np.ndarray) -> None:
    """Start of the backward passes, one write per row in place of zeroing ``grad_rows`` first:
    ``grad_out[i]`` into the root row ``i * stride + R`` of each vertex (when ``stride > R``), 0 into
    every other row (the relation rows, which the edges then accumulate into)."""
    channels = grad_out.shape[1]
    for row in range(grad_rows.shape[0]):
        i, r = row // stride, row % stride
        if r == num_relations and i < grad_out.shape[0]:
            for c in range(channels):
                grad_rows[row, c] = grad_out[i, c]
        else:
            for c in range(channels):
                grad_rows[row, c] = 0.0


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
    :param grad_rows: ``(M * stride, C)``, written (every row: no need to zero it first)
    :return: the number of (edge, channel) pairs equal to their maximum: when it exceeds the
        number of non-empty (segment, channel) pairs, a maximum is tied (or a NaN took none) and the
        gradient must come from :func:`relational_max_backward_ties`
    """
    _root_gradients(grad_out, num_relations, stride, grad_rows)
    channels = grad_out.shape[1]
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
    :param grad_rows: ``(M * stride, C)``, written (every row: no need to zero it first)
    """
    channels = grad_out.shape[1]
    counts = np.zeros_like(maxima)  # float: the division stays in the rows' precision
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        for c in range(channels):
            if rows[s, c] == maxima[t, c]:
                counts[t, c] += 1
    _root_gradients(grad_out, num_relations, stride, grad_rows)
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        i = t // num_relations
        for c in range(channels):
            if rows[s, c] == maxima[t, c]:
                grad_rows[s, c] += grad_out[i, c] / counts[t, c]
