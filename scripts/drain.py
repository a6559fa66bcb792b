"""Run one scenario of a report past its end: does the traffic drain, or is it stuck for good?

The scenario's schedule is kept (no new vehicles after its end); the run goes on to ``--until``
seconds and prints the crossings after the scenario's end, the last crossing and the vehicles stuck::

    python scripts/drain.py reports/shield100_adversarial 2 \\
        --planner envs/planners/adversarial.py:FullThrottle+shield --until 200
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import gymnasium as gym

import envs  # noqa: F401 - registers the environments
from envs.evaluation.harness import evaluation_env_kwargs, run_episode, run_seed
from envs.planners import make_planner
from envs.simulation.traffic import Scenario


def drain(scenario: Scenario, planner_spec: str, seed: int, until: float, env_id: str) -> dict[str, float]:
    """Run ``scenario`` with the planner to ``until`` seconds, with the evaluation harness's episode.

    :return: ``crossings_after_end``, ``last_crossing`` [s], ``stuck`` (vehicles that entered and
        neither crossed nor left), ``collided`` (vehicles), ``waiting_at_end`` (not yet spawned)
    """
    env = gym.make(env_id, **evaluation_env_kwargs(None))
    longer = dataclasses.replace(scenario, duration=until)
    vehicles, facts = run_episode(env, make_planner(planner_spec), longer, until, seed=seed)
    crossed = vehicles["crossed"]
    stuck = vehicles["spawned"] & crossed.isna() & vehicles["removed"].isna()
    return {
        "crossings_after_end": int((crossed > scenario.duration).sum()),
        "last_crossing": float(crossed.max()) if crossed.notna().any() else 0.0,
        "stuck": int(stuck.sum()),
        "collided": int(vehicles["collided"].sum()),
        "waiting_at_end": facts["waiting_at_end"],
    }


def report_seed(report: Path) -> int | None:
    """The base seed of a report (the ``- seed:`` line of its ``report.md``), ``None`` if it has none."""
    path = report / "report.md"
    if path.is_file():
        for line in path.read_text().splitlines():
            if line.startswith("- seed: ") and line[8:].strip().lstrip("-").isdigit():
                return int(line[8:].strip())
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="an sb3-graph evaluate report folder (its scenarios/)")
    parser.add_argument("run", type=int, help="scenario index (scenario_<run>.json)")
    parser.add_argument("--planner", required=True, help="planner spec, as for sb3-graph evaluate")
    parser.add_argument("--until", type=float, default=200.0, help="simulated seconds to run to (> the scenario's)")
    parser.add_argument("--env", default="CoopIntersection4Way-v0", help="environment id")
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        help="the report's base seed (sb3-graph evaluate --seed; default: the seed its report.md names, else 0): "
        "the run replays with the seed the harness gave it",
    )
    args = parser.parse_args(argv)
    path = args.report / "scenarios" / f"scenario_{args.run:03d}.json"
    if not path.is_file():
        parser.error(f"run: {path} does not exist")
    scenario = Scenario.load(path)
    if args.until <= scenario.duration:
        parser.error(f"--until must exceed the scenario's duration {scenario.duration:g} s, got {args.until:g}")
    seed = args.seed if args.seed is not None else report_seed(args.report) or 0
    print(drain(scenario, args.planner, run_seed(seed, args.run), args.until, args.env))
    return 0


if __name__ == "__main__":
    sys.exit(main())
