"""Vectorized simulation: kinematics, removal, events, leaders, collisions, scene snapshot."""

from __future__ import annotations

import numpy as np
import pytest
from highway_env import utils as hw_utils
from highway_env.vehicle.kinematics import Vehicle

from envs.simulation.engine import Simulation, overlapping_pairs
from envs.simulation.layouts import build_layout, parting_arcs
from envs.simulation.scene import STOP_SPEED


@pytest.fixture
def sim():
    return Simulation(build_layout("4way"), max_speed=20.0, max_acceleration=5.0)


def test_constant_acceleration_is_integrated_exactly(sim):
    r = sim.layout.route_id("south->north")
    sim.add([r], [8.0], [7], arc=[10.0])
    sim.step(np.array([2.0]))
    dt = sim.dt
    assert sim.speed[0] == pytest.approx(8.0 + 2.0 * dt)
    assert sim.arc[0] == pytest.approx(10.0 + 8.0 * dt + 0.5 * 2.0 * dt**2)
    assert sim.time == pytest.approx(dt)


def test_commands_are_clipped_and_speed_stays_in_bounds(sim):
    r = sim.layout.route_id("west->east")
    sim.add([r, r], [1.0, 19.9], [0, 1], arc=[10.0, 60.0])
    arcs = [sim.arc.copy()]
    for _ in range(5):
        sim.step(np.array([-100.0, 100.0]))
        arcs.append(sim.arc.copy())
    # 100 is clipped to 5, and the governor holds the vehicle at the straight lane's limit.
    limit = sim.layout.limit_at(sim.route[1:], sim.arc[1:])[0]
    assert sim.speed[0] == 0.0 and sim.speed[1] == pytest.approx(limit) and limit < 20.0
    assert (np.diff(np.array(arcs), axis=0) >= 0).all()  # never backwards
    # -100 is clipped to -5: from 1 m/s the vehicle stops within 1/5 s, after at most 0.1 m.
    assert arcs[-1][0] - 10.0 <= 1.0**2 / (2 * 5.0) + 1e-9 + 0.5 * 1.0 / 15


def test_stop_cross_and_remove_events(sim):
    lay = sim.layout
    r = lay.route_id("east->west")
    sim.add([r, r, r], [0.2, 10.0, 10.0], [10, 11, 12], arc=[5.0, lay.exit_arc[r] - 0.5, lay.length[r] - 0.5])
    events = sim.step(np.zeros(3))
    assert events.stopped.tolist() == [10]
    assert events.crossed.tolist() == [11]
    assert events.removed.tolist() == [12]
    assert sim.vehicle_id.tolist() == [10, 11]  # survivors keep their order
    assert sim.speed[0] < STOP_SPEED


def test_capacity_and_unique_ids(sim):
    small = Simulation(sim.layout, max_vehicles=2)
    small.add([0, 1], [5.0, 5.0], [0, 1])
    with pytest.raises(ValueError, match="max_vehicles"):
        small.add([2], [5.0], [2])
    with pytest.raises(ValueError, match="unique"):
        sim.add([0, 1], [1.0, 1.0], [3, 3])


def test_leaders_on_shared_lanes(sim):
    lay = sim.layout
    sn, se, ew = lay.route_id("south->north"), lay.route_id("south->east"), lay.route_id("east->west")
    ww = lay.route_id("north->west")  # merges with east->west onto the west exit lane
    # rows: 0 south->north at 30; 1 south->east at 50 (same approach lane, ahead of 0);
    # 2 east->west on the exit lane; 3 north->west inside its turn (behind 2 on the exit lane);
    # 4 east->west approaching (its lanes differ from 3's until the exit lane).
    sim.add(
        [sn, se, ew, ww, ew],
        [5.0] * 5,
        [0, 1, 2, 3, 4],
        arc=[30.0, 50.0, lay.exit_arc[ew] + 20.0, lay.exit_arc[ww] - 3.0, 40.0],
    )
    leader, gap = sim.leaders()
    assert leader.tolist() == [1, -1, -1, 2, 2]
    assert gap[0] == pytest.approx(50.0 - 30.0 - 5.0)
    # The gap along the shared exit lane: both positions measured from the exit lane's start.
    expected = (20.0 + 3.0) - 5.0
    assert gap[3] == pytest.approx(expected)
    assert np.isinf(gap[1]) and np.isinf(gap[2])


