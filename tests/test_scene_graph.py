"""Graph input representation: features [s, v, d], same-lane and crossing edges."""

from __future__ import annotations

import numpy as np
import pytest

from envs.simulation.engine import Simulation
from envs.simulation.graph import (
    CROSSING,
    DEFAULT_S_SCALE,
    SAME_LANE,
    build_graph_batch,
    build_observation,
    edges,
    mahalanobis_matrix,
    node_features,
)
from envs.simulation.layouts import LAYOUT_NAMES, build_layout
from envs.simulation.scene import Scene
from sb3_graph.common.spaces import GraphSpace


def _sim(layout="4way", s_ref=25.0):
    return Simulation(build_layout(layout), s_ref=s_ref)


def _edge_set(edge_index, edge_type):
    return {(int(a), int(b), int(t)) for a, b, t in zip(edge_index[0], edge_index[1], edge_type)}


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_s_is_minus_s_ref_at_every_entry_and_zero_at_every_exit(layout):
    sim = _sim(layout, s_ref=30.0)
    lay = sim.layout
    routes = np.arange(lay.num_routes)
    sim.add(routes, np.ones(lay.num_routes), routes, arc=lay.entry_arc)
    np.testing.assert_allclose(sim.scene().s, -30.0)
    sim2 = _sim(layout, s_ref=30.0)
    sim2.add(routes, np.ones(lay.num_routes), routes, arc=lay.exit_arc)
    np.testing.assert_allclose(sim2.scene().s, 0.0, atol=1e-9)
    # Monotonic, metres outside the intersection, scaled inside.
    sim3 = _sim(layout, s_ref=30.0)
    r = np.zeros(5, np.int64)
    arcs = np.array([lay.entry_arc[0] - 10, lay.entry_arc[0], (lay.entry_arc[0] + lay.exit_arc[0]) / 2,
                     lay.exit_arc[0], lay.exit_arc[0] + 10])  # fmt: skip
    sim3.add(r, np.ones(5), np.arange(5), arc=arcs)
    np.testing.assert_allclose(sim3.scene().s, [-40.0, -30.0, -15.0, 0.0, 10.0], atol=1e-9)


def test_same_lane_and_crossing_edges_of_a_hand_built_scene():
    sim = _sim()
    lay = sim.layout
    rid = lay.route_id
    rows = [
        ("south->north", 60.0),  # 0: ahead on the south approach
        ("south->north", 40.0),  # 1: follows 0
        ("west->east", 70.0),  # 2: crosses 0 and 1
        ("north->south", lay.exit_arc[rid("north->south")] + 10.0),  # 3: has left the intersection
        ("north->west", 50.0),  # 4: right turn, conflicts with neither 0, 1 nor 2
        ("east->west", 30.0),  # 5: crosses 0 and 1 (north->south 3 is gone), merges with 4
    ]
    sim.add(
        [rid(r) for r, _ in rows], np.full(len(rows), 5.0), np.arange(len(rows)), arc=[a for _, a in rows]
    )
    scene = sim.scene()
    edge_index, edge_type = edges(scene)
    got = _edge_set(edge_index, edge_type)
    expected = {(0, 1, SAME_LANE)}
    for a, b in ((0, 2), (1, 2), (0, 5), (1, 5), (4, 5)):
        expected |= {(a, b, CROSSING), (b, a, CROSSING)}
    assert got == expected
    # Same-lane edges come first in the edge list.
    assert edge_type.tolist() == sorted(edge_type.tolist())


def test_crossing_edges_follow_the_conflict_matrix_on_every_layout():
    for name in LAYOUT_NAMES:
        sim = _sim(name)
        lay = sim.layout
        routes = np.arange(lay.num_routes)
        sim.add(routes, np.ones(lay.num_routes), routes, arc=lay.entry_arc - 20.0)  # all before entry
        edge_index, edge_type = edges(sim.scene())
        cross = edge_index[:, edge_type == CROSSING]
        matrix = np.zeros_like(lay.conflicts)
        matrix[cross[0], cross[1]] = True
        assert (matrix == lay.conflicts).all()


