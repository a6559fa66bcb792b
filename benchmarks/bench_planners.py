"""Cost per policy step of each planner against the simulation's own step cost.

Every planner runs through the same generated evaluation scenarios in the evaluation harness's
environment (``collision_handling="remove"``), in one process, one torch thread (as the
harness's workers). Per policy step it measures the process's CPU time (``time.process_time``:
on a shared machine less disturbed by other processes than wall time), separately:

- ``plan``: ``planner.act(scene)`` (for a shielded planner: the wrapped planner plus the shield),
- ``step``: ``env.step(action)`` (the simulation),
- ``scene``: ``env.unwrapped.scene()`` (the snapshot every planner reads).

The reference ``sim`` is ``env.step`` under a trivial planner (every vehicle keeps its speed);
``ratio`` is a planner's ``plan`` over that reference. ``shield`` is the share of the shielded
planner's time spent in the shield's check, ``interv`` its interventions, ``rounds`` its
predictions per policy step (one per round of overrides) and ``periods`` the policy periods each
prediction covered. Each run is repeated ``--repeat`` times and every
column reports its smallest value.

``--lockstep`` adds a row ``gnn (lockstep xK)``: the ``K = --scenarios`` scenarios run side by side,
one environment each, and the GNN answers all ``K`` scenes of a step in one forward pass
(``GNNPlanner.act_many``); ``plan`` is then per scene, the planner's time over the ``K`` scenes.

Usage::

    PYTHONPATH=$PWD python benchmarks/bench_planners.py                      # all planners
    PYTHONPATH=$PWD python benchmarks/bench_planners.py --planners aim aim+shield --scenarios 1
    PYTHONPATH=$PWD python benchmarks/bench_planners.py --planners gnn --scenarios 4 --lockstep
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs
from envs.planners import make_planner
from envs.planners.adversarial import FullThrottle
from envs.planners.base import Planner
from envs.planners.shield import Shield
from envs.simulation.scene import Scene
from envs.simulation.traffic import generate_scenario

GNN = str(Path(__file__).resolve().parents[1] / "envs" / "pretrained" / "coop_4way" / "best_model.safetensors")
PLANNERS = (
    "pr", "fifo", "aim", "signal", "gnn",
    "pr+shield", "fifo+shield", "aim+shield", "signal+shield", "gnn+shield", "fullthrottle+shield",
)  # fmt: skip


class Cruise(Planner):
    """The trivial planner of the reference: every vehicle keeps its speed."""

    def __init__(self) -> None:
        super().__init__("cruise")

    def act(self, scene: Scene) -> np.ndarray:
        return np.zeros(scene.num_vehicles)


class _Timed(Planner):
    """Times the wrapped planner's ``act`` (inside a shield: the proposal, without the check)."""

    def __init__(self, planner: Planner) -> None:
        super().__init__(planner.name)
        self.planner = planner
        self.seconds = 0.0

    def reset(self, seed: int | None = None) -> None:
        self.planner.reset(seed)

    def act(self, scene: Scene) -> np.ndarray:
        tic = time.process_time()
        out = self.planner.act(scene)
        self.seconds += time.process_time() - tic
        return out


def build(word: str) -> tuple[Planner, _Timed | None]:
    """The planner of a benchmark word, and the timer around the proposal of a shielded one."""
    if word == "cruise":
        return Cruise(), None
    if word.endswith("+shield"):
        inner, _ = build(word[: -len("+shield")])
        timed = _Timed(inner)
        return Shield(timed), timed
    if word == "fullthrottle":
        return FullThrottle(), None
    return make_planner(GNN if word == "gnn" else word), None


def run(env, planner: Planner, timed: _Timed | None, scenarios, seed: int) -> dict[str, float]:
    """Run one planner through the scenarios; mean milliseconds per policy step."""
    base = env.unwrapped
    plan = step = snap = 0.0
    steps = vehicles = 0
    if timed is not None:
        timed.seconds = 0.0
    rollouts = [0, 0]  # the shield's predictions, and the periods they predicted
    if isinstance(planner, Shield):
        predict = type(planner).predict

        def counted(scene, plan, command):
            arcs, speeds = predict(planner, scene, plan, command)
            rollouts[0] += 1
            rollouts[1] += (len(arcs) - 1) // max(1, int(round(planner.simulation_frequency * scene.dt)))
            return arcs, speeds

        planner.predict = counted
    for k, scenario in enumerate(scenarios):
        env.reset(seed=seed + k, options={"scenario": scenario})
        planner.reset(seed + k)
        done = False
        while not done:
            tic = time.process_time()
            scene = base.scene()
            toc = time.process_time()
            acc = np.asarray(planner.act(scene), float)
            tac = time.process_time()
            _, _, terminated, truncated, _ = env.step(base.accelerations_to_action(acc))
            snap += toc - tic
            plan += tac - toc
            step += time.process_time() - tac
            steps += 1
            vehicles += scene.num_vehicles
            done = terminated or truncated
    out = {"plan": plan, "step": step, "scene": snap}
    out = {key: 1e3 * value / steps for key, value in out.items()}
    out["vehicles"] = vehicles / steps
    out["steps"] = steps
    if timed is not None:
        out["shield"] = 1.0 - timed.seconds / plan
    if isinstance(planner, Shield):
        out["interventions"] = planner.interventions
        out["rounds"] = rollouts[0] / steps
        out["periods"] = rollouts[1] / max(rollouts[0], 1)
    return out


