"""The cost of one ``lookahead`` search, as a ratio to one shielded simulation step measured in the same run.

Scenes:

- ``run N``: scenes of a ``fullthrottle+shield`` run on the 4-way layout at 0.5 veh/s per major lane whose
  vehicle count is within 4 of ``N`` (``--run-sizes``, default 30: the goal's 30-vehicle search);
- ``dense N``: the synthetic scene of ``benchmarks/bench_serve.py`` (vehicles queued 6.5 m apart on every lane
  at 90 % of the limit), at ``--sizes`` (default 20, 50, 100).

Per scene kind, interleaved call by call so that the load of a shared machine hits both alike: one search of
:class:`~envs.planners.lookahead.LookaheadPlanner` (its default parameters, or ``--rollout-frequency`` and
``--per-approach``) and one ``fullthrottle+shield`` decision plus the simulation step it drives
(``Simulation.step``), the reference. Each cell is the median wall time over the scenes and ``--repeat``
rounds, one thread, after a warm-up that compiles. ``--workers`` (default 1, 2 and 4) counts the processes of a
search; a count above the cores runs oversubscribed, for its critical path (its wall time then means little).

Per search, the table counts the rollout steps on the critical path (per wave, the longest share of one process:
the search's wall time on idle cores, in rollout steps, whatever the load) and the searches that the step budget cut
(``step_budget``). Besides the wall ratio it prices the critical path by CPU time: one worker's CPU time per rollout
step x the critical path / a shielded step's CPU time, the ratio an idle machine gives, which a loaded one's wall
times do not. The 4-way layout's synthetic scene holds at most 116 vehicles: 200 has no scene there.

Usage::

    PYTHONPATH=$PWD python benchmarks/bench_lookahead.py                 # a few minutes
    PYTHONPATH=$PWD python benchmarks/bench_lookahead.py --sizes 20 --run-sizes 30 --repeat 3
    PYTHONPATH=$PWD python benchmarks/bench_lookahead.py --profile     # where a 30-vehicle search's time goes

``--profile`` runs the searches of the ``run`` scenes under cProfile and prints the share of a search in the
shield's check (and in its predictions), in glide's plan (and in its reservations), and in the simulation's
step, with the shield's predictions per rollout step.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_serve import dense_scene  # noqa: E402

import envs  # noqa: E402, F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs  # noqa: E402
from envs.planners import make_planner  # noqa: E402
from envs.planners.lookahead import LookaheadParams, LookaheadPlanner  # noqa: E402
from envs.planners.search_workers import available_cores  # noqa: E402
from envs.simulation.engine import Simulation  # noqa: E402
from envs.simulation.scene import Scene  # noqa: E402
from envs.simulation.traffic import generate_scenario  # noqa: E402


def run_scenes(size: int, seed: int = 3, slack: int = 4, most: int = 12) -> list[Scene]:
    """Up to ``most`` scenes (spread over the run) of a busy ``fullthrottle+shield`` run with ``size`` +- ``slack``
    vehicles."""
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs(None))
    env.reset(seed=seed, options={"scenario": generate_scenario("4way", 80.0, seed, rate_range=(0.5, 0.5))})
    planner, scenes, done = make_planner("fullthrottle+shield"), [], False
    planner.reset(seed)
    while not done:
        scene = env.unwrapped.scene()
        if abs(scene.num_vehicles - size) <= slack:
            scenes.append(scene)
        _, _, terminated, truncated, _ = env.step(env.unwrapped.accelerations_to_action(planner.act(scene)))
        done = terminated or truncated
    env.close()
    return scenes[:: max(1, len(scenes) // most)][:most]


def step_of(scene: Scene) -> Simulation:
    """A simulation set to ``scene`` (the reference's step runs in it)."""
    sim = Simulation(scene.layout, max_vehicles=max(256, scene.num_vehicles), max_acceleration=float(scene.a_max))
    width = np.full(scene.num_vehicles, 2.0) if scene.width is None else scene.width
    sim.set_state(scene.time, scene.route, scene.vehicle_id, scene.arc, scene.speed, scene.length, width, scene.humans)
    return sim


def measure(
    scenes: list[Scene], params: LookaheadParams, repeat: int, workers: list[int]
) -> tuple[dict[int, float], float, dict[int, tuple[float, ...]], dict[int, float]]:
    """Median wall ms of a search with each count of ``workers`` and of a shielded step, interleaved (a step before
    each search); per search: rollouts, rollout steps, rollout steps on the critical path (the longest process's
    share, wave by wave: the search's wall time on idle cores, in rollout steps) and the share of searches shrunk;
    and per count of workers, the critical path in shielded steps by CPU time (one worker's CPU time per rollout
    step x the critical path / a shielded step's CPU time; needs 1 among ``workers``)."""
    search: dict[int, list[float]] = {w: [] for w in workers}
    step, step_cpu, search_cpu = [], [], 0.0
    planners = {w: LookaheadPlanner(params=_with_workers(params, w)) for w in workers}
    shield = make_planner("fullthrottle+shield")
    shield.reset(0)
    for planner in planners.values():
        planner.reset(0)
        planner._search(scenes[0])  # warm-up: compiles the kernels, starts the helpers
    step_of(scenes[0]).step(shield.act(scenes[0]))
    before = {w: (p.rollouts, p.rollout_steps, p.critical_steps, p.shrunk) for w, p in planners.items()}
    for _ in range(repeat):
        for scene in scenes:
            for w, planner in planners.items():
                sim = step_of(scene)
                tic, cpu = time.perf_counter(), time.process_time()
                sim.step(shield.act(scene))
                step.append(time.perf_counter() - tic)
                step_cpu.append(time.process_time() - cpu)
                tic, cpu = time.perf_counter(), time.process_time()
                planner._search(scene)
                search[w].append(time.perf_counter() - tic)
                if w == 1:  # one process: all of the search's CPU time is this process's
                    search_cpu += time.process_time() - cpu
    per_search = {
        w: tuple((now - then) / max(1, len(search[w])) for now, then in zip((p.rollouts, p.rollout_steps,
                                                                             p.critical_steps, p.shrunk), before[w]))
        for w, p in planners.items()
    }  # fmt: skip
    for planner in planners.values():
        planner.close()
    # The critical path priced at one process's CPU time per rollout step, over a shielded step's CPU time: the
    # search / step ratio on idle cores, which a loaded machine's wall times do not give.
    per_step = search_cpu / max(1, planners[1].rollout_steps - before[1][1]) if 1 in planners else float("nan")
    estimate = {w: per_search[w][2] * per_step / float(np.median(step_cpu)) for w in planners}
    wall = {w: 1e3 * float(np.median(t)) for w, t in search.items()}
    return wall, 1e3 * float(np.median(step)), per_search, estimate


def _with_workers(params: LookaheadParams, workers: int) -> LookaheadParams:
    """``params`` with ``workers`` processes, also more than the cores (which ``LookaheadParams`` refuses): the
    benchmark times them oversubscribed, for their critical path, which does not depend on the cores."""
    if workers <= available_cores():
        return replace(params, workers=workers)
    params = replace(params, workers=None)
    object.__setattr__(params, "workers", workers)  # past the check on purpose (see above)
    return params


def profile(scenes: list[Scene], params: LookaheadParams, repeat: int) -> None:
    """Print the shares of a search's time in its parts (cumulative cProfile times over ``repeat`` rounds)."""
    import cProfile
    import pstats

    planner = LookaheadPlanner(params=params)
    planner.reset(0)
    planner._search(scenes[0])  # compiles the kernels
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(repeat):
        for scene in scenes:
            planner._search(scene)
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # (file, line, name) -> (calls, primitive calls, own, cumulative, callers)

    def cumulative(path: str, name: str) -> tuple[int, float]:
        rows = [v for (f, _, n), v in stats.items() if f.endswith(path) and n == name]
        return sum(r[1] for r in rows), sum(r[3] for r in rows)

    searches, total = cumulative("envs/planners/lookahead.py", "_search")
    steps = cumulative("envs/planners/shield.py", "check")[0]
    predictions = cumulative("envs/planners/shield.py", "predict")[0]
    print(
        f"{searches} searches of {np.mean([s.num_vehicles for s in scenes]):.0f} vehicles on average, "
        f"{1e3 * total / max(searches, 1):.0f} ms each under the profiler"
    )
    print(
        f"{steps / max(searches, 1):.0f} rollout steps per search, {predictions / max(steps, 1):.1f} shield "
        "predictions per rollout step\n"
    )
    print("| part | share of a search |\n|---|---:|")
    for label, path, name in (
        ("the shield's check", "envs/planners/shield.py", "check"),
        ("  of which its predictions", "envs/planners/shield.py", "predict"),
        ("glide's plan", "envs/planners/glide.py", "act"),
        ("  of which its reservations (AIM's)", "envs/planners/aim.py", "reserve"),
        ("the simulation's step", "envs/simulation/engine.py", "step"),
    ):
        print(f"| {label} | {100 * cumulative(path, name)[1] / total:.0f} % |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[20, 50, 100, 200])
    parser.add_argument("--run-sizes", type=int, nargs="*", default=[30])
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--rollout-frequency", type=int, default=LookaheadParams().rollout_frequency)
    parser.add_argument("--per-approach", choices=("true", "false"), default=None,
                        help="the greedy pass per approach road (default: lookahead's default)")  # fmt: skip
    parser.add_argument("--workers", type=int, nargs="*", default=[1, 2, 4],
                        help="processes per search (a count above the cores is reported, not run)")  # fmt: skip
    parser.add_argument("--profile", action="store_true", help="where a search's time goes (cProfile), then exit")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    per_approach = LookaheadParams().per_approach if args.per_approach is None else args.per_approach == "true"
    params = LookaheadParams(rollout_frequency=args.rollout_frequency, per_approach=per_approach)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, one thread")
    print(f"command: python {' '.join(sys.argv)}")
    print(f"lookahead: {params}\n")
    if args.profile:
        profile(run_scenes(args.run_sizes[0] if args.run_sizes else 30), params, args.repeat)
        return
    cores = available_cores()
    workers = [w for w in args.workers if w >= 1]
    print(f"load average before: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print("| scenes | vehicles | workers | rollouts per search | rollout steps (critical path) | searches shrunk | "
          "search [ms] | shielded step [ms] | search / step: wall (critical path by CPU time) | "
          "against 1 worker: wall (critical path) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    kinds = [(f"run {n}", run_scenes(n)) for n in args.run_sizes]
    for n in args.sizes:
        try:
            kinds.append((f"dense {n}", [dense_scene(n)[0]]))
        except ValueError as error:  # the layout's approaches hold fewer
            kinds.append((f"dense {n}: {error}", []))
    for label, scenes in kinds:
        if not scenes:
            print(f"| {label} | no scene of that size | | | | | | | | |")
            continue
        rounds = args.repeat if label.startswith("run") else 3 * args.repeat
        search, step, rollouts, estimate = measure(scenes, params, rounds, workers)
        vehicles = np.mean([s.num_vehicles for s in scenes])
        for w in workers:
            count, steps, critical, shrunk = rollouts[w]
            against = ""
            if workers[0] == 1:
                against = f"{search[w] / search[1]:.2f}x ({critical / rollouts[1][2]:.2f}x)"
            over = f" (over the {cores} cores)" if w > cores else ""
            print(
                f"| {label} | {vehicles:.0f} | {w}{over} | {count:.1f} | {steps:.0f} ({critical:.0f}) | "
                f"{100 * shrunk:.0f} % | {search[w]:.1f} | {step:.2f} | {search[w] / step:.0f} ({estimate[w]:.0f}) | "
                f"{against} |"
            )
    print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
