"""Run one scenario of a report past its end: does the traffic drain, or is it stuck for good?

The scenario's schedule is kept (no new vehicles after its end); the run goes on to ``--until``
seconds and prints the crossings after the scenario's end, the last crossing and the vehicles left::

    python scripts/drain.py reports/shield100_adversarial 2 \\
        --planner envs/planners/adversarial.py:FullThrottle+shield --until 200
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

import envs  # noqa: F401 - registers the environments
from envs.planners import make_planner
from envs.traffic import Scenario


def drain(scenario: Scenario, planner_spec: str, seed: int, until: float, env_id: str) -> dict[str, float]:
    """Run ``scenario`` with the planner to ``until`` seconds.

    :return: ``crossings_after_end``, ``last_crossing`` [s], ``left_in_scene``, ``collisions``
    """
    end = scenario.duration
    env = gym.make(env_id, config={"collision_handling": "remove"})
    base = env.unwrapped
    planner = make_planner(planner_spec)
    env.reset(seed=seed, options={"scenario": dataclasses.replace(scenario, duration=until)})
    planner.reset(seed)
    crossings: list[float] = []
    collisions = 0
    while True:
        acc = np.asarray(planner.act(base.scene()), float)
        _, _, terminated, truncated, info = env.step(base.accelerations_to_action(acc))
        crossings += [info["time"]] * len(info["crossed"])
        collisions += len(info["collisions"])
        if terminated or truncated or info["time"] >= until - 1e-9:
            break
    times = np.asarray(crossings)
    return {
        "crossings_after_end": int((times > end).sum()),
        "last_crossing": float(times.max(initial=0.0)),
        "left_in_scene": int(base.scene().num_vehicles),
        "collisions": collisions,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="an sb3-graph evaluate report folder (its scenarios/)")
    parser.add_argument("run", type=int, help="scenario index (scenario_<run>.json; its seed is the run's)")
    parser.add_argument("--planner", required=True, help="planner spec, as for sb3-graph evaluate")
    parser.add_argument("--until", type=float, default=200.0, help="simulated seconds to run to (> the scenario's)")
    parser.add_argument("--env", default="CoopIntersection4Way-v0", help="environment id")
    args = parser.parse_args(argv)
    path = args.report / "scenarios" / f"scenario_{args.run:03d}.json"
    if not path.is_file():
        parser.error(f"run: {path} does not exist")
    scenario = Scenario.load(path)
    if args.until <= scenario.duration:
        parser.error(f"--until must exceed the scenario's duration {scenario.duration:g} s, got {args.until:g}")
    print(drain(scenario, args.planner, args.run, args.until, args.env))
    return 0


if __name__ == "__main__":
    sys.exit(main())
