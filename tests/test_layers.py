"""RelationalMaxConv: the paper's max over transformed messages, per relation, summed over relations."""

import numpy as np
import pytest
import torch
from torch_geometric.nn import RGCNConv
from torch_geometric.utils import scatter

from sb3_graph.common.batching import derived_indices
from sb3_graph.common.layers import (
    RelationalMaxConv,
    compact_layout,
    relational_conv,
    relational_layout,
    segment_max,
    use_compact_rows,
    use_compiled_kernels,
)
from sb3_graph.common.layers.relational_max_conv import _fused_weights

torch.set_num_threads(1)


def dense_reference(conv: RelationalMaxConv, x, edge_index, edge_type, reduce: str) -> torch.Tensor:
    """h_i' = W_0 x_i + b + sum_r reduce_{j in N_r(i)} W_r x_j, computed edge by edge."""
    out = conv.root(x) + conv.bias
    for i in range(x.size(0)):
        for r in range(conv.num_relations):
            sources = edge_index[0][(edge_index[1] == i) & (edge_type == r)]
            if len(sources) == 0:
                continue
            messages = x[sources] @ conv.weight[r]
            if reduce == "max":
                out[i] += messages.max(dim=0).values
            elif reduce == "mean":
                out[i] += messages.mean(dim=0)
            else:
                out[i] += messages.sum(dim=0)
    return out


def random_graph(n=7, e=20, relations=3, features=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, features, generator=g)
    edge_index = torch.randint(0, n, (2, e), generator=g)
    edge_type = torch.randint(0, relations, (e,), generator=g)
    return x, edge_index, edge_type


@pytest.mark.parametrize("aggr", ["max", "mean", "sum"])
def test_matches_dense_computation(aggr):
    torch.manual_seed(0)
    x, edge_index, edge_type = random_graph()
    conv = RelationalMaxConv(5, 4, num_relations=3, aggr=aggr)
    expected = dense_reference(conv, x, edge_index, edge_type, aggr)
    torch.testing.assert_close(conv(x, edge_index, edge_type), expected)


def test_differs_from_rgcn_max():
    # Two in-neighbours whose raw max and transformed max disagree: W = -1 flips the order.
    x = torch.tensor([[1.0], [2.0], [0.0]])
    edge_index = torch.tensor([[0, 1], [2, 2]])
    edge_type = torch.tensor([0, 0])
    ours = RelationalMaxConv(1, 1, num_relations=1, aggr="max")
    rgcn = RGCNConv(1, 1, num_relations=1, aggr="max")
    with torch.no_grad():
        for conv in (ours, rgcn):
            conv.weight.fill_(-1.0)
            conv.bias.zero_()
        ours.root.weight.fill_(0.0)
        rgcn.root.fill_(0.0)
    # Ours: max(-1, -2) = -1. RGCNConv: -1 * max(1, 2) = -2.
    assert ours(x, edge_index, edge_type)[2].item() == pytest.approx(-1.0)
    assert rgcn(x, edge_index, edge_type)[2].item() == pytest.approx(-2.0)
    # The same on random data with copied weights.
    x, edge_index, edge_type = random_graph(relations=2)
    ours = RelationalMaxConv(5, 4, num_relations=2)
    rgcn = RGCNConv(5, 4, num_relations=2, aggr="max")
    with torch.no_grad():
        rgcn.weight.copy_(ours.weight)
        rgcn.root.copy_(ours.root.weight.T)
        rgcn.bias.copy_(ours.bias)
    assert not torch.allclose(ours(x, edge_index, edge_type), rgcn(x, edge_index, edge_type))


def test_vertex_without_incoming_edges_is_dense_layer():
    x, _, _ = random_graph()
    conv = RelationalMaxConv(5, 4, num_relations=2)
    empty = torch.zeros(2, 0, dtype=torch.long)
    torch.testing.assert_close(conv(x, empty, torch.zeros(0, dtype=torch.long)), conv.root(x) + conv.bias)
    # Vertex 1 only sends: its output ignores the edge.
    out = conv(x, torch.tensor([[1], [0]]), torch.tensor([1]))
    torch.testing.assert_close(out[1], conv.root(x[1]) + conv.bias)
    assert not torch.allclose(out[0], conv.root(x[0]) + conv.bias)


def test_negative_messages_are_not_clipped_by_empty_slots():
    # A single all-negative message must stay negative (empty-slot zeros must not enter the max).
    conv = RelationalMaxConv(1, 1, num_relations=2, bias=False, root_weight=False)
    with torch.no_grad():
        conv.weight.fill_(1.0)
    out = conv(torch.tensor([[-3.0], [0.0]]), torch.tensor([[0], [1]]), torch.tensor([1]))
    assert out[1].item() == pytest.approx(-3.0)


def test_bad_arguments():
    with pytest.raises(ValueError, match="aggr"):
        RelationalMaxConv(2, 2, 1, aggr="min")
    with pytest.raises(ValueError, match="num_relations"):
        RelationalMaxConv(2, 2, 0)


