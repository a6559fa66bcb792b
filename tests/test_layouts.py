"""Intersection layouts: geometry, maneuvers, priorities, conflicts, vectorized lookups."""

from __future__ import annotations

import numpy as np
import pytest

from envs.simulation.layouts import ARM_ANGLES, KINK_REACH, LAYOUT_NAMES, build_layout
from envs.simulation.scene import LEFT, MAJOR, MINOR, RIGHT, STRAIGHT


@pytest.fixture(params=LAYOUT_NAMES)
def layout(request):
    return build_layout(request.param)


def test_unknown_layout_is_an_error():
    with pytest.raises(ValueError, match="layout must be one of"):
        build_layout("roundabout")


def test_route_names_and_arms(layout):
    for name, a, b in zip(layout.route_names, layout.entry_arm, layout.exit_arm):
        assert name == f"{a}->{b}" and a != b
        assert a in layout.arm_angle and b in layout.arm_angle
    expected = 6 if layout.name == "3way" else 12
    assert layout.num_routes == expected


def test_polylines_are_continuous_and_headings_follow_them(layout):
    for r in range(layout.num_routes):
        m = int(np.ceil(layout.length[r] / layout.ds)) + 1
        xy = layout.xy[r, :m]
        step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        assert step.max() <= layout.ds + 1e-6
        # The finite-difference direction matches the stored heading (ideal path tracking).
        direction = np.arctan2(np.diff(xy[:, 1]), np.diff(xy[:, 0]))
        mid = 0.5 * (layout.heading[r, : m - 1] + layout.heading[r, 1:m])
        err = np.angle(np.exp(1j * (direction - mid)))
        assert np.abs(err[step > 1e-3]).max() < 0.1  # inD: 7.6 deg kink where the lanes split


def test_pose_matches_highway_env_lanes(layout):
    net = layout.network
    rng = np.random.default_rng(0)
    for r in range(layout.num_routes):
        starts = np.concatenate([[0.0], np.cumsum([net.get_lane(li).length for li in layout.route_lanes[r]])])
        arc = rng.uniform(0, layout.length[r], 20)
        xy, heading = layout.pose(np.full(20, r), arc)
        lane_ids = layout.lane_at(np.full(20, r), arc)
        for a, p, h, g in zip(arc, xy, heading, lane_ids):
            k = np.searchsorted(starts, a, side="right") - 1
            lane = net.get_lane(layout.route_lanes[r][k])
            assert layout.lanes[g] == layout.route_lanes[r][k]
            np.testing.assert_allclose(p, lane.position(a - starts[k], 0), atol=0.05)
            assert abs(np.angle(np.exp(1j * (h - lane.heading_at(a - starts[k]))))) < 0.05


def test_maneuvers_follow_right_hand_geometry(layout):
    # Screen frame (y down): coming from the south (driving north), east is a right turn.
    order = ["north", "east", "south", "west"]  # clockwise on screen
    for r, (a, b) in enumerate(zip(layout.entry_arm, layout.exit_arm)):
        heading_idx = (order.index(a) + 2) % 4  # driving towards the opposite arm
        turn = (order.index(b) - heading_idx) % 4
        assert layout.maneuver[r] == {0: STRAIGHT, 1: RIGHT, 3: LEFT}[turn]


def test_priorities_and_speed_limits(layout):
    for r, a in enumerate(layout.entry_arm):
        assert layout.priority[r] == (MAJOR if a in ("east", "west") else MINOR)
        inside = slice(int(np.ceil(layout.entry_arc[r] / layout.ds)) + 1, int(layout.exit_arc[r] / layout.ds) - 1)
        limit_inside = layout.speed_limit[r, inside]
        if layout.maneuver[r] == STRAIGHT:  # the road's limit, but at a kink where lanes join (inD)
            kinked = np.abs(np.diff(layout.heading[r])) > 1e-9
            reach = int(np.ceil(KINK_REACH / layout.ds))
            near = np.convolve(np.append(kinked, False), np.ones(2 * reach + 1), mode="same") > 0
            assert ((limit_inside == layout.speed_limit[r, 0]) | near[inside]).all()
        else:  # the curved part of a turn is slower than the road
            assert limit_inside.min() < layout.speed_limit[r, 0]
    assert (
        layout.spawn_priority == layout.priority[[layout.spawn_routes(k)[0] for k in range(len(layout.spawn_lanes))]]
    ).all()


