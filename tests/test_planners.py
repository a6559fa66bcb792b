"""Planners on hand-built scenes: IDM, priority rules (PR), FIFO and the planner registry."""

from __future__ import annotations

import numpy as np
import pytest

from envs.planners import FIFOPlanner, PriorityRulesPlanner, check_planner_spec, make_planner, planner_name
from envs.planners.idm import IDMParams, idm_acceleration, leader_chain_max, travel_time
from envs.planners.priority_rules import maneuver_priority
from envs.simulation.scene import LEFT, MAJOR, MINOR, RIGHT, STRAIGHT, Scene

# Three routes: south->north (major, straight), west->east (minor, straight),
# north->south (major, straight). Only the two straights across each other conflict.
ROUTES = ("south->north", "west->east", "north->south")
CONFLICTS = np.array([[False, True, False], [True, False, True], [False, True, False]])
INSIDE_LENGTH = 20.0  # metres of path inside the intersection area


def make_scene(vehicles: list[dict], conflicts: np.ndarray = CONFLICTS, dt: float = 0.2) -> Scene:
    """A scene from per-vehicle dicts: route, dist (to the stop line), speed, priority, maneuver."""
    n = len(vehicles)
    dist = np.array([v["dist"] for v in vehicles], dtype=float)
    route = np.array([v["route"] for v in vehicles], dtype=np.int64)
    leader = np.array([v.get("leader", -1) for v in vehicles], dtype=np.int64)
    gap = np.array([v.get("gap", np.inf) for v in vehicles], dtype=float)
    return Scene(
        time=0.0,
        dt=dt,
        vehicle_id=np.arange(n, dtype=np.int64) + 10,
        route=route,
        s=-(dist + INSIDE_LENGTH),
        position=np.zeros((n, 2)),
        heading=np.zeros(n),
        speed=np.array([v["speed"] for v in vehicles], dtype=float),
        speed_limit=np.full(n, 10.0),
        dist_to_entry=dist,
        dist_to_exit=dist + INSIDE_LENGTH + 5.0,
        leader=leader,
        gap=gap,
        priority=np.array([v.get("priority", MAJOR if v["route"] != 1 else MINOR) for v in vehicles]),
        maneuver=np.array([v.get("maneuver", STRAIGHT) for v in vehicles]),
        length=np.full(n, 5.0),
        route_names=ROUTES,
        conflicts=conflicts,
    )


def test_idm_free_road_and_following():
    acc = idm_acceleration(
        np.array([0.0, 10.0, 10.0]),
        np.array([10.0, 10.0, 10.0]),
        np.array([np.inf, np.inf, 5.0]),
        np.array([0.0, 0.0, 0.0]),
        dt=0.1,
    )
    assert acc[0] == pytest.approx(IDMParams().acc_max)  # at rest, free road: full comfortable acceleration
    assert acc[1] == pytest.approx(0.0)  # at the target speed
    assert acc[2] == pytest.approx(-IDMParams().acc_limit)  # close behind a standing obstacle: hard limit


def test_idm_target_speed_zero():
    """Paper tweak 1: a stop target brakes comfortably to rest and a vehicle at rest stays there."""
    speed = np.array([0.0, 0.2, 10.0])
    acc = idm_acceleration(speed, np.zeros(3), np.full(3, np.inf), np.zeros(3), dt=0.1)
    assert acc[0] == 0.0  # highway-env would accelerate at a_max here
    assert acc[1] == pytest.approx(-2.0)  # stops within the step, not beyond
    assert acc[2] == pytest.approx(-IDMParams().comfort_dec)
    assert np.all(speed + acc * 0.1 >= -1e-12)


def test_idm_does_not_mutate_highway_env():
    from highway_env.vehicle.behavior import IDMVehicle

    before = (IDMVehicle.COMFORT_ACC_MAX, IDMVehicle.TIME_WANTED, IDMVehicle.DISTANCE_WANTED)
    PriorityRulesPlanner().act(make_scene([{"route": 0, "dist": 30.0, "speed": 8.0}]))
    assert (IDMVehicle.COMFORT_ACC_MAX, IDMVehicle.TIME_WANTED, IDMVehicle.DISTANCE_WANTED) == before