def pyg_reference_conv(conv: RelationalMaxConv, x, edge_index, edge_type) -> torch.Tensor:
    """The layer as first written with PyG's scatter: one matmul, messages x W_r per edge, reduced
    into N * R slots ``target * R + relation`` (autograd through ``scatter_reduce``)."""
    n, r, out = x.size(0), conv.num_relations, conv.out_channels
    transformed = (x @ conv.weight.permute(1, 0, 2).reshape(conv.in_channels, r * out)).view(n * r, out)
    messages = transformed[edge_index[0] * r + edge_type]
    aggregated = scatter(messages, edge_index[1] * r + edge_type, dim=0, dim_size=n * r, reduce=conv.aggr)
    result = aggregated.view(n, r, out).sum(dim=1)
    if conv.root is not None:
        result = result + conv.root(x)
    return result if conv.bias is None else result + conv.bias


def tie_graph(n=40, e=200, relations=3, features=6, seed=0):
    """Random graph with repeated edges and two identical vertices sending to the same target
    (exact ties in the maximum), and isolated vertices."""
    x, edge_index, edge_type = random_graph(n, e, relations, features, seed)
    x[5] = x[7]
    keep = (edge_index[1] != 9) | (edge_type != 1)  # 5 and 7 are the only relation-1 senders to 9
    edge_index, edge_type = edge_index[:, keep], edge_type[keep]
    edge_index = torch.cat((edge_index, edge_index[:, :40], torch.tensor([[5, 7], [9, 9]])), dim=1)
    edge_type = torch.cat((edge_type, edge_type[:40], torch.tensor([1, 1])))
    return x, edge_index, edge_type


def outputs_and_gradients(conv, forward, x, edge_index, edge_type, grad):
    conv.zero_grad()
    x = x.clone().requires_grad_(True)
    out = forward(conv, x, edge_index, edge_type)
    out.backward(grad)
    return [out.detach(), x.grad] + [p.grad.clone() for p in conv.parameters()]


@pytest.mark.parametrize("aggr", ["max", "mean", "sum"])
@pytest.mark.parametrize("root_weight,bias", [(True, True), (False, True), (True, False), (False, False)])
def test_matches_pyg_reference_with_gradients(aggr, root_weight, bias):
    # The fused aggregation (custom backward, deduplicated edges, cached layout) computes the same
    # function and the same gradients as PyG's scatter, ties split evenly included.
    torch.manual_seed(0)
    conv = RelationalMaxConv(6, 5, num_relations=3, aggr=aggr, root_weight=root_weight, bias=bias)
    x, edge_index, edge_type = tie_graph()
    grad = torch.randn(x.size(0), 5)
    ours = outputs_and_gradients(conv, lambda c, *a: c(*a), x, edge_index, edge_type, grad)
    reference = outputs_and_gradients(conv, pyg_reference_conv, x, edge_index, edge_type, grad)
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b)


def test_segment_max_matches_scatter_max():
    g = torch.Generator().manual_seed(0)
    values = torch.randn(30, 4, generator=g)
    values[3] = values[4]  # tied maxima where both land in one segment
    # Gathered rows: segment 13 reads the two equal rows, segment 14 one row twice; 12, 15 empty.
    source = torch.cat((torch.randint(0, 30, (50,), generator=g), torch.tensor([3, 4, 8, 8])))
    target = torch.cat((torch.randint(0, 12, (50,), generator=g), torch.tensor([13, 13, 14, 14])))
    # All rows in order: rows 3 and 4 alone in segment 13.
    in_order = torch.randint(0, 12, (30,), generator=g)
    in_order[3] = in_order[4] = 13
    grad = torch.randn(16, 4, generator=g)
    for src, tgt in ((source, target), (None, in_order)):
        v1, v2 = values.clone().requires_grad_(True), values.clone().requires_grad_(True)
        ours = segment_max(v1, src, tgt, 16, len(torch.unique(tgt)))
        reference = scatter(v2 if src is None else v2[src], tgt, dim=0, dim_size=16, reduce="max")
        torch.testing.assert_close(ours, reference)
        assert torch.all(ours[[12, 15]] == 0)
        ours.backward(grad)
        reference.backward(grad)
        torch.testing.assert_close(v1.grad, v2.grad)
    torch.testing.assert_close(v1.grad[3], grad[13] / 2)  # the tie is split evenly


@pytest.mark.parametrize("aggr", ["max", "mean"])
def test_stacked_convolutions_equal_separate_ones(aggr):
    torch.manual_seed(0)
    convs = [RelationalMaxConv(6, 5, num_relations=3, aggr=aggr) for _ in range(3)]
    x, edge_index, edge_type = tie_graph()
    inputs = torch.randn(3, x.size(0), 6, requires_grad=True)
    stacked = relational_conv(convs, inputs, edge_index, edge_type)
    separate = torch.stack([conv(inputs[k], edge_index, edge_type) for k, conv in enumerate(convs)])
    torch.testing.assert_close(stacked, separate)
    grad = torch.randn_like(stacked)
    stacked_grads = torch.autograd.grad(stacked, [inputs, *convs[1].parameters()], grad)
    separate_grads = torch.autograd.grad(separate, [inputs, *convs[1].parameters()], grad)
    for a, b in zip(stacked_grads, separate_grads, strict=True):
        torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="K, N"):
        relational_conv(convs, x, edge_index, edge_type)


