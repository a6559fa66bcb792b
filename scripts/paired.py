"""Paired per-scenario differences between planners of *different* ``sb3-graph evaluate`` reports.

The reports must have run the same scenario files (checked byte for byte); their ``metrics.csv``
rows are joined and :func:`envs.evaluation.comparison.paired_differences` is taken against ``--baseline``::

    python scripts/paired.py reports/main100 reports/shield100_adversarial --baseline FullThrottle+shield

``LABEL=REPORT`` prefixes that report's planner names with ``LABEL:`` (two reports whose planners share
names, e.g. the seeds of two weight sets), and ``--pool-seeds`` turns a planner's training seeds into
one planner, named as ``sb3-graph aggregate`` names the configuration (``seed_0`` ... -> ``seed_*``,
``--seed-pattern`` as there): its metrics are averaged per scenario over the seeds, so that a set of
seeds is compared with another per scenario::

    python scripts/paired.py default=reports/w/default tuned=reports/w/tuned --pool-seeds \
        --baseline 'default:RL:seed_*+shield'
"""

from __future__ import annotations

import argparse
import hashlib
import re
import sys
from pathlib import Path

import pandas as pd

from envs.commands.aggregate import compile_seed_pattern, seeds_pooled, split_label
from envs.evaluation.comparison import PAIRED_METRICS, paired_differences
from sb3_graph.commands import UserError


def scenario_digests(report: Path) -> dict[str, str]:
    """``file name -> sha256`` of a report's scenario files."""
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted((report / "scenarios").glob("*.json"))}


def joined_runs(reports: list[Path], labels: list[str] | None = None) -> pd.DataFrame:
    """The ``metrics.csv`` rows of every report, after checking that they share their scenarios.

    :param reports: ``sb3-graph evaluate`` report folders
    :param labels: one per report: ``""`` or a prefix for its planner names (``LABEL:planner``)
    :return: the rows, one per planner and run
    :raises ValueError: naming a report whose scenarios differ from the first one's
    """
    labels = labels or [""] * len(reports)
    first = scenario_digests(reports[0])
    frames = []
    for report, label in zip(reports, labels):
        digests = scenario_digests(report)
        shared = set(first) & set(digests)
        if not shared or any(first[k] != digests[k] for k in shared):
            raise ValueError(f"{report}: its scenario files differ from those of {reports[0]}")
        frame = pd.read_csv(report / "metrics.csv")
        if label:
            frame["planner"] = label + ":" + frame["planner"].astype(str)
        frames.append(frame)
    runs = pd.concat(frames, ignore_index=True)
    return runs.drop_duplicates(subset=["planner", "scenario"], keep="first")


def pool_seeds(runs: pd.DataFrame, pattern: re.Pattern) -> pd.DataFrame:
    """One planner per set of training seeds (named by :func:`envs.commands.aggregate.seeds_pooled`),
    its metrics averaged per scenario over the seeds.

    :param runs: rows of :func:`joined_runs`
    :param pattern: from :func:`envs.commands.aggregate.compile_seed_pattern`
    :return: one row per pooled planner and scenario (the paired metrics only)
    """
    named = runs.assign(planner=runs["planner"].astype(str).map(lambda name: seeds_pooled(pattern, name)))
    metrics = [metric for metric in PAIRED_METRICS if metric in named]  # older reports lack the newer ones
    return named.groupby(["planner", "scenario"], as_index=False)[metrics].mean()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+", help="sb3-graph evaluate report folders, each [LABEL=]REPORT")
    parser.add_argument("--baseline", required=True, help="report name of the reference planner")
    parser.add_argument("--pool-seeds", action="store_true", help="average each planner's training seeds per scenario")
    parser.add_argument(
        "--seed-pattern", default=r"seed_(\d+)", help="regular expression, its first group the seed in a planner name"
    )
    args = parser.parse_args(argv)
    labels, paths = zip(*(split_label(item) for item in args.reports))
    reports = [Path(path) for path in paths]
    for report in reports:
        if not (report / "metrics.csv").is_file():
            parser.error(f"reports: {report / 'metrics.csv'} does not exist (an sb3-graph evaluate report folder?)")
    try:
        runs = joined_runs(reports, list(labels))
    except ValueError as err:
        parser.error(str(err))
    if args.pool_seeds:
        try:
            runs = pool_seeds(runs, compile_seed_pattern(args.seed_pattern))
        except UserError as err:
            parser.error(str(err))
    names = sorted(runs["planner"].unique())
    if args.baseline not in names:
        parser.error(f"--baseline: {args.baseline!r} is not a planner of these reports; allowed: {names}")
    table = paired_differences(runs, baseline=args.baseline)
    print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
