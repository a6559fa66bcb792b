"""The relational max aggregation of :class:`~sb3_graph.layers.RelationalMaxConv` on CPU, compiled
with numba (used by ``sb3_graph.layers._RelationalMax``; the PyTorch formulation there stays the
reference and serves every other device).

Why compiled: per layer, the PyTorch formulation makes about ten passes over an ``(E, C)`` tensor
of messages (gather, ``scatter_reduce``; in the backward pass a gather of the maxima, an equality
mask, a gather of the output gradient, a product, a permutation and an ``index_add``), and on
CPU each pass costs about as much as the layer's matmul at intersection sizes. The kernels here
make one pass over the edges in the forward pass, which also records the winning row of every
(segment, channel), and one pass over the segments in the backward pass, which adds each output
gradient to its winner's row.

The forward pass also adds the layer's bias (in the PyTorch formulation ``addmm`` adds it to
the root block, which first copies the broadcast bias into its whole ``(N, (R + 1) * out)``
result). The maxima are those of the PyTorch formulation and the output's additions run in its
order; only the bias joins after the matmul instead of inside it, so outputs agree to float
rounding. The gradients are PyTorch's rule, the gradient split evenly among
tied maxima: the forward pass counts equalities, and when one occurred (or a NaN) the backward
pass counts the tied maxima of every (segment, channel) and splits as PyTorch does. Only the order
in which the gradients of one row are added differs (segment order instead of edge order), so the
gradients agree to float rounding (tests/test_layers.py).

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
    track: bool,
    out: np.ndarray,
    maxima: np.ndarray,
    winner: np.ndarray,
    seen: np.ndarray,
) -> int:
    """Per vertex ``i`` of copy ``k``: ``out[i] = sum_r maxima[i * R + r] (+ rows[i * stride + R])
    (+ bias[k])``, with ``maxima[s] = max_{e : target[e] = s} rows[source[e]]`` per channel (0 for
    an empty segment). The additions run in the order of the PyTorch formulation: with the root
    term ``(maxima_0 + (root + bias)) + maxima_1 + ...``, else ``(maxima_0 + maxima_1 + ...) + bias``.

    :param rows: ``(M * stride, C)`` transformed rows (per vertex ``R`` relation rows, then the root
        row when ``stride = R + 1``)
    :param source: ``(E,)`` row read by each edge
    :param target: ``(E,)`` segment ``i * R + r`` of each edge (any order)
    :param num_relations: ``R``
    :param stride: rows per vertex
    :param bias: ``(K, C)`` bias of each of the ``K`` stacked copies, or ``(0, 0)`` for none
    :param num_nodes: vertices per copy (``M = K * num_nodes``)
    :param track: record the winners (for a backward pass)
    :param out: ``(M, C)`` output, written
    :param maxima: ``(M * R, C)``, written with the maxima (0 for an empty segment)
    :param winner: ``(M * R, C)`` int32, written with the row of each maximum when ``track``
    :param seen: ``(M * R,)`` False, set for the non-empty segments
    :return: number of equalities and NaNs met (0: every maximum is unique and finite)
    """
    channels = rows.shape[1]
    has_bias = bias.shape[0] > 0
    ties = 0
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        if not seen[t]:
            seen[t] = True
            for c in range(channels):
                maxima[t, c] = rows[s, c]
            if track:
                for c in range(channels):
                    winner[t, c] = s
            continue
        for c in range(channels):
            v, m = rows[s, c], maxima[t, c]
            if v > m:
                maxima[t, c] = v
                if track:
                    winner[t, c] = s
            elif v == m or v != v:
                if v != v:  # NaN propagates, as in scatter_reduce("amax")
                    maxima[t, c] = v
                ties += 1
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
    return ties


@numba.njit(cache=True)
def relational_max_backward(
    grad_out: np.ndarray, winner: np.ndarray, seen: np.ndarray, num_relations: int, stride: int, grad_rows: np.ndarray
) -> None:
    """Gradient of :func:`relational_max_forward` w.r.t. ``rows`` when every maximum is unique.

    :param grad_out: ``(M, C)`` output gradient
    :param winner: ``(M * R, C)`` rows of the maxima
    :param seen: ``(M * R,)`` non-empty segments
    :param num_relations: ``R``
    :param stride: rows per vertex
    :param grad_rows: ``(M * stride, C)`` zeros, written
    """
    channels = grad_out.shape[1]
    for i in range(grad_out.shape[0]):
        if stride > num_relations:
            root = i * stride + num_relations
            for c in range(channels):
                grad_rows[root, c] = grad_out[i, c]
        for r in range(num_relations):
            t = i * num_relations + r
            if seen[t]:
                for c in range(channels):
                    grad_rows[winner[t, c], c] += grad_out[i, c]


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
