"""GraphSpace: fixed-size padded graphs that gym and SB3 accept unchanged."""

import pickle

import numpy as np
import pytest

from sb3_graph import GraphSpace


@pytest.fixture
def space():
    return GraphSpace(max_nodes=5, node_features=3, max_edges=6, num_relations=2, seed=0)


def test_encode_decode_round_trip(space):
    x = np.arange(9, dtype=np.float32).reshape(3, 3)
    edge_index = np.array([[0, 2, 1], [1, 0, 2]])
    edge_type = np.array([1, 0, 1])
    obs = space.encode(x, edge_index, edge_type)
    assert obs in space
    assert obs["node_mask"].tolist() == [1, 1, 1, 0, 0]
    x2, ei2, et2 = space.decode(obs)
    np.testing.assert_array_equal(x2, x)
    np.testing.assert_array_equal(ei2, edge_index)
    np.testing.assert_array_equal(et2, edge_type)
    assert space.num_nodes(obs) == 3


def test_empty_and_isolated_graphs(space):
    empty = space.encode(np.zeros((0, 3)))
    assert empty in space and space.num_nodes(empty) == 0
    isolated = space.encode(np.zeros((2, 3)))
    assert space.num_nodes(isolated) == 2  # isolated vertices are real vertices


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(x=np.zeros((6, 3))), "max_nodes=5"),
        (dict(x=np.zeros((2, 3)), edge_index=np.zeros((2, 7), int)), "max_edges=6"),
        (dict(x=np.zeros((2, 3)), edge_index=np.array([[0], [2]])), "real vertices"),
        (dict(x=np.zeros((2, 3)), edge_index=np.array([[0], [1]]), edge_type=np.array([2])), "num_relations"),
        (dict(x=np.zeros((2, 4))), "node_features|shape"),
    ],
)
def test_encode_errors(space, kwargs, message):
    with pytest.raises(ValueError, match=message):
        space.encode(**kwargs)


def test_sample_and_contains(space):
    for _ in range(50):
        assert space.sample() in space
    obs = space.encode(np.zeros((2, 3)), np.array([[0], [1]]))
    bad = {k: v.copy() for k, v in obs.items()}
    bad["node_mask"][:] = [0, 1, 0, 0, 0]  # not canonical
    assert bad not in space
    bad = {k: v.copy() for k, v in obs.items()}
    bad["edge_index"][1, 0] = 3  # points at a padded vertex
    assert bad not in space
    assert {"x": obs["x"]} not in space


def test_constructor_errors_and_pickle(space):
    with pytest.raises(ValueError, match="max_nodes"):
        GraphSpace(max_nodes=0, node_features=1, max_edges=1)
    with pytest.raises(ValueError, match="num_relations"):
        GraphSpace(max_nodes=2, node_features=1, max_edges=1, num_relations=0)
    clone = pickle.loads(pickle.dumps(space))
    assert clone == space and hash(clone) == hash(space)
    assert clone != GraphSpace(max_nodes=5, node_features=3, max_edges=6, num_relations=3)
