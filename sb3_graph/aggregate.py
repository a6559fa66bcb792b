"""Aggregate results over seeds and tasks: interquartile mean and stratified bootstrap intervals.

The figures of rliable (Agarwal et al., "Deep RL at the edge of the statistical precipice", 2021),
computed with numpy alone (rliable needs ``arch``, whose releases break with new pandas):

- :func:`iqm`: the interquartile mean of all scores pooled, the mean of the middle 50 % (the same
  trimming as ``scipy.stats.trim_mean(scores, 0.25, axis=None)``, which is
  ``rliable.metrics.aggregate_iqm``): robust to a few outlier runs, far less noisy than the median.
- :func:`stratified_bootstrap_ci`: the percentile interval of a statistic under the *stratified*
  bootstrap, which resamples the runs of each task with replacement, task by task, so every
  resample has the same tasks in the same proportion (``rliable.library.get_interval_estimates``
  with ``method="percentile"``). A run is one training seed on one task (here: one scenario).

Tasks may have different numbers of runs (``tasks`` is a list of 1-d arrays), e.g. after runs with
an undefined metric are dropped; a ``(runs, tasks)`` matrix, rliable's layout, is accepted too.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pandas as pd

DEFAULT_REPS = 2000
DEFAULT_CONFIDENCE = 0.95
TRIM = 0.25


def _tasks(scores: np.ndarray | Sequence[Sequence[float]]) -> list[np.ndarray]:
    """A ``(runs, tasks)`` matrix or a list of per-task runs -> a list of 1-d float arrays (tasks)."""
    if isinstance(scores, np.ndarray):
        if scores.ndim == 1:
            return [scores.astype(float)]
        if scores.ndim != 2:
            raise ValueError(f"scores must be a (runs, tasks) matrix or a list of per-task arrays, got {scores.ndim}-d")
        return [scores[:, j].astype(float) for j in range(scores.shape[1])]
    tasks = [np.asarray(task, dtype=float).ravel() for task in scores]
    if not tasks or any(task.size == 0 for task in tasks):
        raise ValueError("every task needs at least one run")
    return tasks


def iqm(scores: np.ndarray | Sequence[float], axis: int | None = None) -> float | np.ndarray:
    """Interquartile mean: the mean of the scores left after cutting ``int(0.25 * n)`` from each end.

    :param scores: scores; all pooled when ``axis`` is ``None``
    :param axis: axis along which to take it (the bootstrap passes 1: one IQM per resample)
    :return: the IQM (an array when ``axis`` is given)
    """
    values = np.asarray(scores, dtype=float)
    if axis is None:
        values, axis = values.ravel(), 0
    values = np.sort(values, axis=axis)
    n = values.shape[axis]
    if n == 0:
        raise ValueError("iqm of no scores")
    cut = int(TRIM * n)
    return np.take(values, np.arange(cut, n - cut), axis=axis).mean(axis=axis)


def bootstrap_interval(
    scores: np.ndarray | Sequence[np.ndarray],
    rng: np.random.Generator,
    reps: int = DEFAULT_REPS,
    confidence: float = DEFAULT_CONFIDENCE,
    statistic: Callable[..., Any] = np.mean,
) -> np.ndarray:
    """Percentile bootstrap interval of ``statistic``, stratified: the rows of each stratum are
    resampled with replacement within it. The one bootstrap of the repository
    (:func:`stratified_bootstrap_ci` and the paired planner comparisons use it).

    :param scores: one stratum, an ``(n, ...)`` array of ``n >= 1`` rows, or a list of strata
        with the same trailing shape (e.g. ``(n, m)``: ``m`` metrics resampled together, row by row)
    :param rng: random generator (one resampling of the rows serves every trailing column)
    :param reps: bootstrap resamples
    :param confidence: interval size in (0, 1)
    :param statistic: ``f(samples, axis=1)`` over a ``(reps, rows, ...)`` array (``np.mean``, :func:`iqm`)
    :return: ``(2, ...)`` lower and upper bounds
    """
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if reps < 1:
        raise ValueError(f"reps must be at least 1, got {reps}")
    strata = [np.asarray(scores, dtype=float)] if isinstance(scores, np.ndarray) else list(scores)
    # one (reps, rows of the stratum, ...) block per stratum, drawn from that stratum's rows only
    blocks = [stratum[rng.integers(0, stratum.shape[0], size=(reps, stratum.shape[0]))] for stratum in strata]
    values = np.asarray(statistic(np.concatenate(blocks, axis=1), axis=1), dtype=float)
    tail = 100 * (1 - confidence) / 2
    return np.percentile(values, [tail, 100 - tail], axis=0)


def stratified_bootstrap_ci(
    scores: np.ndarray | Sequence[Sequence[float]],
    statistic: Callable[..., Any] = iqm,
    reps: int = DEFAULT_REPS,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int | None = 0,
) -> tuple[float, float]:
    """Percentile interval of ``statistic`` under the stratified bootstrap (runs resampled within each task).

    :param scores: a ``(runs, tasks)`` matrix, or one 1-d array of runs per task
    :param statistic: ``f(samples, axis=1) -> one value per row`` for a ``(reps, all runs)`` array
        (:func:`iqm`, ``np.mean``, ``np.median`` all are)
    :param reps: bootstrap resamples
    :param confidence: interval size in (0, 1)
    :param seed: seed of the resampling (``None``: fresh entropy)
    :return: ``(low, high)``
    """
    tasks = _tasks(scores)
    low, high = bootstrap_interval(tasks, np.random.default_rng(seed), reps, confidence, statistic)
    return float(low), float(high)


def aggregate(
    runs: pd.DataFrame,
    group: str,
    task: str,
    metrics: Sequence[str],
    reps: int = DEFAULT_REPS,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
    seed_column: str | None = None,
    stratified: bool = True,
) -> pd.DataFrame:
    """IQM and stratified bootstrap interval of each metric, per group (configuration), over runs and tasks.

    Runs whose metric is NaN (undefined, e.g. a delay without vehicles) are left out of that
    metric only; ``runs`` counts those that remain.

    :param runs: one row per run (a seed on a task), with the columns ``group``, ``task`` and ``metrics``
    :param group: column naming the configuration
    :param task: column naming the task (the bootstrap's strata)
    :param metrics: metric columns
    :param reps: bootstrap resamples
    :param confidence: interval size
    :param seed: seed of the resampling (the same for every group and metric)
    :param seed_column: column of the training seed, to count the seeds (optional)
    :param stratified: resample the runs within each task (rliable's bootstrap: the tasks are
        fixed, the interval measures the spread over runs, and a task with one run adds none);
        ``False`` resamples all runs of a group together (the tasks count as drawn too)
    :return: one row per group and metric: ``group, metric, iqm, ci_low, ci_high, mean, median,
        runs, tasks`` (and ``seeds``)
    """
    missing = [c for c in (group, task, *metrics, *([seed_column] if seed_column else [])) if c not in runs]
    if missing:
        raise KeyError(f"columns {missing} missing; the table has {sorted(runs.columns)}")
    rows = []
    for name, frame in runs.groupby(group, sort=False):
        for metric in metrics:
            kept = frame[np.isfinite(pd.to_numeric(frame[metric], errors="coerce").astype(float))]
            row: dict[str, Any] = {group: name, "metric": metric, "runs": len(kept), "tasks": kept[task].nunique()}
            if seed_column:
                row["seeds"] = kept[seed_column].nunique()
            if len(kept):
                values = kept[metric].astype(float)
                if stratified:
                    per_task = [g.to_numpy() for _, g in values.groupby(kept[task], sort=True)]
                else:
                    per_task = [values.to_numpy()]
                low, high = stratified_bootstrap_ci(per_task, iqm, reps, confidence, seed)
                row.update(iqm=float(iqm(values)), ci_low=low, ci_high=high, mean=values.mean(), median=values.median())
            rows.append(row)
    columns = [group, "metric", "iqm", "ci_low", "ci_high", "mean", "median", "runs", "tasks"]
    return pd.DataFrame(rows).reindex(columns=columns + (["seeds"] if seed_column else []))