def test_travel_time_profile():
    t = travel_time(np.array([0.0, 50.0, 5.0]), np.array([10.0, 10.0, 0.0]), np.full(3, 10.0), accel=2.0)
    assert t[0] == 0.0
    assert t[1] == pytest.approx(5.0)  # already at v_max
    assert t[2] == pytest.approx(np.sqrt(5.0))  # 0.5 a t^2 = 5


def test_leader_chain_max():
    out = leader_chain_max(np.array([5.0, 1.0, 1.0]), np.array([-1, 0, 1]), offset=0.5)
    np.testing.assert_allclose(out, [5.0, 5.5, 6.0])


def test_maneuver_priority_order():
    klass = maneuver_priority(
        np.array([MAJOR, MAJOR, MAJOR, MINOR, MINOR, MINOR]),
        np.array([STRAIGHT, RIGHT, LEFT, STRAIGHT, RIGHT, LEFT]),
    )
    np.testing.assert_array_equal(klass, [0, 0, 1, 2, 2, 3])


@pytest.mark.parametrize("major_route, minor_route", [(0, 1), (1, 0)])
def test_pr_minor_yields_to_major(major_route, minor_route):
    """Both arrive at the same time on crossing paths: the minor-road vehicle waits, not the major one."""
    scene = make_scene(
        [
            {"route": major_route, "dist": 30.0, "speed": 10.0, "priority": MAJOR},
            {"route": minor_route, "dist": 30.0, "speed": 10.0, "priority": MINOR},
        ]
    )
    planner = PriorityRulesPlanner()
    blocked = planner.blocked(scene)
    assert not blocked[0] and blocked[1]
    acc = planner.act(scene)
    assert acc[1] < -1.0 and acc[0] >= 0.0  # the minor vehicle brakes for its stop point


def test_pr_major_left_yields_to_oncoming_straight():
    conflicts = np.array([[False, True, True], [True, False, True], [True, True, False]])
    scene = make_scene(
        [
            {"route": 0, "dist": 30.0, "speed": 10.0, "maneuver": LEFT},
            {"route": 2, "dist": 40.0, "speed": 10.0, "maneuver": STRAIGHT},
        ],
        conflicts=conflicts,
    )
    blocked = PriorityRulesPlanner().blocked(scene)
    assert blocked[0] and not blocked[1]


def test_pr_minor_goes_in_a_large_gap():
    scene = make_scene(
        [
            {"route": 0, "dist": 200.0, "speed": 10.0, "priority": MAJOR},
            {"route": 1, "dist": 20.0, "speed": 10.0, "priority": MINOR},
        ]
    )
    assert not PriorityRulesPlanner().blocked(scene).any()


def test_pr_waits_for_vehicle_inside_the_intersection():
    """A major vehicle still yields to a (minor) vehicle that already holds the intersection."""
    scene = make_scene(
        [
            {"route": 0, "dist": 25.0, "speed": 5.0, "priority": MAJOR},
            {"route": 1, "dist": -2.0, "speed": 1.0, "priority": MINOR},
        ]
    )
    assert PriorityRulesPlanner().blocked(scene)[0]


def test_fifo_non_conflicting_go_together_conflicting_waits():
    scene = make_scene(
        [
            {"route": 0, "dist": 20.0, "speed": 8.0},
            {"route": 2, "dist": 21.0, "speed": 8.0},
            {"route": 1, "dist": 25.0, "speed": 8.0},
        ]
    )
    planner = FIFOPlanner()
    blocked = planner.blocked(scene)
    np.testing.assert_array_equal(blocked, [False, False, True])
    acc = planner.act(scene)
    assert acc[2] < acc[0] and acc[2] < 0


