"""Padded observations <-> one disjoint graph, by index arithmetic."""

import numpy as np
import torch
from torch_geometric.data import Batch, Data

from sb3_graph import GraphSpace
from sb3_graph.common.batching import (
    DerivedIndexCache,
    as_graph_batch,
    batch_to_padded,
    gather_vertex_values,
    padded_to_batch,
)

torch.set_num_threads(1)


def sample_batch(space: GraphSpace, size: int) -> list[dict[str, np.ndarray]]:
    graphs = [space.sample() for _ in range(size)]
    graphs[1] = space.encode(np.zeros((0, space.node_features)))  # an empty graph
    return graphs


def stack(graphs, as_float=True):
    return {
        key: torch.as_tensor(np.stack([g[key] for g in graphs])).float()
        if as_float
        else torch.as_tensor(np.stack([g[key] for g in graphs]))
        for key in graphs[0]
    }


def test_matches_pyg_batch():
    space = GraphSpace(max_nodes=10, node_features=3, max_edges=30, num_relations=3, seed=1)
    graphs = sample_batch(space, 16)
    # SB3's preprocessing hands every entry over as float.
    batch = padded_to_batch(stack(graphs, as_float=True))
    decoded = [space.decode(g) for g in graphs]
    reference = Batch.from_data_list(
        [
            Data(x=torch.as_tensor(x), edge_index=torch.as_tensor(ei), edge_type=torch.as_tensor(et))
            for x, ei, et in decoded
        ]
    )
    torch.testing.assert_close(batch.x, reference.x)
    torch.testing.assert_close(batch.edge_index, reference.edge_index)
    torch.testing.assert_close(batch.edge_type, reference.edge_type)
    torch.testing.assert_close(batch.batch, reference.batch)
    assert batch.num_graphs == 16 and batch.max_nodes == 10
    assert batch.edge_index.dtype == torch.long and batch.edge_type.dtype == torch.long
    expected_slots = np.concatenate([np.arange(len(x)) for x, _, _ in decoded])
    np.testing.assert_array_equal(batch.node_slot.numpy(), expected_slots)


def test_integer_inputs_and_unbatched():
    space = GraphSpace(max_nodes=6, node_features=2, max_edges=8, num_relations=2, seed=2)
    graphs = sample_batch(space, 4)
    a = padded_to_batch(stack(graphs, as_float=False))
    b = padded_to_batch(stack(graphs, as_float=True))
    for t1, t2 in zip(a[:5], b[:5]):
        torch.testing.assert_close(t1, t2)
    single = padded_to_batch({k: torch.as_tensor(v) for k, v in graphs[0].items()})
    assert single.num_graphs == 1
    assert single.num_nodes == space.num_nodes(graphs[0])
    assert as_graph_batch(single) is single


def test_scatter_and_gather_round_trip():
    space = GraphSpace(max_nodes=5, node_features=1, max_edges=4, seed=3)
    graphs = sample_batch(space, 8)
    batch = padded_to_batch(stack(graphs))
    values = torch.randn(batch.num_nodes, requires_grad=True)
    padded = batch_to_padded(values, batch)
    assert padded.shape == (8, 5)
    mask = stack(graphs)["node_mask"].bool()
    assert torch.all(padded[~mask] == 0)
    torch.testing.assert_close(gather_vertex_values(padded, batch), values)
    padded.sum().backward()
    torch.testing.assert_close(values.grad, torch.ones_like(values))
    assert batch_to_padded(torch.randn(batch.num_nodes, 3), batch).shape == (8, 5, 3)


def test_derived_index_cache():
    cache = DerivedIndexCache(size=2)
    a, b = torch.arange(5), torch.arange(5)
    calls = []

    def compute(tag):
        calls.append(tag)
        return tag

    assert cache.get((a,), ("x",), lambda: compute(1)) == 1
    assert cache.get((a,), ("x",), lambda: compute(2)) == 1  # hit: same tensor, same key
    assert cache.get((b,), ("x",), lambda: compute(3)) == 3  # equal values, another tensor: miss
    assert cache.get((a,), ("y",), lambda: compute(4)) == 4  # other key: miss
    a.add_(1)  # in-place change bumps the version: miss
    assert cache.get((a,), ("y",), lambda: compute(5)) == 5
    assert calls == [1, 3, 4, 5] and len(cache._entries) == 2  # least recently used evicted
    with torch.inference_mode():
        c = torch.arange(3)
    assert cache.get((c,), ("x",), lambda: compute(6)) == 6
    assert cache.get((c,), ("x",), lambda: compute(7)) == 7  # inference tensors are never cached


def test_padded_batch_is_converted_once():
    space = GraphSpace(max_nodes=6, node_features=2, max_edges=10, num_relations=2, seed=0)
    obs = stack(sample_batch(space, 4))
    first = as_graph_batch(obs)
    assert as_graph_batch(dict(obs)) is first  # same tensors
    obs["x"].mul_(2.0)  # changed in place: converted again
    second = as_graph_batch(obs)
    assert second is not first
    torch.testing.assert_close(second.x, padded_to_batch(obs).x)


def test_edges_at_padded_slots_and_fractional_masks_are_rejected():
    import pytest

    space = GraphSpace(max_nodes=5, node_features=2, max_edges=4, num_relations=2)
    graphs = [space.encode(np.ones((3, 2)), np.array([[0, 1], [1, 2]])), space.encode(np.ones((2, 2)))]
    obs = stack(graphs)
    padded_to_batch(obs)
    bad = {k: v.clone() for k, v in obs.items()}
    bad["edge_index"][0, 1, 1] = 4.0  # graph 0's second edge into padded slot 4
    with pytest.raises(ValueError, match=r"padded vertex slot \(graph 0: 1 -> 4\)"):
        padded_to_batch(bad)
    bad = {k: v.clone() for k, v in obs.items()}
    bad["edge_index"][0, 0, 0] = 7.0
    with pytest.raises(ValueError, match="outside"):
        padded_to_batch(bad)
    bad = {k: v.clone() for k, v in obs.items()}
    bad["node_mask"] = bad["node_mask"] * 0.5
    with pytest.raises(ValueError, match="VecNormalize"):
        padded_to_batch(bad)