def test_overlapping_pairs_match_highway_env_polygons():
    rng = np.random.default_rng(1)
    n = 40
    pos = rng.uniform(0, 15, (n, 2))
    heading = rng.uniform(-np.pi, np.pi, n)
    length = rng.uniform(3, 6, n)
    width = rng.uniform(1.5, 2.5, n)
    pairs = {tuple(p) for p in overlapping_pairs(pos, heading, length, width).tolist()}
    polys = []
    for i in range(n):
        v = Vehicle(None, pos[i], heading[i])
        v.LENGTH, v.WIDTH = length[i], width[i]
        polys.append(v.polygon())
    expected = set()
    for i in range(n):
        for j in range(i + 1, n):
            if hw_utils.are_polygons_intersecting(polys[i], polys[j], np.zeros(2), np.zeros(2))[0]:
                expected.add((i, j))
    assert expected and pairs == expected


def test_collision_is_reported_with_ids(sim):
    lay = sim.layout
    sn, we = lay.route_id("south->north"), lay.route_id("west->east")
    # Both at the centre of the intersection: the two straight paths cross there.
    centre_sn = lay.entry_arc[sn] + (lay.exit_arc[sn] - lay.entry_arc[sn]) / 2
    centre_we = lay.entry_arc[we] + (lay.exit_arc[we] - lay.entry_arc[we]) / 2
    sim.add([sn, we], [0.0, 0.0], [21, 42], arc=[centre_sn, centre_we])
    events = sim.step(np.zeros(2))
    assert events.collisions.tolist() == [[21, 42]]


def test_scene_fields(sim):
    lay = sim.layout
    r = lay.route_id("north->east")
    sim.add(
        [r, r], [4.0, 6.0], [5, 6], arc=[20.0, lay.entry_arc[r] + 1.0], length=[4.0, 5.0], width=[1.8, 2.0]
    )
    scene = sim.scene()
    assert scene.num_vehicles == 2
    np.testing.assert_allclose(scene.dist_to_entry, lay.entry_arc[r] - (sim.arc + sim.length / 2))
    np.testing.assert_allclose(scene.dist_to_exit, lay.exit_arc[r] - (sim.arc - sim.length / 2))
    assert scene.leader.tolist() == [1, -1]
    assert scene.route_names == lay.route_names and scene.conflicts is lay.conflicts
    assert scene.a_min == -5.0 and scene.a_max == 5.0
    assert scene.approaching.all()
    np.testing.assert_allclose(scene.width, [1.8, 2.0])
    assert scene.speed_limit[0] == lay.speed_limit[r, 0] and scene.speed_limit[1] < scene.speed_limit[0]


def test_the_rollout_scene_is_the_scene_without_copies_and_poses(sim):
    """``rollout_scene`` holds :meth:`scene`'s values, on the simulation's own arrays, with NaN where no planner
    behind the shield reads (position, heading, s); a speed limit passed in is taken as it is."""
    import dataclasses

    lay = sim.layout
    r, q = lay.route_id("north->east"), lay.route_id("south->north")
    sim.add([r, r, q], [4.0, 6.0, 3.0], [5, 6, 9], arc=[20.0, lay.entry_arc[r] + 1.0, 30.0], length=[4.0, 5.0, 4.5])
    full, lean = sim.scene(), sim.rollout_scene()
    for f in dataclasses.fields(full):
        want, got = getattr(full, f.name), getattr(lean, f.name)
        if f.name in ("position", "heading", "s"):
            assert got.shape == want.shape and np.isnan(got).all()
        elif isinstance(want, np.ndarray):
            assert got.dtype == want.dtype and np.array_equal(got, want), f.name
        else:
            assert got == want or got is want, f.name
    assert lean.arc is sim.arc and lean.speed is sim.speed  # not copied
    limit = lay.limit_at(sim.route, sim.arc)
    assert sim.rollout_scene(limit).speed_limit is limit


def test_spawn_free_accounts_for_braking(sim):
    lay = sim.layout
    r = lay.route_id("south->north")
    k = lay.route_spawn_lane[r]
    sim.add([r], [0.0], [0], arc=[5.0 + 2.5 + 6.0])  # rear 11 m from the lane start
    # Newcomer 5 m long: bumper gap 6 m. At 0 m/s it fits with min_gap 5; at 10 m/s it needs 5 + 10 m.
    assert sim.spawn_free(np.array([k]), np.array([0.0]), np.array([5.0]), 5.0).tolist() == [True]
    assert sim.spawn_free(np.array([k]), np.array([10.0]), np.array([5.0]), 5.0).tolist() == [False]
    other = (k + 1) % len(lay.spawn_lanes)
    assert sim.spawn_free(np.array([other]), np.array([10.0]), np.array([5.0]), 5.0).tolist() == [True]


def test_frequency_mismatch_is_an_error():
    with pytest.raises(ValueError, match="multiple of"):
        Simulation(build_layout("4way"), simulation_frequency=10, policy_frequency=3)