@pytest.mark.parametrize("root_weight", [True, False])
@pytest.mark.parametrize("bias", [True, False])
def test_fused_weights_of_one_convolution_equal_the_stacked_ones(root_weight, bias):
    """One convolution's fused weight and bias (built directly) are copy 0 of the stacked ones, bit for
    bit, and so are their gradients; without ``with_bias`` no bias is built."""
    torch.manual_seed(0)
    conv = RelationalMaxConv(6, 5, num_relations=3, root_weight=root_weight, bias=bias)
    weight, fused_bias = _fused_weights([conv], stacked=False)
    stacked_weight, stacked_bias = _fused_weights([conv], stacked=True)
    assert torch.equal(weight, stacked_weight[0])
    assert (fused_bias is None) == (not bias) and (not bias or torch.equal(fused_bias, stacked_bias[0, 0]))
    assert _fused_weights([conv], stacked=False, with_bias=False)[1] is None
    grad = torch.randn_like(weight)
    ours = torch.autograd.grad(weight, list(conv.parameters()), grad, allow_unused=True)
    theirs = torch.autograd.grad(stacked_weight[0], list(conv.parameters()), grad, allow_unused=True)
    for a, b in zip(ours, theirs, strict=True):
        assert (a is None and b is None) or torch.equal(a, b)


def test_layout_is_derived_once_per_batch():
    x, edge_index, edge_type = tie_graph()
    first = relational_layout(edge_index, edge_type, x.size(0), 3, stride=4)
    assert relational_layout(edge_index, edge_type, x.size(0), 3, stride=4) is first
    # Repeated edges are dropped for the maximum; targets are sorted.
    assert len(first.source) < edge_index.size(1)
    assert torch.all(first.target[1:] >= first.target[:-1])
    assert first.num_nonempty == len(torch.unique(edge_index[1] * 3 + edge_type))
    # An equal but distinct tensor, or an in-place change, gives a fresh layout.
    assert relational_layout(edge_index.clone(), edge_type, x.size(0), 3, stride=4) is not first
    edge_index[0, 0] = (edge_index[0, 0] + 1) % x.size(0)
    assert relational_layout(edge_index, edge_type, x.size(0), 3, stride=4) is not first


@pytest.mark.parametrize("aggr", ["max", "mean", "sum"])
@pytest.mark.parametrize("edge_dim", [0, 2])
def test_backward_on_a_batch_without_vertices(aggr, edge_dim):
    conv = RelationalMaxConv(4, 3, num_relations=2, aggr=aggr, edge_dim=edge_dim)
    x = torch.zeros(0, 4, requires_grad=True)
    edges = torch.zeros(2, 0, dtype=torch.long)
    edge_attr = torch.zeros(0, edge_dim) if edge_dim else None
    out = conv(x, edges, torch.zeros(0, dtype=torch.long), edge_attr)
    assert out.shape == (0, 3)
    out.sum().backward()  # used to fail: grad_out.reshape(0, -1)
    assert x.grad.shape == (0, 4) and torch.all(conv.weight.grad == 0)


def test_edges_naming_unknown_relations_or_vertices_are_rejected():
    conv = RelationalMaxConv(2, 2, num_relations=2)
    x = torch.randn(3, 2)
    with pytest.raises(ValueError, match="num_relations=2"):
        conv(x, torch.tensor([[0], [1]]), torch.tensor([2]))
    with pytest.raises(ValueError, match=r"outside \[0, 3\)"):
        conv(x, torch.tensor([[0], [3]]), torch.tensor([0]))


def edge_reference(conv: RelationalMaxConv, x, edge_index, edge_type, edge_attr, reduce: str) -> torch.Tensor:
    """h_i' = W_0 x_i + b + sum_r reduce_{j -> i of relation r} (W_r x_j + U_r e_ji), edge by edge."""
    out = conv.root(x) + conv.bias
    for i in range(x.size(0)):
        for r in range(conv.num_relations):
            chosen = (edge_index[1] == i) & (edge_type == r)
            if not chosen.any():
                continue
            messages = x[edge_index[0][chosen]] @ conv.weight[r] + edge_attr[chosen] @ conv.edge_weight[r]
            reducers = {"max": lambda m: m.max(dim=0).values, "mean": lambda m: m.mean(0), "sum": lambda m: m.sum(0)}
            out[i] += reducers[reduce](messages)
    return out