def test_arm_angles_point_at_the_arms(layout):
    for r in range(layout.num_routes):
        start = layout.xy[r, 0]
        angle = layout.arm_angle[layout.entry_arm[r]]
        assert angle == ARM_ANGLES[layout.entry_arm[r]]
        assert np.dot(start, [np.cos(angle), np.sin(angle)]) > 0.9 * np.linalg.norm(start)


def test_conflict_matrix(layout):
    c = layout.conflicts
    assert (c == c.T).all() and not np.diag(c).any()
    rid = layout.route_id
    for a in range(layout.num_routes):
        for b in range(layout.num_routes):
            same_stop = layout.route_lanes[a][:-1][-1:] and layout.entry_arm[a] == layout.entry_arm[b]
            if layout.exit_arm[a] == layout.exit_arm[b] and layout.entry_arm[a] != layout.entry_arm[b]:
                assert c[a, b], (layout.route_names[a], layout.route_names[b])  # merge
            if same_stop and layout.route_lanes[a][1] == layout.route_lanes[b][1]:
                assert not c[a, b]  # diverging from one lane
    if layout.name != "3way":
        assert c[rid("south->north"), rid("west->east")]  # crossing straights
        assert c[rid("south->west"), rid("north->south")]  # left turn vs oncoming straight
        assert not c[rid("south->east"), rid("north->west")]  # opposite right turns
    else:
        assert not c[rid("west->east"), rid("east->west")]  # the two directions of the major road
        assert c[rid("south->west"), rid("west->east")]  # minor left turn crosses the major road


def test_ind_left_turns_have_their_own_lane():
    lay = build_layout("inD")
    for arm, left, straight in (("west", "west->north", "west->east"), ("east", "east->south", "east->west")):
        lanes_left, lanes_straight = (
            lay.route_lanes[lay.route_id(left)],
            lay.route_lanes[lay.route_id(straight)],
        )
        assert lanes_left[0] == lanes_straight[0]  # one spawn lane, then the branch
        assert lanes_left[1] != lanes_straight[1]
        # The pocket lies beside the through lane at the stop line, one lane width to its left.
        p_left = lay.pose(np.array([lay.route_id(left)]), lay.entry_arc[[lay.route_id(left)]])[0][0]
        p_straight = lay.pose(np.array([lay.route_id(straight)]), lay.entry_arc[[lay.route_id(straight)]])[0][0]
        assert 3.5 < np.linalg.norm(p_left - p_straight) < 4.5
        del arm


def test_unknown_route_is_an_error():
    with pytest.raises(ValueError, match="has no route"):
        build_layout("3way").route_id("north->south")


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_lookups_take_points_in_any_shape(layout):
    """pose and lane_at on ``(times, n)`` arcs give, row by row, what they give on ``(n,)`` arcs
    (the simulation's collision check and leaders look several points per vehicle up at once)."""
    lay = build_layout(layout)
    rng = np.random.default_rng(0)
    route = rng.integers(0, lay.num_routes, 7)
    arc = rng.uniform(-5.0, lay.length[route] + 5.0, (4, 7))
    position, heading = lay.pose(route[None, :], arc)
    lanes = lay.lane_at(route, arc)
    assert position.shape == (4, 7, 2) and heading.shape == lanes.shape == (4, 7)
    for t in range(4):
        p, h = lay.pose(route, arc[t])
        np.testing.assert_array_equal(position[t], p)
        np.testing.assert_array_equal(heading[t], h)
        np.testing.assert_array_equal(lanes[t], lay.lane_at(route, arc[t]))


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_envelope_at_interpolates_the_squared_envelope_under_the_limit(layout):
    lay = build_layout(layout)
    rng = np.random.default_rng(1)
    route = rng.integers(0, lay.num_routes, 200)
    arc = rng.uniform(-3.0, lay.length[route] + 3.0)  # past both ends too
    env = lay.speed_envelope(3.0)
    last = env.shape[1] - 1
    u = np.clip(arc / lay.ds, 0.0, last)
    i0 = np.minimum(np.floor(u).astype(int), last - 1)
    sq = env[route, i0] ** 2 + (env[route, i0 + 1] ** 2 - env[route, i0] ** 2) * (u - i0)
    expected = np.minimum(np.sqrt(sq), lay.limit_at(route, arc))
    np.testing.assert_array_equal(lay.envelope_at(route, arc, 3.0), expected)
