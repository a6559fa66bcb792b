"""Does every planner of a report keep traffic moving? A deadlock check on ``sb3-graph evaluate`` output.

For each planner: runs, collided vehicles, the lowest flow rate of a run, and the runs in which no
vehicle crossed the intersection during the last ``--window`` seconds (a run with waiting vehicles
and no crossing at its end is stuck). Reads ``metrics.csv`` and ``vehicles.csv`` of the report::

    python scripts/liveness.py reports/main100 --window 10
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd


def liveness(report: Path, window: float) -> pd.DataFrame:
    """One row per planner: runs, collided, lowest run flow, runs without a crossing at the end.

    :param report: an ``sb3-graph evaluate`` report folder
    :param window: the last seconds of a run in which some vehicle must cross [s]
    :return: the table
    """
    runs = pd.read_csv(report / "metrics.csv")
    vehicles = pd.read_csv(report / "vehicles.csv")
    end = runs.set_index(["planner", "run"])["duration_s"]
    vehicles = vehicles.join(end, on=["planner", "run"])
    late = vehicles[vehicles["crossed"] >= vehicles["duration_s"] - window]
    moving = late.groupby(["planner", "run"]).size()
    rows = []
    for planner, group in runs.groupby("planner", sort=False):
        keys = [(planner, r) for r in group["run"]]
        waiting = group.set_index("run")["waiting_at_end"]
        stuck = [r for p, r in keys if moving.get((p, r), 0) == 0 and waiting.get(r, 0) > 0]
        rows.append(
            {
                "planner": planner,
                "runs": len(group),
                "collided": int(group["collided"].sum()),
                "vehicles": int(group["vehicles_scheduled"].sum()),
                "lowest_flow": float(group["flow_rate"].min()),
                f"stuck_runs (no crossing in the last {window:g} s)": len(stuck),
            }
        )
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="an sb3-graph evaluate report folder")
    parser.add_argument("--window", type=float, default=10.0, help="last seconds of a run checked [s] (> 0)")
    args = parser.parse_args(argv)
    if args.window <= 0:
        parser.error(f"--window must be > 0, got {args.window}")
    for name in ("metrics.csv", "vehicles.csv"):
        if not (args.report / name).is_file():
            parser.error(f"report: {args.report / name} does not exist (an sb3-graph evaluate report folder?)")
    print(liveness(args.report, args.window).to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
