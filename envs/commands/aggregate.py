"""``sb3-graph aggregate``: IQM and 95 % intervals of the task metrics over seeds and scenarios.

Input: ``sb3-graph evaluate`` reports (folders holding ``metrics.csv``, or the CSV files), one row
per planner and scenario. A planner trained with ``sb3-graph train --seeds`` is named after its
run folder, ``RL:seed_0``, ``RL:seed_1``...; the seed is read from that name (``--seed-pattern``)
and the runs of all seeds form one configuration, ``RL:seed_*``. Each input may carry a label,
``LABEL=PATH`` (default: the folder's name), that prefixes its configurations, so two trainings
(e.g. Table I weights and tuned weights) stay apart::

    sb3-graph train --config zoo_configs/td3.yml --env CoopIntersection4Way-v0 --seeds 0 1 2 --out runs/table1
    sb3-graph evaluate --planner pr --planner runs/table1/seed_0/best_model.zip \\
        --planner runs/table1/seed_1/best_model.zip --planner runs/table1/seed_2/best_model.zip \\
        --scenarios 20 --seed 0 --out reports/table1
    sb3-graph aggregate table1=reports/table1 tuned=reports/tuned --out reports/aggregate

Evaluate every input on the same scenarios (the same ``--seed`` and ``--scenarios``, or
``--scenario-dir``): the scenario file name is the task of the stratified bootstrap.

Per configuration and metric: the interquartile mean over all its runs (seeds x scenarios), the
percentile interval of the stratified bootstrap (scenarios are the strata, as rliable's tasks:
the interval is the spread over seeds, and a configuration with one run per scenario, such as a
deterministic baseline, gets a point; ``--bootstrap iid`` resamples all runs together, so that the
scenarios count as drawn too; see :mod:`sb3_graph.aggregate`), mean, median and the numbers of
runs, seeds and scenarios. Written
into ``--out`` (which must not exist): ``aggregate.csv``, ``aggregate.md`` and ``runs.csv`` (the
pooled input rows with their configuration and seed).
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import TYPE_CHECKING

from sb3_graph.commands import UserError
from sb3_graph.commands.arguments import seed_value

if TYPE_CHECKING:  # pandas loads when the command runs, not for --help
    import pandas as pd

DEFAULT_METRICS = ("flow_rate", "stop_ratio_all", "delay_mean", "collision_rate")
DEFAULT_SEED_PATTERN = r"seed_(\d+)"
CONFIGURATION, SEED, TASK = "configuration", "seed", "scenario"
# Most bootstrap resamples (rliable uses 50,000); the resampling holds resamples x runs numbers.
MAX_REPS = 100_000
# Largest metrics.csv read (an evaluate report holds one row per planner and scenario).
MAX_REPORT_BYTES = 256 << 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "reports", nargs="+", metavar="[LABEL=]REPORT", help="sb3-graph evaluate report folders (or metrics.csv files)"
    )
    parser.add_argument("--out", required=True, help="output folder; must not exist")
    parser.add_argument(
        "--metrics",
        nargs="+",
        default=list(DEFAULT_METRICS),
        help=f"columns of metrics.csv to aggregate (default: {' '.join(DEFAULT_METRICS)})",
    )
    parser.add_argument(
        "--reps",
        type=int,
        default=2000,
        help=f"bootstrap resamples, at most {MAX_REPS} (default: 2000; rliable: 50000)",
    )
    parser.add_argument("--confidence", type=float, default=0.95, help="interval size in (0, 1) (default: 0.95)")
    parser.add_argument("--seed", type=seed_value, default=0, help="seed of the bootstrap (default: 0)")
    parser.add_argument(
        "--bootstrap",
        default="stratified",
        help="stratified (default, rliable's: runs resampled within each scenario, scenarios fixed) or iid "
        "(all runs of a configuration resampled together: scenarios count as drawn too)",
    )
    parser.add_argument(
        "--seed-pattern",
        default=DEFAULT_SEED_PATTERN,
        help="regular expression whose first group is the training seed in a planner name (default: seed_(\\d+))",
    )


def split_label(item: str) -> tuple[str, str]:
    """``[LABEL=]PATH`` -> ``(label, path)``; the label is ``""`` when there is no ``=``."""
    label, sep, path = item.partition("=")
    return (label, path) if sep else ("", item)


def _inputs(items: list[str]) -> list[tuple[str, Path]]:
    """``[LABEL=]PATH`` items -> ``(label, metrics.csv)``, each checked."""
    inputs, seen = [], set()
    for item in items:
        label, path = split_label(item)
        file = Path(path)
        if file.is_dir():
            file = file / "metrics.csv"
        if not file.exists():
            raise UserError(f"REPORT {item!r}: no metrics.csv there (give an sb3-graph evaluate report folder)")
        if not file.is_file():  # a FIFO or a device would block or never end
            raise UserError(f"REPORT {item!r}: {str(file)!r} is not a regular file")
        if file.stat().st_size > MAX_REPORT_BYTES:
            raise UserError(f"REPORT {item!r}: {str(file)!r} is larger than the {MAX_REPORT_BYTES} bytes accepted")
        if file.resolve() in seen:
            raise UserError(f"REPORT {item!r} is given twice: its runs would count twice")
        seen.add(file.resolve())
        inputs.append((label or (file.parent.name if file.name == "metrics.csv" else file.stem), file))
    return inputs


def read_runs(items: list[str], metrics: list[str], seed_pattern: str) -> pd.DataFrame:
    """The rows of every input, with ``configuration`` (label:planner, seed token -> ``seed_*``) and ``seed``.

    :param items: ``[LABEL=]PATH`` of each input
    :param metrics: metric columns that every input must have
    :param seed_pattern: regular expression, its first group the seed in a planner name
    """
    import pandas as pd

    pattern = compile_seed_pattern(seed_pattern)
    frames = []
    for label, file in _inputs(items):
        try:
            frame = pd.read_csv(file)
        except (OSError, ValueError) as error:
            raise UserError(f"REPORT {str(file)!r}: cannot read it as CSV: {error}") from None
        missing = [c for c in ("planner", TASK, *metrics) if c not in frame]
        if missing:
            raise UserError(
                f"REPORT {str(file)!r} has no column {missing}; --metrics allowed: "
                f"{sorted(c for c in frame if pd.api.types.is_numeric_dtype(frame[c]))}"
            )
        _check_metrics(frame, metrics, file)
        planners = frame["planner"].astype(str)
        frame[SEED] = planners.map(lambda name: (m := pattern.search(name)) and m.group(1)).astype("string")
        configuration = planners.map(lambda name: seeds_pooled(pattern, name))
        frame.insert(0, CONFIGURATION, f"{label}:" + configuration)
        frame.insert(1, "input", str(file))
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def _check_metrics(frame: pd.DataFrame, metrics: list[str], file: Path) -> None:
    """Every metric a number: finite, or empty (undefined, e.g. the delay of a run without vehicles)."""
    import numpy as np
    import pandas as pd

    for name in metrics:
        values = pd.to_numeric(frame[name], errors="coerce")
        bad = (values.isna() & frame[name].notna()) | np.isinf(values)
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            raise UserError(
                f"REPORT {str(file)!r}: column {name!r} must hold finite numbers (or nothing), "
                f"got {str(frame[name].iloc[row])[:40]!r} in row {row + 2}"
            )
        frame[name] = values


def compile_seed_pattern(seed_pattern: str) -> re.Pattern:
    """``--seed-pattern``: a regular expression whose first group is the seed in a planner name.

    :raises UserError: naming the flag, when it does not compile or has no group
    """
    try:
        pattern = re.compile(seed_pattern)
        if pattern.groups < 1:
            raise re.error("it needs a group, e.g. seed_(\\d+)")
    except re.error as error:
        raise UserError(f"--seed-pattern {seed_pattern!r}: {error}") from None
    return pattern


def seeds_pooled(pattern: re.Pattern, name: str) -> str:
    """A planner name with its seed replaced by ``*`` (``RL:seed_3`` -> ``RL:seed_*``): the name of
    the configuration that all its training seeds form.

    :param pattern: from :func:`compile_seed_pattern`
    :param name: a planner name
    """

    def wildcard(match: re.Match) -> str:
        text, start = match.group(0), match.start(1) - match.start(0)
        return text[:start] + "*" + text[start + len(match.group(1)) :]

    return pattern.sub(wildcard, name)


def markdown(table: pd.DataFrame, confidence: float, bootstrap: str = "stratified") -> str:
    """The aggregate as a markdown table: one row per configuration and metric."""
    level = f"{100 * confidence:g} %"
    how = (
        "stratified bootstrap interval (runs resampled within each scenario: the spread over seeds; a "
        "configuration with one run per scenario gets a point)"
        if bootstrap == "stratified"
        else "bootstrap interval over all runs together (seeds and scenarios)"
    )
    lines = [
        f"IQM over runs (seeds x scenarios) with the {level} {how}, mean and median.",
        "",
        f"| configuration | metric | IQM [{level} CI] | mean | median | runs | seeds | scenarios |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in table.itertuples(index=False):
        if row.runs:
            cell = f"{row.iqm:.4g} [{row.ci_low:.4g}, {row.ci_high:.4g}]"
            stats = f"{row.mean:.4g} | {row.median:.4g}"
        else:
            cell, stats = "undefined", " | "
        lines.append(
            f"| {row.configuration} | {row.metric} | {cell} | {stats} | {row.runs} | {row.seeds} | {row.tasks} |"
        )
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    from sb3_graph.aggregate import aggregate
    from sb3_graph.files.output_folders import OutputError, check_destination, staged_folder

    if not 1 <= args.reps <= MAX_REPS:
        raise UserError(f"--reps must be in [1, {MAX_REPS}], got {args.reps}")
    if args.bootstrap not in ("stratified", "iid"):
        raise UserError(f"--bootstrap must be stratified or iid, got {args.bootstrap!r}")
    if not 0 < args.confidence < 1:
        raise UserError(f"--confidence must be in (0, 1), got {args.confidence}")
    try:
        check_destination(Path(args.out))
    except OutputError as error:
        raise UserError(str(error)) from None
    runs = read_runs(args.reports, args.metrics, args.seed_pattern)
    table = aggregate(
        runs, CONFIGURATION, TASK, args.metrics, args.reps, args.confidence, args.seed, SEED,
        stratified=args.bootstrap == "stratified",
    )  # fmt: skip
    try:
        with staged_folder(args.out) as folder:
            table.to_csv(folder / "aggregate.csv", index=False)
            (folder / "aggregate.md").write_text(markdown(table, args.confidence, args.bootstrap))
            runs.to_csv(folder / "runs.csv", index=False)
    except OutputError as error:
        raise UserError(str(error)) from None
    print(markdown(table, args.confidence, args.bootstrap), end="")
    print(f"sb3-graph aggregate: {len(runs)} runs, {runs[CONFIGURATION].nunique()} configurations -> {args.out}")
    return 0
