"""Where one planner's delay differs from another's, vehicle by vehicle, grouped by who stopped.

Joins the same vehicle of the same scenario under two planners of one ``sb3-graph evaluate`` report
(``vehicles.csv``; vehicles that crossed under both) and prints, for each of the four groups (stopped
under the baseline or not, under the planner or not), the count, the mean difference of delay (the
report's definition, :func:`envs.evaluation.metrics.add_travel_times`) and its share of the total::

    python scripts/delay_by_stops.py REPORT --planner GlideRecipe+shield --baseline FullThrottle+shield
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from envs.evaluation.metrics import add_travel_times
from sb3_graph.commands import UserError

KEY = ["scenario", "vehicle_id"]


def delay_by_stops(vehicles: pd.DataFrame, planner: str, baseline: str) -> pd.DataFrame:
    """The four groups of vehicles that crossed under both planners.

    :param vehicles: a report's vehicle log (``vehicles.csv``)
    :param planner: the planner compared
    :param baseline: the planner it is compared with
    :return: one row per group (``stopped_baseline``, ``stopped_planner``): ``vehicles``, ``delay_change``
        (mean, planner minus baseline [s]) and ``share`` of the summed change
    :raises UserError: a planner that the log does not hold
    """
    names = sorted(vehicles["planner"].unique())
    for name in (planner, baseline):
        if name not in names:
            raise UserError(f"planner {name!r} is not in the report (it holds {', '.join(names)})")
    timed = add_travel_times(vehicles)
    timed = timed[timed["crossed"].notna()]
    both = timed[timed["planner"] == baseline].set_index(KEY)[["stopped", "delay"]].join(
        timed[timed["planner"] == planner].set_index(KEY)[["stopped", "delay"]], how="inner", lsuffix="_baseline",
        rsuffix="_planner",
    )  # fmt: skip
    change = both["delay_planner"] - both["delay_baseline"]
    groups = change.groupby([both["stopped_baseline"], both["stopped_planner"]])
    out = pd.DataFrame({"vehicles": groups.size(), "delay_change": groups.mean(), "share": groups.sum() / change.sum()})
    out.index.names = ["stopped_baseline", "stopped_planner"]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="an sb3-graph evaluate report folder")
    parser.add_argument("--planner", required=True)
    parser.add_argument("--baseline", required=True)
    args = parser.parse_args(argv)
    path = args.report / "vehicles.csv"
    try:
        if not path.is_file():
            raise UserError(f"report: {path} does not exist (give an sb3-graph evaluate report folder)")
        table = delay_by_stops(pd.read_csv(path), args.planner, args.baseline)
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(table.round(3).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
