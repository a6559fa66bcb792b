"""Evaluate every checkpoint of a training run against FIFO on the same scenarios.

Answers "at which step did the learned planner first beat FIFO?" for a run folder written by
``sb3-graph train``::

    python examples/learning_curve.py runs/4way --scenarios 10 --duration 100 --jobs 2

Prints a markdown table (step, median flow rate, stop ratio, collision rate) and the first
checkpoint that beats FIFO on flow and stops without collisions, and writes the table as
``learning_curve.csv`` into the run folder.
"""

from __future__ import annotations

import argparse
import re
import tempfile
from pathlib import Path

import pandas as pd

from envs.evaluation.harness import evaluate, generate_scenarios, layout_of
from envs.evaluation.metrics import summarize

CHECKPOINT = re.compile(r"model_(\d+)_steps\.zip$")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="run folder of sb3-graph train")
    parser.add_argument("--env", default="CoopIntersection4Way-v0")
    parser.add_argument("--scenarios", type=int, default=10)
    parser.add_argument("--duration", type=float, default=100.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument(
        "--max-collision-rate", type=float, default=0.001, help="share of vehicles (paper's planner: 0.00028)"
    )
    args = parser.parse_args()

    checkpoints = sorted(
        (int(m.group(1)), path)
        for path in (args.run / "checkpoints").glob("model_*_steps.zip")
        if (m := CHECKPOINT.search(path.name))
    )
    planners = [("fifo", "FIFO")] + [(str(path), f"step {step}") for step, path in checkpoints]
    with tempfile.TemporaryDirectory() as folder:
        scenarios = generate_scenarios(folder, args.scenarios, args.duration, args.seed, layout_of(args.env))
        runs, vehicles = evaluate(planners, scenarios, args.env, args.duration, args.seed, args.jobs)
    summary = summarize(runs, vehicles)
    rows = [
        {
            "planner": name,
            "flow_median": s["flow_rate"]["median"],
            "stop_ratio": s["stop_ratio"]["all"],
            "collision_rate": s["collision_rate"],
            "vehicles": s["vehicles"],
        }
        for name, s in summary.items()
    ]
    table = pd.DataFrame(rows)
    table.to_csv(args.run / "learning_curve.csv", index=False)
    print("| " + " | ".join(table.columns) + " |\n|" + "---|" * len(table.columns))
    for row in table.itertuples(index=False):
        print("| " + " | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row) + " |")
    fifo = table.iloc[0]
    better = table[
        (table.planner != "FIFO")
        & (table.flow_median > fifo.flow_median)
        & (table.stop_ratio < fifo.stop_ratio)
        & (table.collision_rate <= args.max_collision_rate)
    ]
    first = better.planner.iloc[0] if len(better) else "none"
    print(
        "\nfirst checkpoint with a higher median flow and fewer stops than FIFO and a collision rate of at most "
        f"{args.max_collision_rate:.2%}: {first}"
    )


if __name__ == "__main__":
    main()
