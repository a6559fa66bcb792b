"""The speed governor: lane limits from curvature, held by the simulation whatever the planner asks."""

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401
from envs.simulation.layouts import build_layout


@pytest.mark.parametrize("layout", ["4way", "3way", "inD"])
def test_curved_lanes_are_limited_by_lateral_acceleration(layout):
    lay = build_layout(layout, lateral_acceleration=3.0)
    # On every sample: limit^2 * curvature <= a_lat (curvature from the sampled heading).
    # Inside arcs only: the inD through lane's straight 7.6 deg shift is a kink, not a curve.
    kappa = np.abs(np.diff(lay.heading, axis=1)) / lay.ds
    in_arc = (kappa[:, 1:] > 1e-3) & (kappa[:, :-1] > 1e-3)
    lateral = lay.speed_limit[:, 1:-1] ** 2 * kappa[:, 1:]
    assert in_arc.any() and lateral[in_arc].max() <= 3.0 * 1.05
    assert lay.speed_limit.max() == pytest.approx(10.0)
    assert lay.speed_limit.min() < 7.0  # turns are slower than the road
    assert build_layout(layout, lateral_acceleration=6.0).speed_limit.min() > lay.speed_limit.min()


def test_envelope_is_the_braking_curve_to_every_lower_limit_ahead():
    lay = build_layout("4way")
    env = lay.speed_envelope(2.0)
    assert (env <= lay.speed_limit + 1e-12).all()
    # Brute force on one route: min over samples ahead of sqrt(limit^2 + 2 b distance).
    r = lay.route_id("west->north")
    lim = lay.speed_limit[r]
    k = np.arange(lim.size)
    distance = np.maximum(k[None, :] - k[:, None], 0) * lay.ds
    ahead = np.where(k[None, :] >= k[:, None], np.sqrt(lim[None, :] ** 2 + 2 * 2.0 * distance), np.inf)
    np.testing.assert_allclose(env[r], ahead.min(axis=1))


@pytest.mark.parametrize("command", [5.0, "random"])
@pytest.mark.parametrize("env_id", ["CoopIntersection4Way-v0", "CoopIntersectionInD-v0"])
def test_no_planner_exceeds_a_lane_limit(env_id, command):
    """Full throttle and random commands: never above the lane limit, and the governor brakes for a
    turn at no more than its deceleration (it starts early enough)."""
    env = gym.make(env_id, config={"collision_handling": "remove", "spawn_probability": 0.1})
    env.reset(seed=1)
    sim = env.unwrapped.sim
    rng = np.random.default_rng(0)
    b, h = sim.governor_deceleration, 1 / sim.simulation_frequency
    governed = 0
    for _ in range(150):
        n = env.action_space.shape[0]
        action = np.ones(n) if command == 5.0 else rng.uniform(-1, 1, n)
        route_before = sim.route.copy()
        _, _, term, trunc, info = env.step(action.astype(np.float32))
        scene = env.unwrapped.scene()
        assert (scene.speed <= scene.speed_limit + 1e-9).all()
        speed, arc = sim.last_trajectory
        assert (speed[1:] <= sim.layout.limit_at(np.broadcast_to(route_before, speed[1:].shape), arc[1:]) + 1e-9).all()
        if command == 5.0:  # braking only ever comes from the governor here
            assert (np.diff(speed, axis=0) >= -b * h * 1.05).all()
        governed += info["governed"].size
        if term or trunc:
            env.reset()
    assert governed > 0