@pytest.mark.parametrize("aggr", ["max", "mean", "sum"])
def test_edge_features_enter_each_message_before_the_aggregation(aggr):
    torch.manual_seed(0)
    x, edge_index, edge_type = tie_graph(n=12, e=40, relations=3, features=5)
    edge_attr = torch.randn(edge_index.size(1), 2)
    conv = RelationalMaxConv(5, 4, num_relations=3, aggr=aggr, edge_dim=2)
    out = conv(x, edge_index, edge_type, edge_attr)
    torch.testing.assert_close(out, edge_reference(conv, x, edge_index, edge_type, edge_attr, aggr))
    # Changing one edge's features changes its target's output only.
    changed = edge_attr.clone()
    changed[0] += 1.0
    target = int(edge_index[1, 0])
    delta = (conv(x, edge_index, edge_type, changed) - out).abs().sum(dim=1)
    assert delta[target] > 0 and torch.all(delta[torch.arange(12) != target] == 0)
    # Gradients reach the edge weights and the edge features.
    attr = edge_attr.clone().requires_grad_(True)
    conv(x, edge_index, edge_type, attr).sum().backward()
    assert conv.edge_weight.grad.abs().sum() > 0 and attr.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="edge_attr"):
        conv(x, edge_index, edge_type)


def test_stacked_convolutions_with_edge_features_equal_separate_ones():
    torch.manual_seed(0)
    convs = [RelationalMaxConv(6, 5, num_relations=3, edge_dim=2) for _ in range(2)]
    x, edge_index, edge_type = tie_graph()
    edge_attr = torch.randn(edge_index.size(1), 2)
    inputs = torch.randn(2, x.size(0), 6)
    stacked = relational_conv(convs, inputs, edge_index, edge_type, edge_attr)
    separate = torch.stack([c(inputs[k], edge_index, edge_type, edge_attr) for k, c in enumerate(convs)])
    torch.testing.assert_close(stacked, separate)


@pytest.mark.parametrize("root_weight, bias", [(True, True), (False, True), (True, False)])
def test_inference_weights_follow_every_parameter_change(root_weight, bias):
    """Without autograd the fused weights are kept between calls, and renewed when a parameter is
    updated in place (optimizer step, load_state_dict), replaced, or converted (.double())."""
    torch.manual_seed(0)
    conv = RelationalMaxConv(5, 4, num_relations=3, root_weight=root_weight, bias=bias)
    x, edge_index, edge_type = random_graph()

    def check(x):
        previous = use_compact_rows(False)  # the fused weights with autograd too: equal bit for bit
        try:
            expected = conv(x, edge_index, edge_type)  # autograd: fused on every call
        finally:
            use_compact_rows(previous)
        with torch.no_grad():
            torch.testing.assert_close(conv(x, edge_index, edge_type), expected, rtol=0, atol=0)
        with torch.inference_mode():
            torch.testing.assert_close(conv(x, edge_index, edge_type), expected, rtol=0, atol=0)

    check(x)
    assert conv.inference_weights()[0] is conv.inference_weights()[0]
    optimizer = torch.optim.SGD(conv.parameters(), lr=0.1)
    conv(x, edge_index, edge_type).sum().backward()
    optimizer.step()
    check(x)
    other = RelationalMaxConv(5, 4, num_relations=3, root_weight=root_weight, bias=bias)
    conv.load_state_dict(other.state_dict())
    check(x)
    conv.weight = torch.nn.Parameter(torch.randn(3, 5, 4))
    check(x)
    conv.double()
    check(x.double())


@pytest.mark.parametrize("copies", [1, 2])
def test_forward_only_layout_gives_the_same_maxima(copies):
    """Without autograd the maximum runs on every edge, unsorted and with repeats (a forward-only
    layout): the same values as with autograd, bit for bit (one convolution: to float rounding, as
    autograd computes only the relation rows that edges read, ``use_compact_rows``); the two
    layouts of one batch are cached apart, so a later pass with autograd gets the full one and its
    gradients."""
    torch.manual_seed(0)
    convs = [RelationalMaxConv(6, 5, num_relations=3) for _ in range(copies)]
    x, edge_index, edge_type = tie_graph()
    inputs = torch.randn(copies, x.size(0), 6) if copies > 1 else torch.randn(x.size(0), 6)
    with torch.no_grad():
        forward_only = relational_conv(convs, inputs, edge_index, edge_type)
        light = relational_layout(edge_index, edge_type, x.size(0), 3, stride=4, copies=copies)
    assert light.source_order is None and len(light.source) == copies * edge_index.size(1)
    full = relational_layout(edge_index, edge_type, x.size(0), 3, stride=4, copies=copies)
    assert full.target_vertex is not None and len(full.source) < copies * edge_index.size(1)
    inputs.requires_grad_(True)
    with_grad = relational_conv(convs, inputs, edge_index, edge_type)
    exact = {"rtol": 0, "atol": 0} if copies > 1 else {}
    torch.testing.assert_close(forward_only, with_grad.detach(), **exact)
    with_grad.sum().backward()  # the full layout: the gradient of every term reaches the inputs
    # d sum(out) / dx, summed over vertices, whichever source wins a maximum (or shares a tie): every vertex's root
    # term, plus one unit per channel of each (target, relation) maximum that has a sender
    pairs = {(int(t), int(r)) for t, r in zip(edge_index[1], edge_type)}
    expected = torch.stack([
        x.size(0) * conv.root.weight.sum(0) + sum(conv.weight[r].sum(1) for _, r in pairs) for conv in convs
    ]).detach()  # fmt: skip
    torch.testing.assert_close(inputs.grad.sum(-2), expected if copies > 1 else expected[0])


