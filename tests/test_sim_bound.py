"""The NumPy lower bound of ``benchmarks/bench_sim_bound.py`` does the simulation's work: it drives
the same trajectories, finds the same collisions and builds the same observations."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from envs.simulation.engine import Simulation
from envs.simulation.graph import NODE_FEATURES, NUM_RELATIONS, build_observation, min_mahalanobis
from envs.simulation.layouts import build_layout
from sb3_graph.common.spaces import GraphSpace

_path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_sim_bound.py"
_spec = importlib.util.spec_from_file_location("bench_sim_bound", _path)
bench = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("bench_sim_bound", bench)  # its dataclass looks its module up
_spec.loader.exec_module(bench)


@pytest.mark.parametrize("layout, n", [("4way", 20), ("4way", 60), ("inD", 30)])
def test_bound_matches_the_simulation(layout, n):
    lay = build_layout(layout)
    space = GraphSpace(bench.MAX_NODES, NODE_FEATURES, bench.MAX_EDGES, NUM_RELATIONS)
    tables = bench.tables(lay)
    rng = np.random.default_rng(n)
    route, arc, speed = bench._fleet(lay, n, rng)
    length, width = np.full(n, 5.0), np.full(n, 2.0)
    state = [route, arc, speed, length, width, *bench._pose_leaders(tables, route, arc, length)]
    sim = Simulation(lay, bench.HZ_SIM, bench.HZ_POLICY, bench.V_MAX, bench.A_MAX, bench.S_REF, bench.MAX_NODES,
                     bench.B_GOV, bench.RESOLUTION)  # fmt: skip
    sim.add(route, speed, np.arange(n), 5.0, 2.0, arc=arc)
    collisions = governed = 0
    for _ in range(15):
        acc = rng.uniform(-3.0, 3.0, n)
        events = sim.step(acc)
        scene = sim.scene()
        ours = build_observation(scene, space, bench.S_SCALE, bench.D_MAX, min_mahalanobis(scene))
        obs, pairs = bench.bound_step(tables, space, state, acc)
        assert sim.num_vehicles == n  # nobody leaves: the count the benchmark reports holds
        np.testing.assert_allclose(state[1], sim.arc, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(state[2], sim.speed, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(pairs, events.collisions)
        for key, value in ours.items():
            np.testing.assert_allclose(obs[key], value, rtol=1e-6, atol=1e-6, err_msg=key)
        collisions += len(pairs)
        governed += events.governed.size
    assert collisions > 0 and governed > 0  # the check and the governor had work to do