def test_d_matches_the_mahalanobis_formula():
    rng = np.random.default_rng(3)
    n = 7
    pos = rng.uniform(-10, 10, (n, 2))
    heading = rng.uniform(-np.pi, np.pi, n)
    scene = _manual_scene(pos, heading, speed=rng.uniform(0, 10, n))
    d = node_features(scene, d_max=1e9)[:, 2]
    for i in range(n):
        c, s = np.cos(heading[i]), np.sin(heading[i])
        rot = np.array([[c, -s], [s, c]])
        sigma = rot @ np.diag([5.0**2 / 4, 2.0**2 / 4]) @ rot.T
        dists = [
            np.sqrt((pos[j] - pos[i]) @ np.linalg.inv(sigma) @ (pos[j] - pos[i])) for j in range(n) if j != i
        ]
        assert d[i] == pytest.approx(1.0 / min(dists), rel=1e-5)
    matrix = mahalanobis_matrix(pos, heading)
    assert np.isinf(np.diag(matrix)).all()


def test_d_is_clipped_and_zero_when_alone():
    scene = _manual_scene(np.zeros((2, 2)), np.zeros(2), speed=np.ones(2))
    assert node_features(scene, d_max=7.0)[:, 2].tolist() == [7.0, 7.0]
    alone = _manual_scene(np.zeros((1, 2)), np.zeros(1), speed=np.ones(1))
    assert node_features(alone)[0, 2] == 0.0


def test_v_is_speed_over_lane_limit_and_observation_fits_space():
    sim = _sim()
    lay = sim.layout
    r = lay.route_id("south->east")
    sim.add([r, r], [3.0, 5.0], [0, 1], arc=[lay.entry_arc[r] + 2.0, 20.0])
    scene = sim.scene()
    space = GraphSpace(8, 3, 16, 2)
    obs = build_observation(scene, space)
    assert space.contains(obs)
    x, edge_index, edge_type = space.decode(obs)
    np.testing.assert_allclose(x[:, 1], scene.speed / scene.speed_limit, rtol=1e-6)
    assert x[0, 1] == pytest.approx(3.0 / np.sqrt(3.0 * 9.0))  # right turn: radius 9 m at 3 m/s^2 lateral
    np.testing.assert_allclose(x[:, 0], scene.s * DEFAULT_S_SCALE, rtol=1e-6)
    assert _edge_set(edge_index, edge_type) == {(0, 1, SAME_LANE)}


def test_edges_beyond_max_edges_keep_same_lane_edges_and_closest_crossings():
    sim = _sim()
    lay = sim.layout
    sn, we = lay.route_id("south->north"), lay.route_id("west->east")
    sim.add([sn, sn, we], [5.0] * 3, [0, 1, 2], arc=[60.0, 40.0, 75.0])
    edge_index, edge_type = edges(sim.scene(), max_edges=3)
    got = _edge_set(edge_index, edge_type)
    assert (0, 1, SAME_LANE) in got and len(got) == 3
    assert got - {(0, 1, SAME_LANE)} == {(0, 2, CROSSING), (2, 0, CROSSING)}  # 0 is closer to 2 than 1


def _manual_scene(pos, heading, speed):
    n = pos.shape[0]
    lay = build_layout("4way")
    return Scene(
        time=0.0, dt=0.2, vehicle_id=np.arange(n), route=np.zeros(n, np.int64), s=np.zeros(n),
        position=pos, heading=heading, speed=speed, speed_limit=np.full(n, 10.0),
        dist_to_entry=np.ones(n), dist_to_exit=np.ones(n), leader=-np.ones(n, np.int64),
        gap=np.full(n, np.inf), priority=np.zeros(n, np.int64), maneuver=np.zeros(n, np.int64),
        length=np.full(n, 5.0), route_names=lay.route_names, conflicts=lay.conflicts,
    )  # fmt: skip


