"""Paired comparison of planners against the strongest baseline, with bootstrap intervals.

Every planner runs the same scenarios, so the comparison is paired: per scenario, the planner's
metric minus the baseline's on that scenario. The *strongest baseline* is the non-learned planner
(``baseline`` column of ``metrics.csv``: its spec is a built-in word, not a model file) with the
highest median flow rate (on a tie, the lower mean delay). The 95 % interval of the mean
difference is a percentile bootstrap over scenarios (resampled with replacement,
:data:`RESAMPLES` times, seeded so a report repeats; :func:`sb3_graph.aggregate.bootstrap_interval`).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from sb3_graph.aggregate import bootstrap_interval

# metrics.csv column -> label in the report
PAIRED_METRICS = {
    "flow_rate": "flow [veh/s]",
    "delay_mean": "mean delay [s]",
    "stop_ratio_all": "stop ratio",
    "slow_ratio": "slow ratio",
    "hard_brakes_per_vehicle": "hard brakes / vehicle",
    "energy_kj_per_vehicle": "energy [kJ/vehicle]",
}
#: metrics.csv column -> (heading of its paired difference in a table, factor, decimals): the report's and the
#: results pages' tables (scripts/results_tables.py)
PAIRED_DISPLAY = {
    "flow_rate": ("Δ flow [veh/s]", 1.0, 3),
    "delay_mean": ("Δ mean delay [s]", 1.0, 2),
    "stop_ratio_all": ("Δ stops [pp]", 100.0, 1),
    "slow_ratio": ("Δ slowed below 2 m/s [pp]", 100.0, 1),
    "hard_brakes_per_vehicle": ("Δ hard brakes per vehicle", 1.0, 2),
    "energy_kj_per_vehicle": ("Δ energy [kJ per crossed vehicle]", 1.0, 0),
}
PAIRED_COLUMNS = ("planner", "baseline", "metric", "pairs", "mean_difference", "ci_low", "ci_high")
RESAMPLES = 10_000
CONFIDENCE = 0.95


def strongest_baseline(runs: pd.DataFrame) -> str | None:
    """The non-learned planner with the highest median flow rate.

    Below every baseline's capacity the flows tie (each serves the whole demand): a tie goes to the
    lower mean delay, then to the planner listed first.

    :param runs: ``metrics.csv`` rows with ``planner``, ``flow_rate``, ``delay_mean`` and ``baseline`` columns
    :return: its report name, or ``None`` when no run is marked as a baseline
    """
    if "baseline" not in runs or runs.empty:
        return None
    base = runs[runs["baseline"].astype(bool)]
    if base.empty:
        return None
    groups = base.groupby("planner", sort=False)
    rank = pd.DataFrame({"flow": groups["flow_rate"].median(), "delay": -groups["delay_mean"].mean()})
    return str(rank.fillna(-np.inf).sort_values(["flow", "delay"], ascending=False, kind="stable").index[0])


def paired_differences(runs: pd.DataFrame, baseline: str | None = None, seed: int = 0) -> pd.DataFrame:
    """Per-scenario differences of every planner against ``baseline``, mean and bootstrap interval.

    :param runs: ``metrics.csv`` rows (``planner``, ``scenario`` and the :data:`PAIRED_METRICS`)
    :param baseline: report name of the reference; default :func:`strongest_baseline`
    :param seed: seed of the bootstrap
    :return: one row per other planner and metric of :data:`PAIRED_METRICS` that ``runs`` has (older
        ``metrics.csv`` files lack the newer ones), columns :data:`PAIRED_COLUMNS` (``pairs``: scenarios
        where both values are defined); empty without a baseline
    """
    baseline = strongest_baseline(runs) if baseline is None else baseline
    rows = []
    if baseline is not None:
        metrics = [metric for metric in PAIRED_METRICS if metric in runs]
        ref = runs[runs["planner"] == baseline].set_index("scenario")[metrics]
        for planner in pd.unique(runs["planner"]):
            if planner == baseline:
                continue
            mine = runs[runs["planner"] == planner].set_index("scenario")[metrics]
            diff = mine.sub(ref).dropna(how="all")
            for metric in metrics:
                d = diff[metric].dropna().to_numpy(float)
                low, high = (
                    bootstrap_interval(d[:, None], np.random.default_rng(seed), RESAMPLES, CONFIDENCE)[:, 0]
                    if d.size
                    else (np.nan, np.nan)
                )
                rows.append((str(planner), baseline, metric, d.size, d.mean() if d.size else np.nan, low, high))
    return pd.DataFrame(rows, columns=list(PAIRED_COLUMNS))
