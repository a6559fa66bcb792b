"""Paired per-scenario differences between planners of *different* ``sb3-graph evaluate`` reports.

The reports must have run the same scenario files (checked byte for byte); their ``metrics.csv``
rows are joined and :func:`envs.evaluation.comparison.paired_differences` is taken against ``--baseline``::

    python scripts/paired.py reports/main100 reports/shield100_adversarial --baseline FullThrottle+shield
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import pandas as pd

from envs.evaluation.comparison import paired_differences


def scenario_digests(report: Path) -> dict[str, str]:
    """``file name -> sha256`` of a report's scenario files."""
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted((report / "scenarios").glob("*.json"))}


def joined_runs(reports: list[Path]) -> pd.DataFrame:
    """The ``metrics.csv`` rows of every report, after checking that they share their scenarios.

    :param reports: ``sb3-graph evaluate`` report folders
    :return: the rows, one per planner and run
    :raises ValueError: naming a report whose scenarios differ from the first one's
    """
    first = scenario_digests(reports[0])
    frames = []
    for report in reports:
        digests = scenario_digests(report)
        shared = set(first) & set(digests)
        if not shared or any(first[k] != digests[k] for k in shared):
            raise ValueError(f"{report}: its scenario files differ from those of {reports[0]}")
        frames.append(pd.read_csv(report / "metrics.csv"))
    runs = pd.concat(frames, ignore_index=True)
    return runs.drop_duplicates(subset=["planner", "scenario"], keep="first")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", type=Path, nargs="+", help="sb3-graph evaluate report folders")
    parser.add_argument("--baseline", required=True, help="report name of the reference planner")
    args = parser.parse_args(argv)
    for report in args.reports:
        if not (report / "metrics.csv").is_file():
            parser.error(f"reports: {report / 'metrics.csv'} does not exist (an sb3-graph evaluate report folder?)")
    try:
        runs = joined_runs(args.reports)
    except ValueError as err:
        parser.error(str(err))
    names = sorted(runs["planner"].unique())
    if args.baseline not in names:
        parser.error(f"--baseline: {args.baseline!r} is not a planner of these reports; allowed: {names}")
    table = paired_differences(runs, baseline=args.baseline)
    print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
