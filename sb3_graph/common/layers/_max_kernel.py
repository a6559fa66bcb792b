"""The relational max aggregation of :class:`~sb3_graph.common.layers.RelationalMaxConv` on CPU,
compiled with numba (used by ``sb3_graph.common.layers.max_aggregation._RelationalMax``, switched
by :mod:`sb3_graph.common.layers.compiled`; the PyTorch formulation there stays the reference and
serves every other device).

Why compiled: per layer, the PyTorch formulation makes about ten passes over an ``(E, C)`` tensor
of messages (gather, ``scatter_reduce``; in the backward pass a gather of the maxima, an equality
mask, a gather of the output gradient, a product, a permutation and an ``index_add``), and on
CPU each pass costs about as much as the layer's matmul at intersection sizes. Here the forward
pass is one pass over the edges (a branch-free maximum per channel, which vectorizes) and one over
the vertices (sum over relations, root term, bias); with autograd, the forward pass also records
per edge and channel whether the row equals its segment's maximum (``wins``, one byte), compared
as each segment completes, while its rows are in cache. The backward pass is one pass over the
edges that adds each output gradient to the rows that won, read from that record: reading the rows
and maxima back instead costs several times the bytes, by then out of cache (the backward pass
ran 3x slower inside a training step than on its own).

The forward pass also adds the layer's bias (in the PyTorch formulation ``addmm`` adds it to
the root block, which first copies the broadcast bias into its whole ``(N, (R + 1) * out)``
result). The maxima are those of the PyTorch formulation and the output's additions run in its
order; only the bias joins after the matmul instead of inside it, so outputs agree to float
rounding. The gradients are PyTorch's rule, the gradient split evenly among tied maxima: when the
count of rows equal to a maximum differs from one per non-empty (segment, channel), the backward
pass counts the winners of each segment and splits as PyTorch does. Only the order
in which the gradients of one row are added differs (edges by target instead of by source), so
the gradients agree to float rounding (tests/test_layers.py, tests/test_learner_updates.py).

With edge features (:func:`relational_max_edge_forward`) each edge's message is the sender's row
plus the edge term, formed in the pass over the edges instead of as an ``(E, C)`` tensor, and the
backward pass adds the edge weights' gradient as it goes. :func:`segment_order` sorts a layout's
edges by segment with a counting sort (the ids are bounded), in place of sorting 64-bit keys.

No ``fastmath``: no reassociation, so the forward sums are PyTorch's. ``cache=True`` stores the
machine code next to this file (or in numba's cache directory), so only the first process of an
installation compiles (a few seconds).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def _vertex_sums(
    maxima: np.ndarray,
    seen: np.ndarray,
    rows: np.ndarray,
    root: np.ndarray,
    bias: np.ndarray,
    num_relations: int,
    stride: int,
    num_nodes: int,
    out: np.ndarray,
) -> None:
    """The forward kernels' pass over the vertices: empty segments' maxima to 0, then per vertex
    the sum over relations, the root row and the bias (see :func:`relational_max_forward`)."""
    channels = maxima.shape[1]
    has_bias = bias.shape[0] > 0
    separate_root = root.shape[0] > 0
    has_root = separate_root or stride > num_relations
    for t in range(seen.shape[0]):
        if not seen[t]:
            for c in range(channels):
                maxima[t, c] = 0.0
    for i in range(out.shape[0]):
        base, k = i * num_relations, i // max(num_nodes, 1)
        if has_root:  # index loops, no row views: a view per vertex costs more than its sums
            # The root row: vertex i of the separate root rows, or the last row of its block.
            src, own = (root, i) if separate_root else (rows, i * stride + num_relations)
            if has_bias:
                for c in range(channels):
                    out[i, c] = maxima[base, c] + (src[own, c] + bias[k, c])
            else:
                for c in range(channels):
                    out[i, c] = maxima[base, c] + src[own, c]
        else:
            for c in range(channels):
                out[i, c] = maxima[base, c]
        for r in range(1, num_relations):
            for c in range(channels):
                out[i, c] += maxima[base + r, c]
        if has_bias and not has_root:
            for c in range(channels):
                out[i, c] += bias[k, c]


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
    wins: np.ndarray,
    root: np.ndarray,
) -> tuple[int, bool]:
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
    :param wins: ``(E, C)`` uint8, written with ``rows[source[e], c] == maxima[target[e], c]`` (the
        rows that receive a gradient, see :func:`relational_max_backward`), or ``(0, 0)`` for none
        (no backward pass). Recorded only for edges sorted by ``target``: each segment's rows are
        compared as soon as its maximum is complete, while they are still in cache.
    :param root: ``(M, C)`` root rows kept apart from ``rows`` (the compact layout: ``rows`` then
        holds only the relation rows that some edge reads, ``stride = R``), or ``(0, 0)`` for the
        root rows inside ``rows`` (``stride = R + 1``) or none
    :return: number of non-empty segments, and whether ``wins`` holds exactly one winner per
        non-empty (segment, channel): no tie and no NaN maximum (False without a record)
    """
    channels = rows.shape[1]
    record = wins.shape[0] > 0
    nonempty, winners, nan_maxima, start = 0, 0, 0, 0
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        if not seen[t]:
            seen[t] = True
            nonempty += 1
            for c in range(channels):
                maxima[t, c] = rows[s, c]
        else:
            for c in range(channels):  # branch-free: the channel loop vectorizes
                v, m = rows[s, c], maxima[t, c]
                maxima[t, c] = v if (v > m) | (v != v) else m
        if record and (e + 1 == source.shape[0] or target[e + 1] != t):  # the segment is complete
            for f in range(start, e + 1):
                row = source[f]
                for c in range(channels):
                    is_max = rows[row, c] == maxima[t, c]
                    wins[f, c] = is_max
                    winners += is_max
            for c in range(channels):  # a NaN maximum has no winner: the count alone would miss it
                nan_maxima += maxima[t, c] != maxima[t, c]
            start = e + 1
    _vertex_sums(maxima, seen, rows, root, bias, num_relations, stride, num_nodes, out)
    return nonempty, record and nan_maxima == 0 and winners == nonempty * channels


