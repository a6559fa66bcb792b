"""The shield within its declared bounds: the prediction under latency and lag (compiled, against the NumPy oracle),
the stopping bound the rules read under them, the widening of a perceived scene, and an exact scene left as it is."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
from test_shield import BLAMED, Fixed, _assert_prediction_is_numpy
from test_shield_bounds import AT_BOUNDS

import envs  # noqa: F401
from envs.evaluation.harness import evaluation_env_kwargs
from envs.planners import DECLARED_BOUNDS, ShieldBounds, _shield_kernel
from envs.planners.adversarial import FullThrottle
from envs.planners.shield import _STANDING, Shield
from envs.simulation.engine import Simulation, integrate
from envs.simulation.faults import Actuator
from envs.simulation.layouts import build_layout
from envs.simulation.traffic import demand_scenario


def _perceived(scene, rng, age=None):
    """A scene as the fault model hands it: with uncertainty, ages, realised accelerations and commands in flight."""
    n = scene.num_vehicles
    return dataclasses.replace(
        scene,
        arc_std=np.full(n, 0.5),
        speed_std=np.full(n, 0.2),
        age=rng.uniform(0.1, 1.0, n) if age is None else age,
        acceleration=rng.uniform(scene.a_min, scene.a_max, n),
        command=rng.uniform(scene.a_min, scene.a_max, n),
    )


@pytest.mark.parametrize("layout", ["4way", "3way", "inD"])
def test_the_prediction_under_latency_and_lag_is_bitwise_the_numpy_prediction(layout):
    """Random perceived scenes, and the scenes of a run at the declared bounds (full throttle behind the shield)."""
    lay = build_layout(layout)
    rng = np.random.default_rng(5)
    shield = Shield(Fixed(), bounds=DECLARED_BOUNDS)
    BLAMED.clear()
    for count in (1, 2, 5, 12, 25) * 3:
        sim = Simulation(lay)
        route = rng.integers(0, lay.num_routes, count)
        sim.add(route, rng.uniform(0.0, 15.0, count), np.arange(count), arc=rng.uniform(0.0, lay.length[route] - 1.0))
        sim.speed[rng.random(count) < 0.3] = 0.0
        scene = _perceived(sim.scene(), rng)
        plan = shield._plan(scene)
        assert plan.actuation is not None and plan.widen is not None
        _assert_prediction_is_numpy(shield, scene, rng.uniform(scene.a_min, scene.a_max, count))
        _assert_prediction_is_numpy(shield, scene, shield._fallback(scene, plan, plan.arc, plan.speed))
    env_id = {"4way": "CoopIntersection4Way-v0", "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}
    kwargs = evaluation_env_kwargs({"config": {"faults": AT_BOUNDS}})
    env = gym.make(env_id[layout], **kwargs)
    env.reset(seed=3, options={"scenario": demand_scenario(env.unwrapped.layout, 15.0, 3, 0.5)})
    shield, done, checked = Shield(FullThrottle(), bounds=DECLARED_BOUNDS), False, 0
    while not done:
        scene = env.unwrapped.scene()
        if scene.num_vehicles:
            assert scene.acceleration is not None and scene.command is not None and scene.arc_std is not None
            _assert_prediction_is_numpy(shield, scene, np.full(scene.num_vehicles, scene.a_max))
            checked += 1
        _, _, terminated, truncated, _ = env.step(env.unwrapped.accelerations_to_action(shield.act(scene)))
        done = terminated or truncated
    assert checked > 20 and len(BLAMED) > 5
    env.close()


def test_the_reach_speed_bounds_the_stop_under_latency_and_lag():
    """Braking at a_max through the plant's actuator (latency 0.1 s, lag 0.3 s) from any realised acceleration and
    command in flight stops a vehicle within v'^2 / (2 a_max) of where it is, v' the reach speed."""
    rng = np.random.default_rng(0)
    n, a_max, h, substeps = 4000, 5.0, 1 / 15, 3
    lay = build_layout("4way")
    speed = np.where(rng.random(n) < 0.2, 0.0, rng.uniform(0.0, 6.0, n))  # under the route's speed limits
    realised, previous = rng.uniform(-a_max, a_max, n), rng.uniform(-a_max, a_max, n)
    actuator = Actuator(0.1, 0.3, substeps, h)
    ids = np.arange(n)
    actuator.memory.store(ids, command=previous, realised=realised)
    route = np.zeros(n, np.int64)
    arc, v = np.full(n, 1.0), speed.copy()
    start = arc.copy()
    for _ in range(60):  # 12 s: every vehicle stops
        acc = actuator(ids, np.full(n, -a_max), v)
        v_all, x_all, _ = integrate(lay, route, arc, v, acc, substeps, h, 1e9, 1e9)
        arc, v = x_all[-1], v_all[-1]
    assert (v == 0).all()
    reach = _shield_kernel.reach_speeds(speed, realised, previous, a_max, 0.3, 0.1, _STANDING)
    travelled = arc - start
    assert (travelled <= reach**2 / (2 * a_max) + 0.05).all()
    assert (travelled > speed**2 / (2 * a_max) + 0.5).any()  # the lag matters: braking at once would not bound it
    moving = speed > 0
    assert (reach[moving] ** 2 / (2 * a_max) - travelled[moving]).max() < 0.05  # and the bound is tight


def test_an_exact_scene_costs_nothing_and_a_perceived_one_is_widened():
    lay = build_layout("4way")
    sim = Simulation(lay)
    sim.add(np.array([0, 0]), np.array([10.0, 10.0]), np.arange(2), arc=np.array([30.0, 45.0]))
    exact = sim.scene()
    declared, none = Shield(FullThrottle(), bounds=DECLARED_BOUNDS), Shield(FullThrottle())
    plan, plain = declared._plan(exact), none._plan(exact)
    assert plan.widen is None and plan.actuation is None
    for name in ("hull_start", "hull_end", "follow_gap", "cross_lo", "cross_hi", "merge_sep", "pad"):
        np.testing.assert_array_equal(getattr(plan, name), getattr(plain, name))
    rng = np.random.default_rng(1)
    scene = _perceived(exact, rng, age=np.array([0.1, 1.0]))
    plan = declared._plan(scene)
    np.testing.assert_allclose(plan.widen, [3.1, 4.0])  # the position bound plus the speed bound over the age
    np.testing.assert_allclose(plan.hull_start, plain.hull_start - plan.widen)
    np.testing.assert_allclose(plan.follow_gap, plain.follow_gap - 7.1)  # both vehicles' widening
    # bounds without faults of a kind leave that part out
    assert Shield(FullThrottle(), bounds=ShieldBounds(lag=0.3))._plan(scene).widen is None
    assert Shield(FullThrottle(), bounds=ShieldBounds(position=3.0))._plan(scene).actuation is None