def test_edge_features_distance_and_bearing():
    from envs.simulation.graph import edge_features

    sim = _sim()
    rid = sim.layout.route_id
    sim.add(np.array([rid("south->north")] * 2), np.ones(2), np.arange(2), arc=np.array([60.0, 40.0]))
    scene = sim.scene()
    edge_index, edge_type = edges(scene)
    assert _edge_set(edge_index, edge_type) == {(0, 1, SAME_LANE)}
    attr = edge_features(scene, edge_index, ["bearing", "distance"])
    # The leader is 20 m straight ahead of its follower.
    np.testing.assert_allclose(attr, [[0.0, 20.0 * DEFAULT_S_SCALE]], atol=1e-6)
    reverse = edge_features(scene, edge_index[::-1], ["bearing"])
    np.testing.assert_allclose(np.abs(reverse), [[1.0]], atol=1e-6)  # the follower is behind the leader
    space = GraphSpace(max_nodes=4, node_features=3, max_edges=4, num_relations=2, edge_features=2)
    obs = build_observation(scene, space, edge_feature_names=["bearing", "distance"])
    np.testing.assert_allclose(obs["edge_attr"][:1], attr)
    with pytest.raises(ValueError, match="2 edge features"):
        build_observation(scene, space)


@pytest.mark.parametrize("names", [(), ("distance", "bearing")])
def test_graph_batch_is_the_unpadded_observation(names):
    """build_graph_batch equals padded_to_batch of build_observation, edge features and the
    max_edges cut included, and refuses what the padded observation refuses."""
    import torch

    from sb3_graph.common.batching import padded_to_batch

    sim = _sim()
    lay = sim.layout
    sn, we, ns = lay.route_id("south->north"), lay.route_id("west->east"), lay.route_id("north->south")
    sim.add([sn, sn, we, ns], [5.0, 4.0, 6.0, 3.0], [0, 1, 2, 3], arc=[60.0, 40.0, 75.0, 50.0])
    scene = sim.scene()
    for max_edges in (16, 3):
        space = GraphSpace(8, 3, max_edges, 2, edge_features=len(names))
        obs = build_observation(scene, space, edge_feature_names=names)
        padded = padded_to_batch({key: torch.as_tensor(value) for key, value in obs.items()})
        direct = build_graph_batch(scene, space, edge_feature_names=names)
        for field in ("x", "edge_index", "edge_type", "batch", "node_slot") + (("edge_attr",) if names else ()):
            assert torch.equal(getattr(direct, field), getattr(padded, field)), field
        assert (direct.num_graphs, direct.max_nodes) == (1, 8)
        assert direct.edge_attr is None if not names else direct.edge_attr.shape == (direct.num_edges, 2)
    with pytest.raises(ValueError, match="exceed max_nodes=3"):
        build_graph_batch(scene, GraphSpace(3, 3, 16, 2, edge_features=len(names)), edge_feature_names=names)
    with pytest.raises(ValueError, match="edge features"):
        build_graph_batch(scene, GraphSpace(8, 3, 16, 2, edge_features=1), edge_feature_names=names)


def test_env_option_edge_features():
    import gymnasium as gym

    import envs  # noqa: F401 - registers the environments

    env = gym.make("CoopIntersection4Way-v0", config={"edge_features": ["distance", "bearing"]})
    obs, _ = env.reset(seed=0)
    assert env.observation_space.edge_features == 2 and env.observation_space.contains(obs)
    e = int(obs["edge_mask"].sum())
    assert e > 0 and np.all(obs["edge_attr"][:e, 0] > 0) and np.all(np.abs(obs["edge_attr"][:e, 1]) <= 1)
    with pytest.raises(ValueError, match="edge_features"):
        gym.make("CoopIntersection4Way-v0", config={"edge_features": ["speed"]})
    assert "edge_attr" not in gym.make("CoopIntersection4Way-v0").reset(seed=0)[0]