@numba.njit(cache=True, inline="always")
def _edge_message(
    rows: np.ndarray, row: int, attr: np.ndarray, edge_weight: np.ndarray, terms: np.ndarray, e: int,
    messages: np.ndarray, slot: int,
) -> None:
    """``messages[slot] = rows[row] + sum_d attr[a, d] * edge_weight[w, d]`` with ``a, w = terms[e]``:
    the edge term summed over the features first, then added to the row (the order of the PyTorch
    formulation: a matmul of the features, then the sum with the gathered rows)."""
    a, w = terms[e, 0], terms[e, 1]
    channels = rows.shape[1]
    for c in range(channels):
        messages[slot, c] = attr[a, 0] * edge_weight[w, 0, c]
    for d in range(1, attr.shape[1]):
        for c in range(channels):
            messages[slot, c] += attr[a, d] * edge_weight[w, d, c]
    for c in range(channels):
        messages[slot, c] += rows[row, c]


@numba.njit(cache=True)
def relational_max_edge_forward(
    rows: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    num_relations: int,
    bias: np.ndarray,
    num_nodes: int,
    out: np.ndarray,
    maxima: np.ndarray,
    seen: np.ndarray,
    wins: np.ndarray,
    root: np.ndarray,
    attr: np.ndarray,
    edge_weight: np.ndarray,
    terms: np.ndarray,
) -> tuple[int, bool]:
    """:func:`relational_max_forward` of a convolution with edge features: the message of edge ``e``
    is ``rows[source[e]] + sum_d attr[a, d] * edge_weight[w, d]`` with ``a, w = terms[e]`` (``w = k
    * R + r`` for relation ``r`` of copy ``k``), computed as the edges are reduced (no ``(E, C)``
    tensor of messages); a segment's messages stay in a scratch buffer for its record. The root
    rows are ``root`` (the compact layout, ``stride = R``), or none when ``(0, 0)``.

    :param attr: ``(A, D)`` edge features, ``D >= 1``
    :param edge_weight: ``(K * R, D, C)`` the edge features' weights
    :param terms: ``(E, 2)`` each edge's row of ``attr`` and of ``edge_weight``
    :return: as :func:`relational_max_forward`
    """
    channels = rows.shape[1]
    record = wins.shape[0] > 0
    longest, run = 1, 0
    if record:  # the longest segment (edges sorted by target) sizes the scratch
        for e in range(source.shape[0]):
            run = run + 1 if e > 0 and target[e] == target[e - 1] else 1
            longest = max(longest, run)
    messages = np.empty((longest, channels), rows.dtype)
    pairs = attr.shape[1] == 2  # the intersection's edges: two features, one fused pass
    nonempty, winners, nan_maxima, start = 0, 0, 0, 0
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        slot = e - start if record else 0
        first = not seen[t]
        if first:
            seen[t] = True
            nonempty += 1
        if pairs:
            a, w = terms[e, 0], terms[e, 1]
            a0, a1 = attr[a, 0], attr[a, 1]
            for c in range(channels):  # branch-free: the channel loop vectorizes
                v = (a0 * edge_weight[w, 0, c] + a1 * edge_weight[w, 1, c]) + rows[s, c]
                messages[slot, c] = v
                m = maxima[t, c]
                maxima[t, c] = v if first | (v > m) | (v != v) else m
        else:
            _edge_message(rows, s, attr, edge_weight, terms, e, messages, slot)
            for c in range(channels):
                v, m = messages[slot, c], maxima[t, c]
                maxima[t, c] = v if first | (v > m) | (v != v) else m
        if record and (e + 1 == source.shape[0] or target[e + 1] != t):  # the segment is complete
            for f in range(start, e + 1):
                for c in range(channels):
                    is_max = messages[f - start, c] == maxima[t, c]
                    wins[f, c] = is_max
                    winners += is_max
            for c in range(channels):
                nan_maxima += maxima[t, c] != maxima[t, c]
            start = e + 1
    _vertex_sums(maxima, seen, rows, root, bias, num_relations, num_relations, num_nodes, out)
    return nonempty, record and nan_maxima == 0 and winners == nonempty * channels


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


