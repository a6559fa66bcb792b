"""The strong baselines on hand-built scenes in the real simulation: PR's stop point, AIM's
reservations, the actuated signal, and no collisions on busy scenarios for every baseline."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs, run_episode
from envs.planners import AIMPlanner, PriorityRulesPlanner, make_planner
from envs.planners.signal import ALL_RED, GREEN, YELLOW, SignalController, SignalParams
from envs.simulation.traffic import generate_scenario

EMPTY = {"spawn_probability": 0.0, "initial_spawn_probability": 0.0}


def empty_env(layout_id: str = "CoopIntersection4Way-v0"):
    env = gym.make(layout_id, config=dict(EMPTY))
    env.reset(seed=0)
    return env


def drive(env, planner, steps: int, record=None) -> None:
    """Run ``planner`` for ``steps`` policy steps; ``record(scene)`` sees every scene before a step."""
    base = env.unwrapped
    for _ in range(steps):
        scene = base.scene()
        if record is not None:
            record(scene)
        env.step(base.accelerations_to_action(planner.act(scene)))


def test_pr_leader_stops_at_its_stop_line():
    """A yielding leader comes to rest within 1 m of its stop line (not the jam distance before it),
    its follower the jam distance behind it, and both stay at rest."""
    env = empty_env()
    base = env.unwrapped
    base.place_vehicles(["south->north", "south->west", "west->east"], arc=[30.0, 5.0, 20.0], speed=[10.0, 10.0, 8.0])
    planner = PriorityRulesPlanner()
    planner.blocked = lambda scene: np.ones(scene.num_vehicles, bool)  # everyone yields, forever
    drive(env, planner, 150)
    scene = base.scene()
    leaders = scene.leader < 0
    assert np.all(scene.speed < 0.05)
    assert np.all((scene.dist_to_entry[leaders] >= 0.0) & (scene.dist_to_entry[leaders] <= 1.0))
    follower = np.flatnonzero(~leaders)
    assert scene.gap[follower] == pytest.approx(planner.idm.jam_distance, abs=0.5)


def body_in_zone(layout, route: int, other: int, arc: float, length: float) -> bool:
    """Whether a body centred at ``arc`` on ``route`` overlaps its conflict zone with ``other``."""
    return arc + length / 2 >= layout.zone_start[route, other] and arc - length / 2 <= layout.zone_end[route, other]


def test_aim_non_conflicting_paths_go_together():
    """Opposing straights do not conflict: both keep their speed and enter at the same time."""
    env = empty_env()
    base = env.unwrapped
    routes = ["west->east", "east->west"]
    assert not base.layout.conflicts[base.layout.route_id(routes[0]), base.layout.route_id(routes[1])]
    base.place_vehicles(routes, arc=[40.0, 40.0], speed=[8.0, 8.0])
    entered, slowest = {}, [np.inf, np.inf]

    def record(scene):
        for i in range(scene.num_vehicles):
            slowest[i] = min(slowest[i], scene.speed[i])
            if scene.dist_to_entry[i] <= 0 and i not in entered:
                entered[i] = scene.time

    drive(env, AIMPlanner(), 40, record)
    assert set(entered) == {0, 1} and abs(entered[0] - entered[1]) < 0.3
    assert min(slowest) >= 8.0 - 1e-6  # nobody slowed down


def test_aim_conflicting_vehicle_slows_down_instead_of_stopping():
    """Two crossing vehicles due at their conflict zones at the same time: one goes unhindered, the
    other slows early, enters its zone only after the first one's body has left the first one's
    zone, and never stops."""
    env = empty_env()
    base = env.unwrapped
    lay = base.layout
    routes = np.array([lay.route_id("west->east"), lay.route_id("south->north")])
    to_zone = 30.0  # both fronts this far from their conflict zone with the other
    starts = np.array([lay.zone_start[routes[0], routes[1]], lay.zone_start[routes[1], routes[0]]])
    length = base.config["vehicle_length"]
    base.place_vehicles(routes, arc=starts - to_zone - length / 2, speed=[8.0, 8.0])
    trace = []
    drive(env, AIMPlanner(), 60, lambda scene: trace.append((scene.arc.copy(), scene.speed.copy())))
    arcs = np.array([a for a, _ in trace if a.size == 2])
    speeds = np.array([v for a, v in trace if a.size == 2])
    inside = np.array([[body_in_zone(lay, routes[k], routes[1 - k], a[k], length) for k in (0, 1)] for a in arcs])
    assert inside.any(axis=0).all()
    first = int(np.argmin([np.flatnonzero(inside[:, k]).min() for k in (0, 1)]))
    second = 1 - first
    assert np.flatnonzero(inside[:, first]).max() < np.flatnonzero(inside[:, second]).min()  # one after the other
    assert speeds[:, second].min() < 8.0 - 1.0  # the second one adapted its speed ...
    assert speeds[:, second].min() > 2.0  # ... and kept moving
    assert speeds[:, first].min() >= 8.0 - 1e-6  # the first one was not held up


def run_controller(controller, times, detected, waiting):
    return [controller.update(t, np.asarray(d), np.asarray(w)) for t, d, w in zip(times, detected, waiting)]


def test_signal_phases_alternate_with_yellow_and_all_red():
    params = SignalParams(min_green=4.0, max_green=10.0, gap=2.0, yellow=3.0, all_red=1.0)
    controller = SignalController(params, 2)
    times = np.arange(0.0, 60.0, 0.2)
    states = run_controller(controller, times, [[True, True]] * len(times), [[True, True]] * len(times))
    stages = [s for _, s in states]
    changes = [states[k] for k in range(1, len(states)) if states[k] != states[k - 1]]
    expected = [(0, YELLOW), (0, ALL_RED), (1, GREEN), (1, YELLOW), (1, ALL_RED), (0, GREEN)]
    assert changes[: len(expected)] == expected
    # Durations: max green (detectors always busy), then the yellow and all-red times.
    first_yellow = times[stages.index(YELLOW)]
    first_all_red = times[stages.index(ALL_RED)]
    second_green = times[next(k for k, s in enumerate(states) if s == (1, GREEN))]
    assert first_yellow == pytest.approx(params.max_green, abs=0.21)
    assert first_all_red - first_yellow == pytest.approx(params.yellow, abs=0.21)
    assert second_green - first_all_red == pytest.approx(params.all_red, abs=0.21)


def test_signal_gap_out_ends_green_early_and_green_rests_without_demand():
    params = SignalParams(min_green=4.0, max_green=30.0, gap=2.0)
    times = np.arange(0.0, 40.0, 0.2)
    # Phase 0's detectors see vehicles until t = 6 s; phase 1 waits all along.
    detected = [[t < 6.0, False] for t in times]
    states = run_controller(SignalController(params, 2), times, detected, [[True, True]] * len(times))
    yellow_at = times[[s for _, s in states].index(YELLOW)]
    assert yellow_at == pytest.approx(6.0 + params.gap, abs=0.21)  # gap-out, long before max green
    # No vehicle waits for the other phase: the green rests past max green.
    states = run_controller(SignalController(params, 2), times, detected, [[True, False]] * len(times))
    assert all(s == (0, GREEN) for s in states)


@pytest.mark.parametrize("spec", ["pr", "fifo", "aim", "signal"])
def test_baselines_no_collisions_on_busy_scenarios(spec):
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    planner = make_planner(spec)
    for seed in (2000, 2001):
        scenario = generate_scenario("4way", 40.0, seed, rate_range=(0.4, 0.5))
        log, _ = run_episode(env, planner, scenario, 40.0, seed=seed)
        assert len(log) > 20 and int(log["collided"].sum()) == 0


def test_fullthrottle_is_a_named_planner_with_the_class_specs_report_name():
    """``fullthrottle`` (the main job's strongest baseline behind the shield) is a planner word: the
    same planner and report name as ``envs/planners/adversarial.py:FullThrottle``, so reports of both agree."""
    from envs.planners import check_planner_spec, planner_name

    assert check_planner_spec("FullThrottle+shield") == "fullthrottle+shield"
    assert planner_name("fullthrottle+shield") == planner_name("envs/planners/adversarial.py:FullThrottle+shield")
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    env.reset(seed=0)
    for _ in range(30):
        env.step(env.action_space.sample() * 0)
    scene = env.unwrapped.scene()
    assert scene.num_vehicles > 0
    np.testing.assert_array_equal(make_planner("fullthrottle").act(scene), np.full(scene.num_vehicles, scene.a_max))