def run_lockstep(side: list, planner, scenarios, seed: int) -> dict[str, float]:
    """Run the scenarios side by side (scenario ``k`` in ``side[k]``), the GNN answering the scenes
    of every step at once; mean milliseconds per scene and policy step."""
    bases = [env.unwrapped for env in side]
    plan = step = snap = 0.0
    steps = vehicles = 0
    for k, (env, scenario) in enumerate(zip(side, scenarios)):
        env.reset(seed=seed + k, options={"scenario": scenario})
    running = list(range(len(side)))
    while running:
        tic = time.process_time()
        scenes = [bases[k].scene() for k in running]
        toc = time.process_time()
        answers = planner.act_many(scenes)
        tac = time.process_time()
        done = []
        for k, acc in zip(running, answers):
            _, _, terminated, truncated, _ = side[k].step(bases[k].accelerations_to_action(np.asarray(acc, float)))
            if terminated or truncated:
                done.append(k)
        snap += toc - tic
        plan += tac - toc
        step += time.process_time() - tac
        steps += len(running)
        vehicles += sum(scene.num_vehicles for scene in scenes)
        running = [k for k in running if k not in done]
    out = {"plan": plan, "step": step, "scene": snap}
    out = {key: 1e3 * value / steps for key, value in out.items()}
    out.update(vehicles=vehicles / steps, steps=steps)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planners", nargs="+", default=list(PLANNERS), help=f"any of {PLANNERS}")
    parser.add_argument("--env", default="CoopIntersection4Way-v0")
    parser.add_argument("--scenarios", type=int, default=2, help="generated scenarios (seeds seed, seed + 1, ...)")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of traffic per scenario")
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=2, help="runs per planner; each column reports its minimum")
    parser.add_argument(
        "--lockstep", action="store_true", help="add the GNN with the scenarios run side by side, batched"
    )
    args = parser.parse_args()
    try:
        import torch

        torch.set_num_threads(1)  # as the harness's workers
    except ImportError:
        pass
    env = gym.make(args.env, **evaluation_env_kwargs(None))
    layout = env.unwrapped.layout
    scenarios = [generate_scenario(layout, args.duration, args.seed + k) for k in range(args.scenarios)]
    def best(word: str) -> dict[str, float]:
        runs = [run(env, *build(word), scenarios, args.seed) for _ in range(args.repeat)]
        return {key: min(r[key] for r in runs) for key in runs[0]}

    reference = best("cruise")
    sim = reference["step"]
    print(f"{args.env}: {args.scenarios} scenarios x {args.duration:g} s, {reference['steps']} policy steps each")
    header = f"{'planner':<22}{'plan ms':>9}{'ratio':>7}{'step ms':>9}{'scene ms':>9}"
    header += f"{'veh':>6}{'shield':>8}{'interv':>8}{'rounds':>8}{'periods':>8}"
    print(header)
    print(f"{'sim (cruise)':<22}{'':>9}{'':>7}{sim:9.2f}{reference['scene']:9.2f}{reference['vehicles']:6.1f}")
    for word in args.planners:
        r = best(word)
        shield = f"{100 * r['shield']:7.0f}%" if "shield" in r else ""
        interv = f"{r['interventions']:8d}{r['rounds']:8.2f}{r['periods']:8.1f}" if "interventions" in r else ""
        print(
            f"{word:<22}{r['plan']:9.2f}{r['plan'] / sim:7.2f}{r['step']:9.2f}{r['scene']:9.2f}"
            f"{r['vehicles']:6.1f}{shield:>8}{interv}",
            flush=True,
        )
    if args.lockstep:
        side = [gym.make(args.env, **evaluation_env_kwargs(None)) for _ in scenarios]
        runs = [run_lockstep(side, make_planner(GNN), scenarios, args.seed) for _ in range(args.repeat)]
        r = {key: min(run[key] for run in runs) for key in runs[0]}
        word = f"gnn (lockstep x{len(scenarios)})"
        print(
            f"{word:<22}{r['plan']:9.2f}{r['plan'] / sim:7.2f}{r['step']:9.2f}{r['scene']:9.2f}{r['vehicles']:6.1f}",
            flush=True,
        )
        for other in side:
            other.close()
    env.close()


if __name__ == "__main__":
    main()