def test_fifo_order_beats_road_priority():
    """FIFO lets the minor-road vehicle that is closer go first; PR would hold it."""
    scene = make_scene(
        [
            {"route": 0, "dist": 40.0, "speed": 10.0, "priority": MAJOR},
            {"route": 1, "dist": 25.0, "speed": 10.0, "priority": MINOR},
        ]
    )
    np.testing.assert_array_equal(FIFOPlanner().blocked(scene), [True, False])
    np.testing.assert_array_equal(PriorityRulesPlanner().blocked(scene), [False, True])


def test_committed_vehicle_is_not_held():
    """A vehicle too close to its stop line to stop is let through (and others wait for it)."""
    scene = make_scene(
        [
            {"route": 0, "dist": 3.0, "speed": 10.0, "priority": MINOR},
            {"route": 1, "dist": 30.0, "speed": 10.0, "priority": MAJOR},
        ]
    )
    for planner in (PriorityRulesPlanner(), FIFOPlanner()):
        np.testing.assert_array_equal(planner.blocked(scene), [False, True])


def test_planners_output_shape_and_bounds():
    rng = np.random.default_rng(0)
    n = 12
    scene = make_scene(
        [
            {
                "route": int(rng.integers(3)),
                "dist": float(rng.uniform(-10, 80)),
                "speed": float(rng.uniform(0, 12)),
            }
            for _ in range(n)
        ]
    )
    for planner in (PriorityRulesPlanner(), FIFOPlanner()):
        acc = planner.act(scene)
        assert acc.shape == (n,) and np.all(np.isfinite(acc))
        assert np.all((acc >= scene.a_min) & (acc <= scene.a_max))
    empty = make_scene([])
    assert PriorityRulesPlanner().act(empty).shape == (0,)


def test_registry(tmp_path):
    assert isinstance(make_planner("pr"), PriorityRulesPlanner)
    assert isinstance(make_planner("FIFO"), FIFOPlanner)
    assert planner_name("fifo") == "FIFO"
    for bad in ("random", str(tmp_path / "missing.zip"), str(tmp_path)):
        with pytest.raises(ValueError, match="pr, fifo"):
            check_planner_spec(bad)
    model = tmp_path / "coop" / "best_model.zip"
    model.parent.mkdir()
    model.write_bytes(b"")
    assert check_planner_spec(str(model)) == str(model)
    assert planner_name(str(model)) == "RL:coop"


def test_gnn_planner_scales_the_model_action(monkeypatch, tmp_path):
    """The learned planner: model's own observation space in, action[:n] * a_max out."""
    import envs.planners.gnn as gnn

    seen = {}

    class FakeModel:
        observation_space = "graph-space-of-the-model"

        def predict(self, obs, deterministic=False):
            seen["deterministic"] = deterministic
            return np.array([0.5, -1.0, 0.2, 0.9, 0.9]), None  # padded to 5 slots

    def build_observation(scene, space, **names):
        seen["space"] = space
        assert names == {"vertex_feature_names": (), "edge_feature_names": ()}  # a file without a planner config
        return {"n": scene.num_vehicles}

    monkeypatch.setattr(gnn, "build_observation", build_observation)
    monkeypatch.setattr(gnn, "load_model", lambda path, device="cpu", **kwargs: FakeModel())
    planner = gnn.GNNPlanner(tmp_path / "run" / "best_model.zip")
    assert planner.name == "RL:run"
    scene = make_scene(
        [
            {"route": 0, "dist": 30.0, "speed": 8.0},
            {"route": 1, "dist": 30.0, "speed": 8.0},
            {"route": 2, "dist": 10.0, "speed": 8.0},
        ]
    )
    acc = planner.act(scene)
    np.testing.assert_allclose(acc, [2.5, -5.0, 1.0])
    assert seen == {"deterministic": True, "space": "graph-space-of-the-model"}


def test_rank_by_uses_the_first_key_most():
    from envs.planners.yielding import rank_by

    np.testing.assert_array_equal(rank_by(np.array([1, 0, 1]), np.array([5, 9, 2])), [2, 0, 1])
    np.testing.assert_array_equal(rank_by(np.array([3.0, 1.0, 2.0])), [2, 0, 1])
