"""RelationalMaxConv: the paper's max over transformed messages, per relation, summed over relations."""

import pytest
import torch
from torch_geometric.nn import RGCNConv

from sb3_graph.layers import RelationalMaxConv

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