def _fine_all_pairs(sim: Simulation, route, length, width, per_substep: int) -> set[tuple[int, int]]:
    """Reference: every pair tested at ``per_substep`` times per sub-step of the last trajectory."""
    speed, arc = sim.last_trajectory
    h = 1 / sim.simulation_frequency
    pairs: set[tuple[int, int]] = set()
    for k in range(sim.substeps):
        a = (speed[k + 1] - speed[k]) / h
        for t in np.arange(1, per_substep + 1) / per_substep * h:
            pos, heading = sim.layout.pose(route, arc[k] + speed[k] * t + 0.5 * a * t**2)
            pairs |= {tuple(p) for p in overlapping_pairs(pos, heading, length, width).tolist()}
    return pairs


@pytest.mark.parametrize("layout, seed", [("4way", 0), ("4way", 1), ("3way", 2), ("inD", 3), ("inD", 4)])
def test_collision_checks_find_every_contact_of_a_fine_all_pairs_check(layout, seed):
    """The candidate filtering, the 1-D check on shared lanes and the adaptive check times find
    every pair that the full separating-axis test over all pairs finds at 600 Hz (40 checks per
    15 Hz sub-step) along the same trajectory, and nothing that it does not find."""
    lay = build_layout(layout)
    rng = np.random.default_rng(seed)
    found = 0
    for _ in range(60):
        sim = Simulation(lay)
        route = rng.integers(0, lay.num_routes, 40)
        arc0 = rng.uniform(40, 105, 40)
        # Start without overlaps (as in the environment, where a collision ends the episode).
        pos, heading = lay.pose(route, arc0)
        overlapping = np.unique(overlapping_pairs(pos, heading, np.full(40, 5.0), np.full(40, 2.0)))
        keep = np.setdiff1d(np.arange(40), overlapping)
        route, n = route[keep], keep.size
        sim.add(route, rng.uniform(0, 12, n), np.arange(n), arc=arc0[keep])
        length, width = sim.length.copy(), sim.width.copy()
        events = sim.step(rng.uniform(-5, 5, n))
        got = {tuple(p) for p in events.collisions.tolist()}
        assert got == _fine_all_pairs(sim, route, length, width, 40)
        found += len(got)
    assert found >= 5  # the random cases do contain collisions


def test_corner_grazes_between_15hz_substeps_are_found():
    """Two vehicles crossing at the limit: where one's front corner only grazes the other's rear
    corner between two 15 Hz sub-steps, a check after every sub-step sees nothing; ours sees it."""
    lay = build_layout("4way")
    we, sn = lay.route_id("west->east"), lay.route_id("south->north")
    seen_only_between = 0
    for offset in np.linspace(9.5, 12.5, 31):
        sim = Simulation(lay)
        sim.add([we, sn], [10.0, 10.0], [0, 1], arc=[lay.entry_arc[we] + 7.75, lay.entry_arc[sn] + offset])
        if sim.collisions().size:
            continue
        route, length, width = sim.route.copy(), sim.length.copy(), sim.width.copy()
        events = sim.step(np.zeros(2))
        fine = _fine_all_pairs(sim, route, length, width, 40)
        assert {tuple(p) for p in events.collisions.tolist()} == fine
        if fine and not _fine_all_pairs(sim, route, length, width, 1):
            seen_only_between += 1
    assert seen_only_between > 0


@pytest.mark.parametrize(
    "leader_route, follower_route, leader_arc, is_leader",
    [
        ("east->south", "east->west", 50.0, True),
        ("east->south", "east->west", 58.0, True),
        ("east->south", "east->west", 75.0, False),
        ("east->west", "east->south", 67.55, True),
        ("east->west", "east->south", 76.0, False),
    ],
)
def test_a_car_that_took_the_other_branch_stays_the_leader_while_the_lanes_overlap(
    leader_route, follower_route, leader_arc, is_leader
):
    """inD: the through lane leaves the left-turn pocket at a shallow angle, so a car that has just
    taken the other branch still blocks the lane of the car behind it, both ways: a left-turner in its
    pocket ahead of a through car (regression: the through car lost its leader and rear-ended it), and
    a through car ahead of a left-turner (regression: with its rear 15 m past the split at 50 m, a
    human left-turner lost it and rear-ended it in the penetration sweep). It stays the leader while
    its rear is short of the arc where the two centre lines part by the conflict distance (69 m, the
    shield's rule, ``parting_arcs``), and no longer once it is past."""
    lay = build_layout("inD")
    lr, fr = lay.route_id(leader_route), lay.route_id(follower_route)
    sim = Simulation(lay)
    sim.add([lr, fr], [0.0, 8.0], [0, 1], arc=[leader_arc, leader_arc - 5.5])
    leader, gap = sim.leaders()
    assert leader.tolist() == [-1, 0 if is_leader else -1]
    rear = leader_arc - sim.length[0] / 2
    assert (rear < parting_arcs(lay)[lr, fr]) == is_leader
    if is_leader:
        assert gap[1] == pytest.approx(0.5)
        # Brute force: where the leader's rear is, the two centre lines run closer than the conflict distance.
        p_leader, _ = lay.pose(np.array([lr]), np.array([rear]))
        p_follower, _ = lay.pose(np.array([fr]), np.array([rear]))
        assert np.hypot(*(p_leader - p_follower)[0]) < 2.5
        events = sim.step(np.array([0.0, 0.0]))  # at 8 m/s without braking it hits the leader
        assert events.collisions.tolist() == [[0, 1]]
    else:
        assert np.isinf(gap[1])