@numba.njit(cache=True, inline="always")
def _edge_weight_gradient(
    attr: np.ndarray, terms: np.ndarray, e: int, share: np.ndarray, grad_edge_weight: np.ndarray
) -> None:
    """``grad_edge_weight[w, d] += attr[a, d] * share`` for every feature ``d``, ``a, w = terms[e]``."""
    a, w = terms[e, 0], terms[e, 1]
    for d in range(attr.shape[1]):
        value = attr[a, d]
        for c in range(share.shape[0]):
            grad_edge_weight[w, d, c] += value * share[c]


@numba.njit(cache=True)
def relational_max_backward(
    grad_out: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    wins: np.ndarray,
    num_relations: int,
    stride: int,
    ties: bool,
    grad_rows: np.ndarray,
    attr: np.ndarray,
    terms: np.ndarray,
    grad_edge_weight: np.ndarray,
) -> None:
    """Gradient of :func:`relational_max_forward` w.r.t. ``rows`` from the ``wins`` it recorded:
    each row equal to its segment's maximum gets the output gradient of the segment's vertex,
    divided by the number of such rows when ``ties`` (PyTorch's rule; a NaN maximum passes none).

    Reads the ``(E, C)`` bytes of ``wins`` where the rows-based :func:`relational_max_backward_ties`
    reads the rows and the maxima (about five times as many bytes, long out of cache by then). The
    gradients of one row are added in the order of the edges, as there.

    :param grad_out: ``(M, C)`` output gradient
    :param source: ``(E,)`` row read by each edge (no repeated ``(source, target)`` pair)
    :param target: ``(E,)`` segment of each edge, sorted
    :param wins: ``(E, C)`` the forward pass's record
    :param num_relations: ``R``
    :param stride: rows per vertex
    :param ties: some maximum is tied or NaN (the record holds more or fewer ones than the
        non-empty (segment, channel) pairs)
    :param grad_rows: ``(M * stride, C)``, written (every row: no need to zero it first)
    :param attr: ``(A, D)`` the forward pass's edge features, or ``(0, 0)`` for none
    :param terms: ``(E, 2)`` the forward pass's rows of ``attr`` and of the weights per edge
    :param grad_edge_weight: ``(K * R, D, C)`` zeros, the edge features' weights' gradient added
        (``attr[a, d]`` times each edge's share), or ``(0, 0, 0)``
    """
    _root_gradients(grad_out, num_relations, stride, grad_rows)
    channels = grad_out.shape[1]
    has_edges = attr.shape[0] > 0
    share = np.empty(channels, grad_out.dtype)
    if not ties:
        for e in range(source.shape[0]):
            s, i = source[e], target[e] // num_relations
            if has_edges:
                for c in range(channels):
                    share[c] = grad_out[i, c] if wins[e, c] else 0.0
                    grad_rows[s, c] += share[c]
                _edge_weight_gradient(attr, terms, e, share, grad_edge_weight)
                continue
            for c in range(channels):  # branch-free: the channel loop vectorizes
                grad_rows[s, c] += grad_out[i, c] if wins[e, c] else 0.0
        return
    counts = np.zeros_like(grad_out[0])  # float: the division stays in the rows' precision
    start = 0
    for e in range(source.shape[0]):
        t = target[e]
        if e + 1 < source.shape[0] and target[e + 1] == t:
            continue
        counts[:] = 0.0  # the segment of edges start..e is complete: split among its maxima
        for f in range(start, e + 1):
            for c in range(channels):
                counts[c] += wins[f, c]
        i = t // num_relations
        for f in range(start, e + 1):
            s = source[f]
            for c in range(channels):
                if wins[f, c]:
                    share[c] = grad_out[i, c] / counts[c]
                    grad_rows[s, c] += share[c]
                else:
                    share[c] = 0.0
            if has_edges:
                _edge_weight_gradient(attr, terms, f, share, grad_edge_weight)
        start = e + 1


