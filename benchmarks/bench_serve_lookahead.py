"""``lookahead + shield`` served beside ``glide + shield``: the latency of each step through the server's default
path (the fast path, ``--workers 1``, ``--time-limit 1``), and the searches that ran beside the steps.

Two servers run at once, one per planner, each with one stream. Each stream drives its own simulation in closed
loop (``--scene run``, the default): a generated 4-way scenario at ``--rate`` veh/s per lane (default 1.5 on every
lane, arrivals at least ``--min-headway`` 0.5 s apart: more than the junction serves, so its approaches stay full),
at most ``--vehicles`` vehicles at once (default 100), each step the server's accelerations applied. The 4-way's
80 m approaches hold about 55 vehicles in closed loop whatever the demand; 100 fit only the synthetic scene, which
puts vehicles on the exits and inside the junction too. ``--scene dense``
sends instead the synthetic dense scene of ``benchmarks/bench_serve.py`` (the same vehicles at every step, the time
advancing): nothing moves, so after 10 s the shield's liveness watchdog hands both planners' steps to FIFO. At every
tick the client steps both (the order swapped each tick, so that the load hits both alike), at the policy period in
wall time (``--pace``, default 1: real time, as vehicles send their scenes; 0: back to back). The last step of each
stream goes over HTTP (JSON), whose answer reports the searches of ``lookahead``: started, applied, late, dropped,
expired, replaced processes and the age of the windows in force.

Usage::

    PYTHONPATH=$PWD python benchmarks/bench_serve_lookahead.py --steps 300           # about 2 minutes
    PYTHONPATH=$PWD python benchmarks/bench_serve_lookahead.py --steps 3000 --vehicles 100
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_serve import SimpleCar, _ms, dense_scene, start_server, stop_server  # noqa: E402


def closed_loop(args: argparse.Namespace, seed: int):
    """The 4-way environment on a generated scenario at ``args.rate``, holding at most ``args.vehicles``."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)
    from envs.evaluation.harness import evaluation_env_kwargs
    from envs.simulation.traffic import generate_scenario

    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({"config": {"max_vehicles": args.vehicles}}))
    duration = args.steps * 0.2 + 60.0
    scenario = generate_scenario("4way", duration, seed, rate_range=(args.rate,) * 2, minor_factor=args.minor_factor,
                                 min_headway=args.min_headway)  # fmt: skip
    env.reset(seed=seed, options={"scenario": scenario})
    return env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="steps per stream (default: 300)")
    parser.add_argument("--vehicles", type=int, default=100)
    parser.add_argument("--pace", type=float, default=1.0, help="wall seconds per policy period (1: real time)")
    parser.add_argument("--planners", nargs=2, default=["glide+shield", "lookahead+shield"])
    parser.add_argument("--scene", choices=["run", "dense"], default="run")
    parser.add_argument("--rate", type=float, default=1.5, help="demand of --scene run [veh/s per major lane]")
    parser.add_argument("--minor-factor", type=float, default=1.0, help="the minor lanes' demand, a share of --rate")
    parser.add_argument("--min-headway", type=float, default=0.5, help="least seconds between two arrivals on a lane")
    args = parser.parse_args()
    from envs.serve.client import PlannerClient, RemotePlannerError
    from envs.serve.wire import scene_to_wire

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"command: python {' '.join(sys.argv)}")
    print(f"load average before: {' '.join(f'{x:.1f}' for x in os.getloadavg())}\n")
    scene, builder = dense_scene(min(args.vehicles, 100))
    cars = [SimpleCar(**v) for v in scene_to_wire(scene)["vehicles"]]
    envs = [closed_loop(args, seed) for seed in (0, 0)] if args.scene == "run" else None
    counts: list[int] = []
    kwargs = json.dumps({"config": {"max_vehicles": max(args.vehicles, 64)}})
    servers = [start_server(planner, "--env-kwargs", kwargs, "--time-limit", "1") for planner in args.planners]
    try:
        clients = [PlannerClient(url) for _, url in servers]
        streams = [client.open("4way", dt=scene.dt, seed=0) for client in clients]
        times: list[list[float]] = [[] for _ in servers]
        failed = [0, 0]
        start = time.perf_counter()
        for k in range(args.steps):
            for i in (0, 1) if k % 2 else (1, 0):
                at_t = envs[i].unwrapped.scene() if envs else builder.scene("4way", k * scene.dt, cars)
                counts.append(at_t.num_vehicles)
                tic = time.perf_counter()
                try:
                    if k == args.steps - 1:  # the last over JSON: its answer reports the searches
                        acc = clients[i].step(streams[i], scene_to_wire(at_t))
                    else:
                        acc = clients[i].step_scene(streams[i], at_t)
                except RemotePlannerError as error:
                    if not failed[i]:
                        print(f"{args.planners[i]}: first failure at step {k}: {error}")
                    failed[i] += 1
                    acc = np.zeros(at_t.num_vehicles)
                times[i].append(time.perf_counter() - tic)
                if envs:
                    envs[i].step(envs[i].unwrapped.accelerations_to_action(acc))
            wait = start + (k + 1) * scene.dt * args.pace - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        print(f"scene: {args.scene}, vehicles per step: mean {np.mean(counts):.0f}, max {max(counts)}\n")
        print("| planner | vehicles | steps | failed | over 1 s | p50 [ms] | p99 [ms] | max [ms] |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|")
        ms = []
        for i, planner in enumerate(args.planners):
            p50, p99, worst = _ms(times[i])
            ms.append((p50, p99))
            over = int(np.sum(np.array(times[i]) > 1.0))
            print(f"| {planner} | {args.vehicles} | {len(times[i])} | {failed[i]} | {over} | {p50:.1f} | {p99:.1f} | "
                  f"{worst:.1f} |")  # fmt: skip
        print(f"\n{args.planners[1]} / {args.planners[0]}: p50 {ms[1][0] / ms[0][0]:.2f}x, "
              f"p99 {ms[1][1] / ms[0][1]:.2f}x")  # fmt: skip
        report = clients[1].last_search
        if report is not None:
            print("searches beside the steps: " + ", ".join(f"{key} {value:g}" for key, value in report.items()))
        totals = clients[1].health().get("searches")
        if totals is not None:
            print("/health, searches since the start: " + ", ".join(f"{k} {v:g}" for k, v in totals.items()))
    finally:
        for process, _ in servers:
            stop_server(process)
    print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