def _leaders_numpy(sim: Simulation) -> tuple[np.ndarray, np.ndarray]:
    """The leader search in NumPy (every pair at once): the oracle of the compiled ``_leaders_kernel.leaders``."""
    from envs.simulation.engine import SPLIT_CLEARANCE

    lay, n = sim.layout, sim.num_vehicles
    back_arc = sim.arc - sim.length / 2 - SPLIT_CLEARANCE
    lane, back_lane = lay.lane_at(sim.route, np.stack([sim.arc, back_arc]))
    into_lane = sim.arc - lay.lane_start[sim.route, lane]
    x = lay.lane_start[sim.route[:, None], lane[None, :]] + into_lane[None, :]  # (i, j): j on i's route
    missing = np.isnan(x)
    if missing.any():
        into_back = sim.arc - lay.lane_start[sim.route, back_lane]
        x_back = lay.lane_start[sim.route[:, None], back_lane[None, :]] + into_back[None, :]
        rear = sim.arc - sim.length / 2
        overlaps = rear[None, :] < parting_arcs(lay)[sim.route[None, :], sim.route[:, None]]
        x = np.where(missing, np.where(np.isnan(x_back) & overlaps, sim.arc[None, :], x_back), x)
    ahead = x - sim.arc[:, None]
    valid = np.isfinite(ahead) & (ahead > 0)
    np.fill_diagonal(valid, False)
    masked = np.where(valid, ahead, np.inf)
    leader = masked.argmin(axis=1)
    dist = masked[np.arange(n), leader]
    has = np.isfinite(dist)
    gap = np.where(has, dist - (sim.length + sim.length[leader]) / 2, np.inf)
    return np.where(has, leader, -1).astype(np.int64), gap


@pytest.mark.parametrize("layout", ["4way", "3way", "inD"])
def test_compiled_leaders_are_bitwise_the_numpy_search(layout):
    """Random scenes, dense enough that paths split under vehicles and several are equally far ahead."""
    lay = build_layout(layout)
    rng = np.random.default_rng(7)
    compared = 0
    for count in (1, 2, 8, 30, 80) * 6:
        sim = Simulation(lay, max_vehicles=128)
        route = rng.integers(0, lay.num_routes, count)
        arc = np.round(rng.uniform(0.0, lay.length[route] - 1.0), 1)  # rounded: ties in distance happen
        sim.add(route, rng.uniform(0.0, 15.0, count), np.arange(count), length=rng.uniform(3.0, 12.0, count), arc=arc)
        leader, gap = sim.leaders()
        expected = _leaders_numpy(sim)
        np.testing.assert_array_equal(leader, expected[0])
        np.testing.assert_array_equal(gap, expected[1])
        compared += int((leader >= 0).sum())
    assert compared > 100


@pytest.mark.parametrize("layout", ["4way", "3way", "inD"])
def test_compiled_lane_lookup_is_the_layouts(layout):
    """The leader search's compiled lane lookup gives ``Layout.lane_at``'s lanes, lane starts and ends included."""
    from envs.simulation import _leaders_kernel

    lay = build_layout(layout)
    rng = np.random.default_rng(3)
    route = rng.integers(0, lay.num_routes, 400)
    starts = lay.route_lane_starts[route, rng.integers(0, lay.route_lane_starts.shape[1], 400)]
    arc = np.where(np.isfinite(starts), starts, rng.uniform(-20.0, lay.length[route] + 20.0))
    arc[::2] = rng.uniform(-20.0, lay.length[route[::2]] + 20.0)
    np.testing.assert_array_equal(
        _leaders_kernel.lanes(route, arc, lay.route_lane_starts, lay.route_lane_ids), lay.lane_at(route, arc)
    )
