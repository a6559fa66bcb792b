"""``lookahead + shield`` served beside ``glide + shield``: the latency of each step through the server's default
path (the fast path, ``--workers 1``, ``--time-limit 1``), the CPU each step costs the planning process, and the
searches that ran beside the steps.

Two servers run at once, one per planner, each with one stream. The scenes (``--scene``):

- ``long`` (default): a closed loop on the 4-way with ``--approach`` m roads outside the junction (default 200; the
  4-way's own 80 m approaches hold about 55 vehicles in closed loop whatever the demand), written as a SUMO network
  and served as the layout ``net:FILE`` (the ``sumo`` extra). A generated scenario at ``--rate`` veh/s per lane
  (default 1.5 on every lane, arrivals at least ``--min-headway`` 0.5 s apart: more than the junction serves), at
  most ``--vehicles`` at once (default 100), filled for ``--warmup`` s (default 40) by glide + shield in this
  process before serving: the scenes hold 100 vehicles from the first step served.
- ``4way``: the same closed loop on the 4-way itself (about 55 vehicles).
- ``dense``: the synthetic dense scene of ``benchmarks/bench_serve.py`` (the same vehicles at every step, the time
  advancing): nothing moves, so after 10 s the shield's liveness watchdog hands both planners' steps to FIFO.

``--loop shared`` (default): one simulation, moved by the second planner's answers (``lookahead``'s traffic); at
every tick both planners are stepped on its scene, the order swapped each tick, so both plan the same scenes under
the same load. ``--loop each``: a simulation per planner, each moved by its own planner's answers, served in turns of
``--turn`` steps (default 50; 0: both at every tick), so that ``glide``'s steps are not timed beside ``lookahead``'s
search. Steps go at the policy period in wall time (``--pace``, default 1: real time, as vehicles send their scenes;
0: back to back). The last step of each stream goes over HTTP (JSON), whose answer reports the searches of
``lookahead``: started, applied, late, dropped, expired, replaced processes and the age of the windows in force.
``CPU per step`` is the planning process's own CPU time over the run (its search process not counted) per step.

Usage::

    PYTHONPATH=$PWD python benchmarks/bench_serve_lookahead.py --steps 300           # about 2 minutes
    PYTHONPATH=$PWD python benchmarks/bench_serve_lookahead.py --steps 3000
    PYTHONPATH=$PWD python benchmarks/bench_serve_lookahead.py --steps 1000 --loop each
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_serve import SimpleCar, _ms, dense_scene, start_server, stop_server  # noqa: E402


def long_network(access: float, folder: str) -> str:
    """The 4-way with ``access`` m roads outside the junction, written as a SUMO network: its layout name
    ``net:FILE`` (the 4-way's own 80 m approaches hold about 55 vehicles in closed loop, whatever the demand)."""
    from envs.simulation.layouts import build_layout
    from envs.simulation.sumo_network import write_network

    return "net:" + str(write_network(build_layout("4way", access_length=access), Path(folder) / "net").net_file)


def closed_loop(args: argparse.Namespace, layout: str | None, seed: int):
    """The 4-way environment (on ``layout``, ``None``: its own) on a generated scenario at ``args.rate``, holding
    at most ``args.vehicles``, filled for ``args.warmup`` s by glide + shield in this process."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)
    from envs.evaluation.harness import evaluation_env_kwargs
    from envs.planners import make_planner
    from envs.simulation.traffic import generate_scenario

    config = {"max_vehicles": args.vehicles, **({"layout": layout} if layout else {})}
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({"config": config}))
    duration = args.warmup + args.steps * 0.2 + 60.0
    scenario = generate_scenario(layout or "4way", duration, seed, rate_range=(args.rate,) * 2,
                                 minor_factor=args.minor_factor, min_headway=args.min_headway)  # fmt: skip
    env.reset(seed=seed, options={"scenario": scenario})
    filler = make_planner("glide+shield")
    filler.reset(seed)
    for _ in range(int(round(args.warmup / env.unwrapped.scene().dt))):
        scene = env.unwrapped.scene()
        env.step(env.unwrapped.accelerations_to_action(filler.act(scene.copy())))
    return env


def _turns(steps: int, turn: int) -> list[tuple[int, int]]:
    """``(step, planner)`` in the order they are served: ``turn`` steps of one planner, then of the other, the
    first of a pair of turns swapped each time; ``turn`` 0: both at every tick, the order swapped each tick."""
    if turn == 0:
        return [(k, i) for k in range(steps) for i in ((0, 1) if k % 2 else (1, 0))]
    order = []
    for block, first in enumerate(range(0, steps, turn)):
        pair = (0, 1) if block % 2 else (1, 0)
        for i in pair:
            order += [(k, i) for k in range(first, min(first + turn, steps))]
    return order


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="steps per stream (default: 300)")
    parser.add_argument("--vehicles", type=int, default=100, help="at most this many vehicles at once")
    parser.add_argument("--pace", type=float, default=1.0, help="wall seconds per policy period (1: real time)")
    parser.add_argument("--planners", nargs=2, default=["glide+shield", "lookahead+shield"])
    parser.add_argument("--scene", choices=["long", "4way", "dense"], default="long")
    parser.add_argument("--approach", type=float, default=200.0, help="--scene long: roads' length outside [m]")
    parser.add_argument("--loop", choices=["shared", "each"], default="shared",
                        help="shared: one simulation, moved by the second planner's answers, both planners stepped "
                             "on each of its scenes; each: a simulation per planner, served in turns")  # fmt: skip
    parser.add_argument("--turn", type=int, default=50, help="--loop each: steps per planner turn (0: both per tick)")
    parser.add_argument("--warmup", type=float, default=40.0, help="seconds of scene time filled before serving")
    parser.add_argument("--rate", type=float, default=1.5, help="demand of the closed loop [veh/s per major lane]")
    parser.add_argument("--minor-factor", type=float, default=1.0, help="the minor lanes' demand, a share of --rate")
    parser.add_argument("--min-headway", type=float, default=0.5, help="least seconds between two arrivals on a lane")
    args = parser.parse_args()
    if args.scene == "dense":
        args.loop = "shared"
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"command: python {' '.join(sys.argv)}")
    print(f"load average before: {' '.join(f'{x:.1f}' for x in os.getloadavg())}\n")
    with tempfile.TemporaryDirectory() as folder:
        layout = long_network(args.approach, folder) if args.scene == "long" else None
        serve(args, layout)
    print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


def _order(args: argparse.Namespace) -> list[tuple[int, int]]:
    """``(step, planner)`` in the order they are served: per tick both, the order swapped each tick (``--loop
    shared``, or ``--turn 0``); else in turns of ``--turn`` steps."""
    return _turns(args.steps, 0 if args.loop == "shared" else args.turn)


def serve(args: argparse.Namespace, layout: str | None) -> None:
    """Serve both planners (see the module docstring), and print the table."""
    from envs.serve.client import PlannerClient, RemotePlannerError
    from envs.serve.wire import scene_to_wire

    scene, builder = dense_scene(min(args.vehicles, 100))
    cars = [SimpleCar(**v) for v in scene_to_wire(scene)["vehicles"]]
    loops = {"dense": 0, "long": 1, "4way": 1}[args.scene] * (1 if args.loop == "shared" else 2)
    envs = [closed_loop(args, layout, 0) for _ in range(loops)]
    config = {"max_vehicles": max(args.vehicles, 64), **({"layout": layout} if layout else {})}
    servers = [start_server(planner, "--env-kwargs", json.dumps({"config": config}), "--time-limit", "1")
               for planner in args.planners]  # fmt: skip
    counts: list[list[int]] = [[], []]
    times: list[list[float]] = [[], []]
    failed, loads = [0, 0], []
    try:
        clients = [PlannerClient(url) for _, url in servers]
        streams = [client.open(layout or "4way", dt=scene.dt, seed=0) for client in clients]
        planning = [planning_pid(process.pid) for process, _ in servers]
        cpu = [own_cpu_s(pid) for pid in planning]
        order = _order(args)
        both = args.loop == "shared" or args.turn == 0
        start = time.perf_counter()
        for tick, (k, i) in enumerate(order):
            env = envs[0 if args.loop == "shared" else i] if envs else None
            at_t = env.unwrapped.scene() if env else builder.scene("4way", k * scene.dt, cars)
            counts[i].append(at_t.num_vehicles)
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
            if env and (args.loop == "each" or i == 1):  # the shared simulation moves by the second's answers
                env.step(env.unwrapped.accelerations_to_action(acc))
            if tick % 50 == 0:
                loads.append(os.getloadavg()[0])
            # one policy period per step of each stream: in turns a step a period, both per tick two a period
            wait = start + (tick + 1) * scene.dt * args.pace * (0.5 if both else 1.0) - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        cpu = [(own_cpu_s(pid) - before) / len(t) for pid, before, t in zip(planning, cpu, times)]
        report(args, times, failed, counts, loads, cpu, clients[1])
    finally:
        for process, _ in servers:
            stop_server(process)


def planning_pid(server: int) -> int:
    """The planning process of a server started with ``--workers 1`` (its one child; Linux ``/proc``)."""
    children = Path(f"/proc/{server}/task/{server}/children").read_text().split()
    if len(children) != 1:
        raise RuntimeError(f"server {server}: expected one planning process, found {children}")
    return int(children[0])


def own_cpu_s(pid: int) -> float:
    """CPU time (user + system) of process ``pid`` itself, its children's not counted [s] (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def report(args, times, failed, counts, loads, cpu, searcher) -> None:
    """The latency table, the ratios and the searches."""
    served = (
        "one simulation moved by the second planner's answers, both stepped on each scene (the order swapped each tick)"
        if args.loop == "shared"
        else f"a simulation each, served in turns of {args.turn} steps"
    )
    where = {"long": f"the 4-way with {args.approach:g} m approaches", "4way": "the 4-way"}.get(args.scene, "dense")
    print(f"scene: {args.scene} ({where}); {served}; load average during: mean {np.mean(loads):.1f}, "
          f"max {max(loads):.1f}\n")  # fmt: skip
    print("| planner | vehicles per step (mean, max) | steps | failed | over 1 s | p50 [ms] | p99 [ms] | max [ms] | "
          "CPU per step [ms] |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|")  # fmt: skip
    ms = []
    for i, planner in enumerate(args.planners):
        p50, p99, worst = _ms(times[i])
        ms.append((p50, p99))
        over = int(np.sum(np.array(times[i]) > 1.0))
        print(f"| {planner} | {np.mean(counts[i]):.0f}, {max(counts[i])} | {len(times[i])} | {failed[i]} | {over} | "
              f"{p50:.1f} | {p99:.1f} | {worst:.1f} | {cpu[i] * 1e3:.1f} |")  # fmt: skip
    print(f"\n{args.planners[1]} / {args.planners[0]}: p50 {ms[1][0] / ms[0][0]:.2f}x, p99 {ms[1][1] / ms[0][1]:.2f}x, "
          f"CPU per step of the planning process {cpu[1] / cpu[0]:.2f}x")  # fmt: skip
    report = searcher.last_search
    if report is not None:
        print("searches beside the steps: " + ", ".join(f"{key} {value:g}" for key, value in report.items()))
    totals = searcher.health().get("searches")
    if totals is not None:
        print("/health, searches since the start: " + ", ".join(f"{k} {v:g}" for k, v in totals.items()))


if __name__ == "__main__":
    main()