def conv_outputs_and_gradients(convs, inputs, edge_index, edge_type, grad, compiled):
    """Outputs, input gradient and parameter gradients of :func:`relational_conv`, with the
    compiled kernels on or off (fresh layouts each time)."""
    previous = use_compiled_kernels(compiled)
    try:
        derived_indices.clear()
        for conv in convs:
            conv.zero_grad()
        inputs = inputs.clone().requires_grad_(True)
        out = relational_conv(convs, inputs, edge_index, edge_type)
        out.backward(grad)
        with torch.no_grad():
            derived_indices.clear()
            no_grad = relational_conv(convs, inputs, edge_index, edge_type)
        return [out.detach(), no_grad, inputs.grad] + [p.grad.clone() for c in convs for p in c.parameters()]
    finally:
        use_compiled_kernels(previous)


@pytest.mark.parametrize("graph", ["random", "ties", "zeros"])
@pytest.mark.parametrize("root_weight,bias", [(True, True), (False, True), (False, False)])
@pytest.mark.parametrize("copies", [1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_kernels_match_the_pytorch_formulation(graph, root_weight, bias, copies, dtype):
    """The numba kernels (CPU) against the PyTorch formulation they replace: the same outputs and
    gradients to float rounding (the kernel adds the bias after the matmul, where ``addmm`` adds it
    inside), including exact ties (repeated rows, and rows of zeros as after a dead ReLU); with and
    without autograd the kernels' outputs are equal bit for bit."""
    torch.manual_seed(0)
    convs = [
        RelationalMaxConv(6, 5, num_relations=3, root_weight=root_weight, bias=bias).to(dtype) for _ in range(copies)
    ]
    if graph == "random":
        x, edge_index, edge_type = random_graph(60, 300, relations=3, features=6, seed=1)
    else:
        x, edge_index, edge_type = tie_graph()
    if graph == "zeros":
        x[::3] = 0.0
    x = x.to(dtype)
    inputs = x.expand(copies, -1, -1) + 0.1 * torch.randn(copies, *x.shape, dtype=dtype) if copies > 1 else x
    if copies > 1 and graph == "zeros":
        inputs[:, ::3] = 0.0
    grad = torch.randn(*inputs.shape[:-1], 5, dtype=dtype)
    compiled = conv_outputs_and_gradients(convs, inputs, edge_index, edge_type, grad, compiled=True)
    reference = conv_outputs_and_gradients(convs, inputs, edge_index, edge_type, grad, compiled=False)
    # With and without autograd: bit for bit, except one convolution without autograd, which keeps
    # its fused weights (inference_weights) where autograd computes compact rows.
    exact = {"rtol": 0, "atol": 0} if copies > 1 else {}
    torch.testing.assert_close(compiled[0], compiled[1], **exact)
    for a, b in zip(compiled, reference, strict=True):
        torch.testing.assert_close(a, b)


def test_compiled_kernels_split_ties_as_pytorch_does():
    # Two identical senders into one (target, relation) segment: each gets half the gradient.
    conv = RelationalMaxConv(2, 2, num_relations=1, root_weight=False, bias=False)
    x = torch.tensor([[1.0, -2.0], [1.0, -2.0], [0.5, 3.0]], requires_grad=True)
    edge_index = torch.tensor([[0, 1], [2, 2]])
    derived_indices.clear()
    out = conv(x, edge_index, torch.zeros(2, dtype=torch.long))
    out.backward(torch.ones_like(out))
    expected = conv.weight[0].sum(dim=1).detach() / 2
    torch.testing.assert_close(x.grad[0], expected)
    torch.testing.assert_close(x.grad[1], expected)
    assert torch.all(x.grad[2] == 0)


def test_compiled_kernels_can_be_switched_off():
    assert use_compiled_kernels(False) is True
    try:
        assert use_compiled_kernels(False) is False
    finally:
        use_compiled_kernels(True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_segment_max_equals_the_pytorch_formulation(dtype):
    """``segment_max`` over all rows in order (critic max pooling, edge-feature messages) in the
    kernels: the same maxima and gradients bit for bit, with ties (split evenly), a NaN row,
    rows of zeros, empty segments and segments in any order."""
    g = torch.Generator().manual_seed(0)
    values = torch.randn(40, 5, generator=g).to(dtype)
    values[3] = values[4]  # a tie in segment 13
    values[10:14] = 0.0  # rows of zeros, as after a dead ReLU: ties in segment 2
    values[20, 1] = float("nan")  # a NaN maximum passes no gradient
    target = torch.randint(0, 12, (40,), generator=g)
    target[3] = target[4] = 13
    target[10:14] = 2
    grad = torch.randn(16, 5, generator=g).to(dtype)
    results = []
    for compiled in (True, False):
        previous = use_compiled_kernels(compiled)
        try:
            v = values.clone().requires_grad_(True)
            out = segment_max(v, None, target, 16, len(torch.unique(target)))
            out.backward(grad)
            results.append((out.detach(), v.grad))
        finally:
            use_compiled_kernels(previous)
    (out, grad_values), (reference, reference_grad) = results
    torch.testing.assert_close(out, reference, rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(grad_values, reference_grad, rtol=0, atol=0)
    assert torch.all(out[[12, 14, 15]] == 0)
    torch.testing.assert_close(grad_values[3], grad[13] / 2)
    assert bool(torch.isnan(out[target[20], 1]))


@pytest.mark.parametrize(
    "stride,num_relations,rows,vertices", [(3, 2, 18, 6), (2, 2, 12, 6), (1, 1, 9, 4), (1, 1, 3, 7)]
)
@pytest.mark.parametrize("ties", [False, True])
def test_backward_kernels_write_every_row(stride, num_relations, rows, vertices, ties):
    """The backward kernels fill their output themselves (it comes from ``new_empty``): the same
    gradient into rows of NaN as into zeros, also where the output has more rows than the vertices'
    (max pooling: more vertices than graphs) or fewer (more graphs than vertices)."""
    from sb3_graph.common.layers import _max_kernel

    g = torch.Generator().manual_seed(0)
    values = torch.randn(rows, 4, generator=g)
    values[1] = values[0]  # a tie
    source = torch.arange(rows)
    source = source[source % stride < num_relations]  # edges read relation rows, never root rows
    target = torch.randint(0, vertices * num_relations, (len(source),), generator=g)
    target[1] = target[0]
    target, order = torch.sort(target, stable=True)
    source = source[order]
    maxima = torch.full((vertices * num_relations, 4), -torch.inf)
    maxima = maxima.scatter_reduce(0, target.unsqueeze(-1).expand(-1, 4), values[source], "amax")
    wins = (values[source] == maxima[target]).to(torch.uint8)
    grad_out = torch.randn(vertices, 4, generator=g)
    rows_based = (values.numpy(), source.numpy(), target.numpy(), maxima.numpy(), num_relations, stride)
    kernels = {
        "wins": lambda out: _max_kernel.relational_max_backward(
            grad_out.numpy(), source.numpy(), target.numpy(), wins.numpy(), num_relations, stride, ties, out,
            np.empty((0, 0), np.float32), np.empty((0, 2), np.int64), np.empty((0, 0, 0), np.float32),
        ),  # fmt: skip
        "rows": lambda out: _max_kernel.relational_max_backward_ties(grad_out.numpy(), *rows_based, out),
    }
    results = {}
    for name, kernel in kernels.items():
        outputs = []
        for fill in (0.0, float("nan")):
            grad_rows = torch.full((rows, 4), fill)
            kernel(grad_rows.numpy())
            outputs.append(grad_rows)
        assert not torch.isnan(outputs[1]).any()
        torch.testing.assert_close(outputs[1], outputs[0], rtol=0, atol=0)
        if stride > num_relations:  # each root row holds its vertex's output gradient
            torch.testing.assert_close(outputs[0].view(-1, stride, 4)[:, num_relations], grad_out)
        results[name] = outputs[0]
    if ties:  # the tie rule from the record equals the one from the rows and maxima
        torch.testing.assert_close(results["wins"], results["rows"], rtol=0, atol=0)


def test_compiled_kernels_with_a_nan_maximum_and_a_tie_in_one_batch():
    """A NaN maximum (no winner) and a tie (two winners) in one batch: the winners add up to one
    per (segment, channel), yet the tie must still be split (as PyTorch's ``scatter_reduce`` does)
    and the NaN pass none, in the kernels and in the PyTorch formulation (which split no tie here
    before issue #27's second round)."""
    conv = RelationalMaxConv(1, 1, num_relations=1, root_weight=False, bias=False)
    with torch.no_grad():
        conv.weight.fill_(1.0)
    # Vertex 2 reads the tied vertices 0 and 1; vertex 5 reads vertices 3 (NaN) and 4.
    x = torch.tensor([[1.0], [1.0], [0.0], [float("nan")], [2.0], [0.0]])
    edge_index = torch.tensor([[0, 1, 3, 4], [2, 2, 5, 5]])
    edge_type = torch.zeros(4, dtype=torch.long)
    grads = []
    for compiled in (True, False):
        previous = use_compiled_kernels(compiled)
        try:
            derived_indices.clear()
            inputs = x.clone().requires_grad_(True)
            conv(inputs, edge_index, edge_type).backward(torch.ones(6, 1))
            grads.append(inputs.grad)
        finally:
            use_compiled_kernels(previous)
    torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(grads[0][:2], torch.full((2, 1), 0.5))  # the tie is split
    assert torch.all(grads[0][3:5] == 0)  # the NaN maximum passes no gradient


def compact_graph(kind: str, n: int = 50, relations: int = 4):
    """Graphs for the compact relation rows: random, with ties, with isolated vertices and empty
    relations, or without edges."""
    if kind == "random":
        return random_graph(n, 240, relations=relations, features=6, seed=3)
    if kind == "ties":
        x, edge_index, edge_type = tie_graph(n=n, relations=relations)
        x[::4] = 0.0  # rows of zeros, as after a dead ReLU: ties in every segment they reach
        return x, edge_index, edge_type
    x, edge_index, edge_type = random_graph(n, 0 if kind == "no_edges" else 120, relations, features=6, seed=4)
    if kind == "sparse":  # relations 1 and 3 empty; vertices >= n // 2 neither send nor receive
        keep = (edge_type % 2 == 0) & (edge_index.max(dim=0).values < n // 2)
        edge_index, edge_type = edge_index[:, keep], edge_type[keep]
    return x, edge_index, edge_type


def compact_outputs_and_gradients(
    convs, inputs, edge_index, edge_type, grad, compact, needs, edge_attr=None, compiled=True
):
    """Outputs (with and without autograd), and the gradients of the inputs and parameters in
    ``needs`` ("x", "params"), with the compact relation rows on or off, or the compiled kernels
    off (the PyTorch formulation), on fresh layouts."""
    previous, previous_kernels = use_compact_rows(compact), use_compiled_kernels(compiled)
    try:
        derived_indices.clear()
        params = [p for c in convs for p in c.parameters()]
        for p in params:
            p.grad = None
            p.requires_grad_("params" in needs)
        inputs = inputs.clone().requires_grad_("x" in needs)
        out = relational_conv(convs, inputs, edge_index, edge_type, edge_attr)
        assert (type(out.grad_fn).__name__ == "_CompactRelationalConvBackward") == (compact and compiled)
        out.backward(grad)
        with torch.no_grad():
            derived_indices.clear()
            no_grad = relational_conv(convs, inputs, edge_index, edge_type, edge_attr)
        return [out.detach(), no_grad, inputs.grad] + [p.grad for p in params]
    finally:
        use_compact_rows(previous)
        use_compiled_kernels(previous_kernels)
        for c in convs:
            c.requires_grad_(True)


@pytest.mark.parametrize("kind", ["random", "ties", "sparse", "no_edges"])
@pytest.mark.parametrize("root_weight", [True, False])
@pytest.mark.parametrize("copies", [1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compact_rows_match_the_fused_matmul(kind, root_weight, copies, dtype):
    """Computing only the relation rows that some edge reads (``use_compact_rows``) gives the
    values and the gradients of x, the weights and the bias of the fused matmul over every row,
    to float rounding: on random graphs, exact ties, isolated vertices and empty relations, a
    batch without edges, one convolution and stacked ones (twin critics)."""
    torch.manual_seed(0)
    convs = [RelationalMaxConv(6, 5, num_relations=4, root_weight=root_weight).to(dtype) for _ in range(copies)]
    x, edge_index, edge_type = compact_graph(kind)
    x = x.to(dtype)
    inputs = x.expand(copies, -1, -1) + 0.1 * torch.randn(copies, *x.shape, dtype=dtype) if copies > 1 else x
    if kind == "ties" and copies > 1:
        inputs[:, ::4] = 0.0
    grad = torch.randn(*inputs.shape[:-1], 5, dtype=dtype)
    for needs in (("x", "params"), ("x",), ("params",)):
        compact = compact_outputs_and_gradients(convs, inputs, edge_index, edge_type, grad, True, needs)
        fused = compact_outputs_and_gradients(convs, inputs, edge_index, edge_type, grad, False, needs)
        assert all((a is None) == (b is None) for a, b in zip(compact, fused, strict=True))
        for a, b in zip(compact, fused, strict=True):
            if a is not None:
                torch.testing.assert_close(a, b)
    if kind == "sparse":  # the parameters' gradients of an empty relation are zeros, as fused
        assert all(torch.all(c.weight.grad[1] == 0) and torch.all(c.weight.grad[3] == 0) for c in convs)


def test_compact_layout_reads_only_the_senders_of_each_relation():
    x, edge_index, edge_type = compact_graph("sparse", n=20)
    derived_indices.clear()
    layout = compact_layout(edge_index, edge_type, 20, 4, stride=5, copies=2)
    offsets = layout.offsets
    for r in range(4):
        expected = torch.unique(edge_index[0][edge_type == r])
        torch.testing.assert_close(layout.senders[offsets[r] : offsets[r + 1]], expected)
    assert len(layout.rows) == 2 * offsets[-1] and len(layout.source) == len(layout.base.source)
    # Every edge reads a row of its own sender in its own copy.
    assert torch.equal(layout.rows[layout.source] % 20, layout.base.source % (20 * 5) // 5)
    assert torch.equal(layout.rows[layout.source] // 20, layout.base.target_vertex // 20)


@pytest.mark.parametrize("kind", ["random", "ties", "sparse", "no_edges", "repeated"])
@pytest.mark.parametrize("root_weight", [True, False])
@pytest.mark.parametrize("copies", [1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_edge_features_match_the_pytorch_formulation(kind, root_weight, copies, dtype):
    """A convolution with edge features on the compiled path (each message ``x_j W_r + e_ji U_r``
    formed in the kernels as they reduce) gives the values and the gradients of x and of every
    parameter, the edge weights included, of the PyTorch formulation to float rounding: random
    graphs, exact ties (zero rows and zero features), isolated vertices and empty relations, no
    edges, and repeated edges that carry their own features (each one its own message)."""
    torch.manual_seed(0)
    convs = [
        RelationalMaxConv(6, 5, num_relations=4, root_weight=root_weight, edge_dim=3).to(dtype) for _ in range(copies)
    ]
    x, edge_index, edge_type = compact_graph("random" if kind == "repeated" else kind)
    edge_attr = torch.randn(edge_index.size(1), 3, dtype=dtype)
    if kind == "ties":
        edge_attr[::2] = 0.0
    if kind == "repeated":  # every third edge twice, the copy with other features
        extra = torch.arange(0, edge_index.size(1), 3)
        edge_index = torch.cat((edge_index, edge_index[:, extra]), dim=1)
        edge_type = torch.cat((edge_type, edge_type[extra]))
        edge_attr = torch.cat((edge_attr, torch.randn(len(extra), 3, dtype=dtype)))
    x = x.to(dtype)
    inputs = x.expand(copies, -1, -1) + 0.1 * torch.randn(copies, *x.shape, dtype=dtype) if copies > 1 else x
    if kind == "ties" and copies > 1:
        inputs[:, ::4] = 0.0
    grad = torch.randn(*inputs.shape[:-1], 5, dtype=dtype)
    args = (convs, inputs, edge_index, edge_type, grad)
    for needs in (("x", "params"), ("x",), ("params",)):
        compiled = compact_outputs_and_gradients(*args, True, needs, edge_attr)
        reference = compact_outputs_and_gradients(*args, True, needs, edge_attr, compiled=False)
        assert all((a is None) == (b is None) for a, b in zip(compiled, reference, strict=True))
        for a, b in zip(compiled, reference, strict=True):
            if a is not None:
                torch.testing.assert_close(a, b)
    if kind == "sparse":  # the edge weights' gradients of an empty relation are zeros
        assert all(torch.all(c.edge_weight.grad[1] == 0) and torch.all(c.edge_weight.grad[3] == 0) for c in convs)


def test_edge_features_that_need_a_gradient_take_the_pytorch_formulation():
    """The kernels give no gradient to the edge features (observations need none): features that
    require one run the PyTorch formulation, and their gradient is the same as with the kernels off."""
    torch.manual_seed(0)
    conv = RelationalMaxConv(6, 5, num_relations=4, edge_dim=2)
    x, edge_index, edge_type = compact_graph("random")
    grads = []
    for compiled in (True, False):
        previous = use_compiled_kernels(compiled)
        try:
            attr = torch.randn(edge_index.size(1), 2, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
            out = conv(x, edge_index, edge_type, attr)
            assert type(out.grad_fn).__name__ != "_CompactRelationalConvBackward"
            out.sum().backward()
            grads.append(attr.grad)
        finally:
            use_compiled_kernels(previous)
    torch.testing.assert_close(grads[0], grads[1])
    # Without a gradient, the kernels: the same values.
    attr = attr.detach()
    out = conv(x, edge_index, edge_type, attr)
    assert type(out.grad_fn).__name__ == "_CompactRelationalConvBackward"
    previous = use_compiled_kernels(False)
    try:
        torch.testing.assert_close(out, conv(x, edge_index, edge_type, attr))
    finally:
        use_compiled_kernels(previous)


@pytest.mark.parametrize("edge_dim", [0, 2])
def test_large_batches_without_autograd_compute_only_the_rows_that_edges_read(edge_dim):
    """Without autograd a single convolution switches from the fused matmul over every relation
    row (without edge features) or the PyTorch formulation (with them), which are faster for a
    planner's few vertices, to the compact rows at 256 vertices (the target networks of a training
    batch): the same values to float rounding, and the compact layout is what it builds."""
    torch.manual_seed(0)
    conv = RelationalMaxConv(6, 5, num_relations=4, edge_dim=edge_dim)
    for n, compact_expected in ((40, False), (300, True)):
        x, edge_index, edge_type = random_graph(n, 5 * n, relations=4, features=6, seed=1)
        edge_attr = torch.randn(edge_index.size(1), edge_dim) if edge_dim else None
        outputs = []
        for compact in (True, False):
            previous = use_compact_rows(compact)
            try:
                derived_indices.clear()
                with torch.no_grad():
                    outputs.append(conv(x, edge_index, edge_type, edge_attr))
                built = any(key[1][0] == "compact" for key in derived_indices._entries)
                assert built == (compact and compact_expected)
            finally:
                use_compact_rows(previous)
        torch.testing.assert_close(outputs[0], outputs[1])