@numba.njit(cache=True, error_model="numpy")
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
    """Gradient of :func:`relational_max_forward` w.r.t. ``rows`` from the rows and the maxima (edges
    in any order; ``SegmentMax``): each row equal to its segment's maximum gets the output
    gradient divided by the number of such rows (PyTorch's rule; a NaN maximum passes none).

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
    # Branch-free channel loops (a select, not a branch), which vectorize: 2x faster (critic max
    # pooling, batch 256). A row that is not a maximum adds +0.0, which leaves every sum unchanged
    # bit for bit (the rows start at +0.0, so no sum is -0.0); error_model="numpy" lets the
    # discarded x / 0 of a channel whose maximum is NaN (no row equals it: count 0) give inf or
    # NaN instead of raising, and spares the zero test per division.
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        for c in range(channels):
            counts[t, c] += 1.0 if rows[s, c] == maxima[t, c] else 0.0
    _root_gradients(grad_out, num_relations, stride, grad_rows)
    for e in range(source.shape[0]):
        s, t = source[e], target[e]
        i = t // num_relations
        for c in range(channels):
            share = grad_out[i, c] / counts[t, c]
            grad_rows[s, c] += share if rows[s, c] == maxima[t, c] else 0.0


@numba.njit(cache=True)
def segment_order(target: np.ndarray, source: np.ndarray, num_segments: int, merge: bool) -> tuple[np.ndarray, int]:
    """The edges of a layout sorted by segment: a counting sort over the bounded segment ids
    (``O(E + S)``, where ``torch.unique`` / ``argsort`` sort 64-bit keys).

    :param target: ``(E,)`` segment of each edge, in ``[0, num_segments)``
    :param source: ``(E,)`` row read by each edge
    :param num_segments: ``S``
    :param merge: sort each segment's edges by ``source`` and keep one of each repeated
        ``(target, source)`` pair: the order of ``torch.unique(target * rows + source)``; else keep
        every edge in its input order within its segment (``argsort(target, stable=True)``)
    :return: the edges' indices in that order, and the number of non-empty segments
    """
    starts = np.zeros(num_segments + 1, np.int64)
    for e in range(target.shape[0]):
        starts[target[e] + 1] += 1
    nonempty = 0
    for s in range(num_segments):
        nonempty += starts[s + 1] > 0
        starts[s + 1] += starts[s]
    order = np.empty(target.shape[0], np.int64)
    position = starts[:-1].copy()
    for e in range(target.shape[0]):
        order[position[target[e]]] = e
        position[target[e]] += 1
    if not merge:
        return order, nonempty
    kept = 0
    for s in range(num_segments):
        lo, hi = starts[s], starts[s + 1]
        # Insertion sort by source: segments hold a few edges (one per in-neighbour); long ones
        # take numpy's sort.
        if hi - lo > 32:
            segment = order[lo:hi]
            order[lo:hi] = segment[np.argsort(source[segment], kind="mergesort")]
        else:
            for i in range(lo + 1, hi):
                edge, j = order[i], i - 1
                while j >= lo and source[order[j]] > source[edge]:
                    order[j + 1] = order[j]
                    j -= 1
                order[j + 1] = edge
        for i in range(lo, hi):  # repeated pairs are adjacent now: keep the first
            if i == lo or source[order[i]] != source[order[i - 1]]:
                order[kept] = order[i]
                kept += 1
    return order[:kept], nonempty
