"""The SUMO plant against ours, and against SUMO stepping alone: what the second plant and its bridge cost.

Three sides replay the same generated scenarios (the 4-way, ``--rate`` veh/s per major lane, ``--duration``
simulated seconds, no humans) at SUMO's step of 50 ms (20 Hz simulation, 5 Hz policy):

- **ours**: :class:`envs.simulation.engine.Simulation` at 20 Hz, every vehicle at full throttle
  (``+max_acceleration``: our speed governor holds it to the lane limits), the scenario's spawns;
- **sumo plant**: :class:`envs.simulation.sumo_plant.SumoPlant`, the same commands and spawns: per sub-step one
  ``setAcceleration`` per vehicle, one ``simulationStep``, the subscription results of every vehicle and
  SUMO's collision list, and the scene's columns;
- **bare sumo**: libsumo on the same generated network, the same vehicles inserted at the times our spawns
  gave them, driven by SUMO's own model (no command, no read-back): ``simulationStep`` alone.

The sides run in turns in one process (``--repeats`` rounds, each side once per round), so the ratios compare
the same machine state; a first round warms up and does not count, then the fastest round of each side counts.
A whole ``glide+shield`` run through the environment (:func:`envs.evaluation.harness.run_episode`) is timed in
the same way on both plants (``--no-episode`` skips it). Units: simulated s per wall s, and the ratios of wall
times (SUMO plant over ours, SUMO plant over bare SUMO).

Run: ``python benchmarks/bench_sumo.py [--repeats 3] [--duration 60] [--rate 0.3] [--no-episode]``
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

from envs.simulation.engine import Simulation
from envs.simulation.layouts import build_layout
from envs.simulation.sumo_plant import SumoPlant, libsumo_module, network_of
from envs.simulation.traffic import ScenarioTraffic, generate_scenario

HZ_SIM = 20


def _drive(plant, layout, scenario) -> tuple[float, list[tuple[float, int, int]]]:
    """Full throttle through the scenario; the wall time of the steps and the spawns (time, id, route)."""
    traffic = ScenarioTraffic(layout, scenario)
    spawns = [(0.0, int(i), int(r)) for i, r in zip(*_new(plant, traffic.spawn(plant)))]
    wall = 0.0
    while plant.time < scenario.duration - 1e-9:
        acc = np.full(plant.num_vehicles, plant.max_acceleration)
        tic = time.perf_counter()
        plant.step(acc)
        wall += time.perf_counter() - tic
        now = plant.time
        spawns += [(now, int(i), int(r)) for i, r in zip(*_new(plant, traffic.spawn(plant)))]
    return wall, spawns


def _new(plant, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rows = np.isin(plant.vehicle_id, ids)
    return plant.vehicle_id[rows], plant.route[rows]


def _bare(layout, scenario, spawns) -> float:
    """SUMO alone: the same vehicles inserted at the same times, SUMO's own drivers, no read-back."""
    sumo = libsumo_module()
    net = network_of(layout)
    sumo.start(["sumo", "-n", str(net.net_file), "--step-length", f"{1 / HZ_SIM}", "--step-method.ballistic",
                "--collision.check-junctions", "--collision.action", "warn", "--time-to-teleport", "-1",
                "--no-step-log", "--no-warnings"])  # fmt: skip
    try:
        for r, edges in enumerate(net.route_edges):
            sumo.route.add(f"r{r}", list(edges))
        pending = sorted(spawns)
        k, wall, steps = 0, 0.0, int(round(scenario.duration * HZ_SIM))
        for step in range(steps):
            now = step / HZ_SIM
            while k < len(pending) and pending[k][0] <= now + 1e-9:
                _, vid, route = pending[k]
                sumo.vehicle.add(str(vid), f"r{route}", depart="now", departPos="5", departSpeed="max")
                k += 1
            tic = time.perf_counter()
            sumo.simulation.step()
            wall += time.perf_counter() - tic
        return wall
    finally:
        sumo.close()


def _episode(plant_name: str, scenario, duration: float) -> float:
    from envs.evaluation.harness import run_episode
    from envs.planners import make_planner
    from envs.simulation.env import CoopIntersectionEnv

    env = CoopIntersectionEnv({"plant": plant_name, "simulation_frequency": HZ_SIM, "collision_handling": "remove"})
    try:
        tic = time.perf_counter()
        run_episode(env, make_planner("glide+shield"), scenario, duration, seed=0)
        return time.perf_counter() - tic
    finally:
        env.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--rate", type=float, default=0.3)
    parser.add_argument("--no-episode", action="store_true")
    args = parser.parse_args()
    layout = build_layout("4way")
    scenario = generate_scenario(layout, args.duration, 0, rate_range=(args.rate, args.rate))
    best = {"ours": np.inf, "sumo plant": np.inf, "bare sumo": np.inf, "glide+shield ours": np.inf,
            "glide+shield sumo": np.inf}  # fmt: skip
    for round_ in range(args.repeats + 1):  # round 0 warms up (numba's compilation, caches) and does not count
        if round_ == 1:
            best = dict.fromkeys(best, np.inf)
        wall, spawns = _drive(Simulation(layout, simulation_frequency=HZ_SIM), layout, scenario)
        best["ours"] = min(best["ours"], wall)
        plant = SumoPlant(layout, simulation_frequency=HZ_SIM)
        try:
            best["sumo plant"] = min(best["sumo plant"], _drive(plant, layout, scenario)[0])
        finally:
            plant.close()
        best["bare sumo"] = min(best["bare sumo"], _bare(layout, scenario, spawns))
        if not args.no_episode:
            best["glide+shield ours"] = min(best["glide+shield ours"], _episode("builtin", scenario, args.duration))
            best["glide+shield sumo"] = min(best["glide+shield sumo"], _episode("sumo", scenario, args.duration))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}")
    print(f"command: python benchmarks/bench_sumo.py --repeats {args.repeats} --duration {args.duration:g} "
          f"--rate {args.rate:g}{' --no-episode' if args.no_episode else ''}")  # fmt: skip
    print(f"scenario: 4-way, {scenario.num_vehicles} vehicles in {args.duration:g} s, 20 Hz simulation, 5 Hz policy\n")
    print("| side | wall s (best of rounds) | simulated s per wall s |")
    print("|---|---|---|")
    for side, wall in best.items():
        if np.isfinite(wall):
            print(f"| {side} | {wall:.3f} | {args.duration / wall:.0f} |")
    print(f"\nfull throttle: SUMO plant / ours = {best['sumo plant'] / best['ours']:.2f}x; "
          f"SUMO plant / bare SUMO = {best['sumo plant'] / best['bare sumo']:.2f}x")  # fmt: skip
    if not args.no_episode:
        print(f"glide+shield run: SUMO plant / ours = {best['glide+shield sumo'] / best['glide+shield ours']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
