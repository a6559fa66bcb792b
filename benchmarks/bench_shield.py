"""The shield's cost per decision, with and without its pruning of the pairs that cannot conflict.

Two kinds of scenes:

- ``dense N``: the synthetic scene of ``benchmarks/bench_serve.py`` (vehicles queued 6.5 m apart on every
  lane of the 4-way layout, at 90 % of the lane limit; the server's latency load), at ``--sizes``;
- ``run``: every scene of one evaluation run of ``fullthrottle+shield`` on the 4-way layout (generated
  scenario, ``--duration`` s), the proposals full throttle.

Per scene kind and planner (AIM's proposal, full throttle), CPU time per decision (``time.process_time``)
of ``Shield.check`` (the shield alone) and of ``Shield.act`` (the planner and the shield), the pruning
on (``Shield._prune``, the default) and off, interleaved call by call in one process so that the load of
a shared machine hits both alike; each cell is the median over ``--repeat`` rounds. ``ratio`` is the
unpruned time over the pruned one. Every decision is checked to be the same bit for bit both ways.
The pairs column counts the crossing and merging pairs the check reads (pruned / all).

Usage::

    PYTHONPATH=$PWD python benchmarks/bench_shield.py                  # about a minute
    PYTHONPATH=$PWD python benchmarks/bench_shield.py --sizes 100 --repeat 50
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_serve import dense_scene  # noqa: E402

import envs  # noqa: E402, F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs  # noqa: E402
from envs.planners import AIMPlanner  # noqa: E402
from envs.planners.adversarial import FullThrottle  # noqa: E402
from envs.planners.base import Planner  # noqa: E402
from envs.planners.shield import Shield  # noqa: E402
from envs.simulation.scene import Scene  # noqa: E402
from envs.simulation.traffic import generate_scenario  # noqa: E402


def run_scenes(duration: float, seed: int) -> list[Scene]:
    """The scenes of one ``fullthrottle+shield`` run on the 4-way layout."""
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs(None))
    env.reset(seed=seed, options={"scenario": generate_scenario("4way", duration, seed)})
    shield, scenes, done = Shield(FullThrottle()), [], False
    while not done:
        scene = env.unwrapped.scene()
        if scene.num_vehicles:
            scenes.append(scene)
        _, _, terminated, truncated, _ = env.step(env.unwrapped.accelerations_to_action(shield.act(scene)))
        done = terminated or truncated
    env.close()
    return scenes


def pairs(shield: Shield, scene: Scene) -> int:
    plan = shield._plan(scene)
    return len(plan.cross) + len(plan.merge)


def measure(scenes: list[Scene], make: type[Planner], repeat: int, seed: int) -> dict[str, float]:
    """Median CPU ms per decision of ``check`` and ``act``, pruned and not, interleaved (each shield
    with a planner of its own, and the proposals of a third)."""
    pruned, full, planner = Shield(make(), watchdog_after=None), Shield(make(), watchdog_after=None), make()
    for p in (pruned, full, planner):
        p.reset(seed)
    full._prune = False
    proposals = [np.asarray(planner.act(scene), float) for scene in scenes]
    for scene, proposal in zip(scenes, proposals):  # the same decisions, bit for bit (and compiled)
        a, b = pruned.check(scene, proposal), full.check(scene, proposal)
        if not (np.array_equal(a, b) and np.array_equal(pruned.last_overridden, full.last_overridden)):
            raise AssertionError(f"pruned and full shields differ at t = {scene.time}")
    times = {key: [] for key in ("check", "check_full", "act", "act_full")}
    for _ in range(repeat):
        spent = dict.fromkeys(times, 0.0)
        for scene, proposal in zip(scenes, proposals):
            for key, call, args in (
                ("check", pruned.check, (scene, proposal)),
                ("check_full", full.check, (scene, proposal)),
                ("act", pruned.act, (scene,)),
                ("act_full", full.act, (scene,)),
            ):
                tic = time.process_time()
                call(*args)
                spent[key] += time.process_time() - tic
        for key in times:
            times[key].append(1e3 * spent[key] / len(scenes))
    out = {key: float(np.median(value)) for key, value in times.items()}
    out["pairs"] = float(np.mean([pairs(pruned, s) for s in scenes]))
    out["pairs_full"] = float(np.mean([pairs(full, s) for s in scenes]))
    out["vehicles"] = float(np.mean([s.num_vehicles for s in scenes]))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 50, 100], help="dense scene sizes")
    parser.add_argument("--repeat", type=int, default=30, help="rounds per cell (median) (default: 30)")
    parser.add_argument("--duration", type=float, default=30.0, help="simulated seconds of the run scenes")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    load = os.getloadavg()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average {load[0]:.1f}")
    print("CPU ms per decision (median over rounds); ratio = without pruning / with pruning\n")
    print(
        "| scenes | vehicles | planner | pairs (pruned / all) | check | check, all pairs | ratio "
        "| act | act, all pairs | ratio |"
    )
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    kinds = [(f"dense {n}", [dense_scene(n)[0]]) for n in args.sizes]
    kinds.append((f"run ({args.duration:g} s)", run_scenes(args.duration, args.seed)))
    for kind, scenes in kinds:
        for make in (AIMPlanner, FullThrottle):
            repeat = args.repeat if len(scenes) == 1 else max(1, args.repeat // 10)
            r = measure(scenes, make, repeat, args.seed)
            print(
                f"| {kind} | {r['vehicles']:.0f} | {make().name} | {r['pairs']:.0f} / {r['pairs_full']:.0f} "
                f"| {r['check']:.2f} | {r['check_full']:.2f} | {r['check_full'] / r['check']:.1f}x "
                f"| {r['act']:.2f} | {r['act_full']:.2f} | {r['act_full'] / r['act']:.1f}x |",
                flush=True,
            )
    print(f"\nload average after: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
