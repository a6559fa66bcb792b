"""Paired comparison of planners against the strongest baseline, with bootstrap intervals.

Every planner runs the same scenarios, so the comparison is paired: per scenario, the planner's
metric minus the baseline's on that scenario. The *strongest baseline* is the non-learned planner
(``baseline`` column of ``metrics.csv``: its spec is a built-in word, not a model file) with the
highest median flow rate (on a tie, the lower mean delay). The 95 % interval of the mean
difference is a percentile bootstrap over scenarios (resampled with replacement,
:data:`RESAMPLES` times, seeded so a report repeats).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

# metrics.csv column -> label in the report
PAIRED_METRICS = {"flow_rate": "flow [veh/s]", "delay_mean": "mean delay [s]", "stop_ratio_all": "stop ratio"}
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


def bootstrap_interval(
    differences: np.ndarray, rng: np.random.Generator, resamples: int = RESAMPLES, confidence: float = CONFIDENCE
) -> np.ndarray:
    """Percentile bootstrap interval of the mean of each column.

    :param differences: ``(n, m)`` paired differences, ``n >= 1`` pairs of ``m`` metrics (no NaN)
    :param rng: random generator (one resampling of the pairs serves every column)
    :param resamples: bootstrap resamples
    :param confidence: interval level
    :return: ``(2, m)`` lower and upper bounds
    """
    differences = np.asarray(differences, float)
    n = differences.shape[0]
    index = rng.integers(0, n, (resamples, n))
    means = differences[index].mean(axis=1)  # (resamples, m)
    tail = 100 * (1 - confidence) / 2
    return np.percentile(means, [tail, 100 - tail], axis=0)


def paired_differences(runs: pd.DataFrame, baseline: str | None = None, seed: int = 0) -> pd.DataFrame:
    """Per-scenario differences of every planner against ``baseline``, mean and bootstrap interval.

    :param runs: ``metrics.csv`` rows (``planner``, ``scenario`` and the :data:`PAIRED_METRICS`)
    :param baseline: report name of the reference; default :func:`strongest_baseline`
    :param seed: seed of the bootstrap
    :return: one row per other planner and metric, columns :data:`PAIRED_COLUMNS` (``pairs``:
        scenarios where both values are defined); empty without a baseline
    """
    baseline = strongest_baseline(runs) if baseline is None else baseline
    rows = []
    if baseline is not None:
        metrics = list(PAIRED_METRICS)
        ref = runs[runs["planner"] == baseline].set_index("scenario")[metrics]
        for planner in pd.unique(runs["planner"]):
            if planner == baseline:
                continue
            mine = runs[runs["planner"] == planner].set_index("scenario")[metrics]
            diff = mine.sub(ref).dropna(how="all")
            for metric in metrics:
                d = diff[metric].dropna().to_numpy(float)
                low, high = (
                    bootstrap_interval(d[:, None], np.random.default_rng(seed))[:, 0] if d.size else (np.nan, np.nan)
                )
                rows.append((str(planner), baseline, metric, d.size, d.mean() if d.size else np.nan, low, high))
    return pd.DataFrame(rows, columns=list(PAIRED_COLUMNS))
