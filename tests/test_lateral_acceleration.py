"""No planner exceeds the lateral-acceleration limit at any sub-step, on any layout (curvature from the headings)."""

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401
from envs.evaluation.harness import evaluation_env_kwargs
from envs.simulation.traffic import generate_scenario

ENVS = {"4way": "CoopIntersection4Way-v0", "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}


def _curvature(layout, route: np.ndarray, arc: np.ndarray) -> np.ndarray:
    """Curvature at points on routes, independently of the speed limits: the sampled heading's change
    over the sample interval the point lies in (:meth:`Layout.pose` interpolates the heading linearly)."""
    last = layout.heading.shape[1] - 1
    i = np.minimum(np.maximum(arc / layout.ds, 0.0), last).astype(np.int64)
    i = np.minimum(i, last - 1)
    return np.abs(layout.heading[route, i + 1] - layout.heading[route, i]) / layout.ds


@pytest.mark.parametrize("layout", sorted(ENVS))
def test_full_throttle_stays_within_the_lateral_limit_at_every_sub_step(layout):
    env = gym.make(ENVS[layout], **evaluation_env_kwargs(None))
    base = env.unwrapped
    env.reset(seed=1, options={"scenario": generate_scenario(layout, 40.0, 1)})
    sim = base.sim
    limit = sim.layout.lateral_acceleration
    worst, checked, curved = 0.0, 0, 0
    for _ in range(200):
        n = sim.num_vehicles
        route = sim.route.copy()
        env.step(base.accelerations_to_action(np.full(n, base.config["max_acceleration"])))
        speed, arc = sim.last_trajectory
        if n == 0:
            continue
        kappa = _curvature(sim.layout, route[None, :], arc[1:])
        lateral = speed[1:] ** 2 * kappa
        worst = max(worst, float(lateral.max()))
        checked += lateral.size
        curved += int((lateral > 0.5 * limit).sum())
    assert checked > 1000 and curved > 50  # vehicles did drive through the curves near the limit
    assert worst <= limit + 0.05, f"{layout}: {worst:.2f} m/s^2 lateral, limit {limit}"
