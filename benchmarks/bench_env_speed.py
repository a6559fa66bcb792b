"""Speed of the cooperative intersection environment against stock highway-env ``intersection-v0``.

Measures policy steps per wall-clock second and simulated seconds per wall-clock second (two
units: at our 5 Hz policy one policy step is 0.2 simulated seconds, at stock highway-env's 1 Hz
one step is 1 simulated second), both environments in the same process, with the graph
observation built every policy step (15 Hz simulation, 5 Hz policy) and about 20 vehicles,
against stock ``intersection-v0`` in its default configuration (1 Hz policy, about 10 vehicles)
and with about 20 vehicles. Then the cost per policy step for 10, 20, 50 and 100 vehicles.
Prints markdown tables with the machine, the load, the torch threads and the command; every
figure carries its unit in its column name.

Run: ``python benchmarks/bench_env_speed.py [--seconds 5] [--clock cpu]`` (with ``--clock cpu`` the
rates are per CPU second of this process, and the column names say so).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the environments)
from envs.planners import make_planner

# The clock of every measurement: wall time (default), or this process's CPU time (--clock cpu),
# which a busy shared machine inflates far less (the loop is single-threaded).
CLOCK = [time.perf_counter]


def _time_ours(seconds: float, spawn_probability: float, seed: int = 0) -> dict[str, float]:
    """Our env with traffic as under a real planner: FIFO's accelerations drive it (collision-free),
    and only ``env.step`` (simulation sub-steps, reward, graph observation) is timed."""
    env = gym.make(
        "CoopIntersection4Way-v0", config={"spawn_probability": spawn_probability, "duration": 1e6}
    )
    env.reset(seed=seed)
    base = env.unwrapped
    planner = make_planner("fifo")

    def action():
        return base.accelerations_to_action(planner.act(base.scene()))

    for _ in range(300):  # warm up to a steady traffic level
        env.step(action())
    steps, counts, wall = 0, [], 0.0
    while wall < seconds:
        act = action()
        start = CLOCK[0]()
        info = env.step(act)[-1]
        wall += CLOCK[0]() - start
        counts.append(info["num_vehicles"])
        steps += 1
    dt = 1.0 / base.config["policy_frequency"]
    return {
        "sim_per_wall": steps * dt / wall,
        "steps_per_s": steps / wall,
        "vehicles": float(np.mean(counts)),
    }


def _time_stock(seconds: float, config: dict, target: int = 0, seed: int = 0) -> dict[str, float]:
    """Stock ``intersection-v0`` stepping IDLE; with ``target`` > 0 the road is topped up to about
    that many vehicles between steps (its own spawner saturates near 12; top-up time not counted)."""
    import highway_env  # noqa: F401

    env = gym.make("intersection-v0", config=config)
    env.reset(seed=seed)
    base = env.unwrapped
    rng = np.random.default_rng(seed)
    pf = base.config["policy_frequency"]
    steps, counts, wall = 0, [], 0.0
    while wall < seconds:
        for _ in range(10 if target else 0):
            if len(base.road.vehicles) >= target:
                break
            base._spawn_vehicle(longitudinal=float(rng.uniform(0, 80)), spawn_probability=1.0)
        start = CLOCK[0]()
        _, _, terminated, truncated, _ = env.step(1)  # IDLE
        wall += CLOCK[0]() - start
        counts.append(len(base.road.vehicles))
        steps += 1
        if truncated or (terminated and not target):
            env.reset()
    return {
        "sim_per_wall": steps / pf / wall,
        "steps_per_s": steps / wall,
        "vehicles": float(np.mean(counts)),
    }


def _time_fixed(n: int, seconds: float, seed: int = 0) -> dict[str, float]:
    """Cost per policy step with ``n`` vehicles spread over all routes (no spawning, slow speeds
    so that nobody leaves during the measurement)."""
    env = gym.make(
        "CoopIntersection4Way-v0",
        config={
            "spawn_probability": 0.0,
            "initial_spawn_probability": 0.0,
            "max_vehicles": 128,
            "max_edges": 16384,
            "duration": 1e6,
        },
    )
    rng = np.random.default_rng(seed)
    lay = None
    zeros = np.zeros(128, np.float32)
    steps = 0
    wall = 0.0
    while wall < seconds:
        env.reset(seed=seed)
        lay = env.unwrapped.layout
        route = rng.integers(0, lay.num_routes, n)
        arc = rng.uniform(3.0, lay.length[route] - 40.0)
        env.unwrapped.place_vehicles(route, arc, rng.uniform(0.5, 2.0, n))
        start = CLOCK[0]()
        for _ in range(50):
            env.step(zeros)
        wall += CLOCK[0]() - start
        steps += 50
    return {"ms_per_step": 1e3 * wall / steps, "steps_per_s": steps / wall, "sim_per_wall": steps * 0.2 / wall}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="measured time per measurement")
    parser.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall: perf_counter; cpu: process_time, for a machine that other work keeps busy",
    )
    args = parser.parse_args(argv)
    CLOCK[0] = time.perf_counter if args.clock == "wall" else time.process_time
    warnings.filterwarnings("ignore")
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover
        pass

    ours = _time_ours(args.seconds, spawn_probability=0.035)
    stock_default = _time_stock(args.seconds, {})
    stock_20 = _time_stock(
        args.seconds, {"initial_vehicle_count": 20, "spawn_probability": 0.0, "duration": 10_000}, target=20
    )

    threads = torch.get_num_threads() if "torch" in sys.modules else "n/a"
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    print(f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, "
          f"Python {platform.python_version()}, NumPy {np.__version__}, torch threads {threads}, "
          f"load average {load}, clock {args.clock}")  # fmt: skip
    print(f"Command: python {' '.join(sys.argv)}\n")
    per = "wall s" if args.clock == "wall" else "CPU s"
    header = ["environment", "policy Hz", "mean vehicles", f"policy steps / {per}", f"simulated s / {per}"]
    header.append(f"ours / this (simulated s / {per})")
    print("| " + " | ".join(header) + " |")
    print("|---|---|---|---|---|---|")
    rows = [
        ("CoopIntersection4Way-v0 (FIFO-driven traffic, graph obs every step)", 5, ours),
        ("highway-env intersection-v0, default config", 1, stock_default),
        ("highway-env intersection-v0, topped up to ~20 vehicles", 1, stock_20),
    ]
    for name, hz, r in rows:
        ratio = ours["sim_per_wall"] / r["sim_per_wall"]
        cells = [name, str(hz), f"{r['vehicles']:.1f}", f"{r['steps_per_s']:.1f}", f"{r['sim_per_wall']:.1f}"]
        print("| " + " | ".join(cells + [f"{ratio:.1f}"]) + " |")
    print(
        f"\nOurs: {ours['steps_per_s']:.1f} policy steps / {per} x 0.2 simulated s per policy step = "
        f"{ours['sim_per_wall']:.1f} simulated s / {per}."
    )

    print("\nCost growth (CoopIntersection4Way-v0, 15 Hz simulation, 5 Hz policy, graph observation):\n")
    print(f"| vehicles | ms ({args.clock}) per policy step | policy steps / {per} | simulated s / {per} "
          "| cost relative to 10 vehicles |")  # fmt: skip
    print("|---|---|---|---|---|")
    base = None
    for n in (10, 20, 50, 100):
        r = _time_fixed(n, max(args.seconds / 2, 1.0))
        base = base or r["ms_per_step"]
        cells = [f"{r['ms_per_step']:.3f}", f"{r['steps_per_s']:.1f}", f"{r['sim_per_wall']:.1f}"]
        print(f"| {n} | {' | '.join(cells)} | {r['ms_per_step'] / base:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
