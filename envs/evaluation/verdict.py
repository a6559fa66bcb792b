"""The verdict of an evaluation: who leads on each headline metric, by how much, and whether it is clear.

It reads the paired comparison (:func:`envs.evaluation.comparison.paired_differences`: per planner and
metric, the mean per-scenario difference against a reference planner with a bootstrap interval) and
says, per metric of :data:`VERDICT_METRICS`:

- a leader only where the paired interval excludes zero: the planner with the best mean difference (the
  reference itself when every other planner is clearly worse), by how much (the mean difference between
  the leader and the reference, or, when the reference leads, its closest follower), in the metric's unit,
  relative to the reference's mean where that makes sense;
- otherwise "no clear lead", with the best difference and its interval, and no planner named as leader.

The section opens with one sentence (:func:`summary_sentence`) that names the clear leads only.

Only the metrics of :data:`VERDICT_METRICS` enter the verdict; a report's other columns (or a new
paired metric) enter it when a line is added there.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from envs.evaluation.comparison import paired_differences

HEADING = "## Verdict"


@dataclass(frozen=True)
class VerdictMetric:
    """How one paired metric enters the verdict.

    :param word: its name in the verdict (``"flow"``)
    :param direction: ``+1`` when more is better, ``-1`` when less is
    :param unit: unit of a difference, after ``scale`` (``"veh/s"``, ``"s"``, ``"percentage points"``)
    :param digits: decimals of a difference
    :param scale: factor from the ``metrics.csv`` unit to ``unit`` (100 for a share in percentage points)
    :param relative: also give the difference relative to the reference's mean (in %)
    :param gain: what leading on it means, for the summary sentence (``"more flow"``; default: ``"a better <word>"``)
    """

    word: str
    direction: int
    unit: str
    digits: int = 3
    scale: float = 1.0
    relative: bool = True
    gain: str = ""


#: ``metrics.csv`` column -> how it enters the verdict (in the verdict's order)
VERDICT_METRICS: dict[str, VerdictMetric] = {
    "flow_rate": VerdictMetric("flow", +1, "veh/s", 3, gain="more flow"),
    "delay_mean": VerdictMetric("delay", -1, "s", 2, gain="less delay"),
    "stop_ratio_all": VerdictMetric(
        "stops", -1, "percentage points", 1, scale=100.0, relative=False, gain="fewer stopped vehicles"
    ),
}


def _signed(value: float, metric: VerdictMetric) -> str:
    return f"{metric.scale * value:+.{metric.digits}f}"


@dataclass(frozen=True)
class Lead:
    """Who leads on one metric (:func:`lead`).

    :param leader: the planner with the best mean difference, or the reference when every other planner is worse
    :param other: the planner it leads (the reference, or the reference's closest follower)
    :param planner: the planner of the paired row read (``planner - reference``)
    :param reference: the reference planner
    :param difference: mean per-scenario ``planner - reference`` (NaN: no paired scenario)
    :param low: lower end of its interval
    :param high: upper end of its interval
    :param pairs: paired scenarios
    :param clear: the interval excludes zero (``None``: no interval)
    :param tie: equal on every paired scenario
    """

    leader: str
    other: str
    planner: str
    reference: str
    difference: float
    low: float
    high: float
    pairs: int
    clear: bool | None
    tie: bool


def lead(rows: pd.DataFrame, metric: VerdictMetric) -> Lead:
    """Who leads on one metric, from its paired rows.

    :param rows: the paired rows of one metric (columns of :data:`envs.evaluation.comparison.PAIRED_COLUMNS`),
        one per planner other than the reference
    :param metric: how the metric enters the verdict (its direction)
    """
    reference = str(rows["baseline"].iloc[0])
    means = rows["mean_difference"].to_numpy(float)
    gains = metric.direction * np.where(np.isfinite(means), means, -np.inf)
    best = int(np.argmax(gains))
    row = rows.iloc[best]
    planner = str(row["planner"])
    diff, low, high = float(row["mean_difference"]), float(row["ci_low"]), float(row["ci_high"])
    clear = bool(low > 0 or high < 0) if np.isfinite(low) and np.isfinite(high) else None
    ahead = bool(gains[best] > 0)
    return Lead(
        leader=planner if ahead else reference, other=reference if ahead else planner, planner=planner,
        reference=reference, difference=diff, low=low, high=high, pairs=int(row["pairs"]), clear=clear,
        tie=diff == 0 and low == 0 and high == 0,
    )  # fmt: skip


def metric_verdict(
    rows: pd.DataFrame, metric: VerdictMetric, reference_mean: float | None = None, level: str = "95 %"
) -> str:
    """One metric's verdict line: a leader only where the paired interval excludes zero.

    :param rows: the paired rows of one metric (columns of :data:`envs.evaluation.comparison.PAIRED_COLUMNS`),
        one per planner other than the reference
    :param metric: how the metric enters the verdict
    :param reference_mean: the reference's mean of the metric over the runs (for the relative difference)
    :param level: the interval's confidence, as text
    :return: a Markdown list item, e.g. ``"- flow: **A** leads by 0.052 veh/s (13.0 % of PR's mean) over PR; ..."``
        or ``"- flow: no clear lead; the best difference, A - PR = +0.004 [-0.010, +0.018] veh/s, ..."``
    """
    found = lead(rows, metric)
    reference, diff = found.reference, found.difference
    if not np.isfinite(diff):
        return f"- {metric.word}: no verdict (no scenario where both {found.planner} and {reference} have a value)"
    if found.tie:
        return f"- {metric.word}: tie, {found.planner} and {reference} equal on all {found.pairs} paired scenarios"
    interval = f" [{_signed(found.low, metric)}, {_signed(found.high, metric)}]" if found.clear is not None else ""
    detail = f"{found.planner} - {reference} = {_signed(diff, metric)}{interval} {metric.unit} over {found.pairs}"
    detail += " scenario" if found.pairs == 1 else " scenarios"
    if not found.clear:
        why = "one scenario, no interval" if found.clear is None else f"its {level} interval includes zero"
        return f"- {metric.word}: no clear lead; the best difference, {detail} ({why})"
    size = f"{abs(metric.scale * diff):.{metric.digits}f} {metric.unit}"
    if metric.relative and reference_mean is not None and np.isfinite(reference_mean) and reference_mean != 0:
        size += f" ({100 * abs(diff) / abs(reference_mean):.1f} % of {reference}'s mean)"
    closest = " (the closest)" if found.leader == reference and len(rows) > 1 else ""
    return (
        f"- {metric.word}: **{found.leader}** leads by {size} over {found.other}{closest}; {detail} "
        f"(its {level} interval excludes zero)"
    )


def summary_sentence(
    paired: pd.DataFrame, metrics: Mapping[str, VerdictMetric] | None = None, collided: Mapping[str, int] | None = None
) -> str:
    """The verdict in one sentence, naming a planner only where its paired interval excludes zero, e.g.
    ``"In short: AIM has fewer stopped vehicles than FullThrottle+shield (-15.4 percentage points); no planner
    leads clearly on flow or delay."``

    :param paired: :func:`envs.evaluation.comparison.paired_differences` output (one reference)
    :param metrics: the metrics that enter (default :data:`VERDICT_METRICS`)
    :param collided: collided vehicles per planner: as in :func:`verdict_lines`, those cannot lead
    :return: the sentence (Markdown, ``"**In short:**"`` first)
    """
    if paired is None or paired.empty:
        return "**In short:** a single planner ran; there is nothing to compare it with."
    paired, unsafe, left_out = without_collided(paired, collided)
    clear, unclear = [], []
    for column, metric in (VERDICT_METRICS if metrics is None else metrics).items():
        rows = paired[paired["metric"] == column]
        if rows.empty:
            continue
        found = lead(rows, metric)
        if not found.clear or found.tie or not np.isfinite(found.difference):
            unclear.append(metric.word)
            continue
        gain = metric.gain or f"a better {metric.word}"
        difference = f"{_signed(found.difference, metric)} {metric.unit}"
        if found.leader == found.reference:
            clear.append(f"{found.leader} has {gain} than the closest, {found.other} ({difference} for it)")
        else:
            clear.append(f"{found.leader} has {gain} than {found.reference} ({difference})")
    parts = ["; ".join(clear)] if clear else []
    if unclear:
        words = unclear[0] if len(unclear) == 1 else f"{', '.join(unclear[:-1])} or {unclear[-1]}"
        parts.append(f"no planner leads clearly on {words}")
    if left_out:
        names = list(unsafe)
        listed = names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"
        parts.append(f"{listed} cannot lead, as {'its' if len(names) == 1 else 'their'} vehicles collided")
    text = "; ".join(parts)
    return f"**In short:** {text[0].upper()}{text[1:]}." if text else "**In short:** no verdict."


def without_collided(
    paired: pd.DataFrame, collided: Mapping[str, int] | None
) -> tuple[pd.DataFrame, dict[str, int], bool]:
    """The paired rows of the planners that may lead: none whose vehicles collided, unless every
    planner compared with the reference did (then all stay, and the caller says so).

    :param paired: a non-empty paired table (one reference)
    :param collided: collided vehicles per planner (``None``: all may lead)
    :return: ``(rows, {planner: collided vehicles} of the planners other than the reference that collided,
        whether those were left out)``
    """
    reference = str(paired["baseline"].iloc[0])
    unsafe = {p: int(n) for p, n in (collided or {}).items() if n > 0 and p != reference}
    crashed = paired["planner"].isin(list(unsafe))
    left_out = bool(unsafe) and not crashed.all()
    return (paired[~crashed] if left_out else paired), unsafe, left_out


def collided_by_planner(runs: pd.DataFrame) -> dict[str, int] | None:
    """Collided vehicles per planner over ``metrics.csv`` rows (``None`` without the column)."""
    return runs.groupby("planner")["collided"].sum().to_dict() if "collided" in runs else None


def compact_verdict(
    paired: pd.DataFrame, metrics: Mapping[str, VerdictMetric] | None = None, collided: Mapping[str, int] | None = None
) -> str:
    """The verdict in one line, e.g. ``"flow: AIM, delay: no clear lead, stops: tie"`` (a sweep's level): a planner
    is named only where its paired interval excludes zero.

    :param paired: :func:`envs.evaluation.comparison.paired_differences` output
    :param metrics: the metrics that enter (default :data:`VERDICT_METRICS`)
    :param collided: collided vehicles per planner: as in :func:`verdict_lines`, those cannot lead
    :return: the line; ``"no verdict (a single planner)"`` for an empty table
    """
    if paired is None or paired.empty:
        return "no verdict (a single planner)"
    paired, unsafe, left_out = without_collided(paired, collided)
    parts = []
    for column, metric in (VERDICT_METRICS if metrics is None else metrics).items():
        rows = paired[paired["metric"] == column]
        if rows.empty:
            continue
        found = lead(rows, metric)
        if found.tie or not np.isfinite(found.difference):
            parts.append(f"{metric.word}: {'tie' if found.tie else 'n/a'}")
        else:
            parts.append(f"{metric.word}: {found.leader if found.clear else 'no clear lead'}")
    if left_out:
        parts.append(f"not in the lead (collided): {', '.join(unsafe)}")
    return ", ".join(parts)


def verdict_lines(
    paired: pd.DataFrame,
    metrics: Mapping[str, VerdictMetric] | None = None,
    reference_means: Mapping[str, float] | None = None,
    reference_kind: str = "the strongest baseline",
    level: str = "95 %",
    collided: Mapping[str, int] | None = None,
) -> list[str]:
    """The verdict section of a report: a heading, the summary sentence (:func:`summary_sentence`), what the
    comparison is, one line per metric.

    :param paired: :func:`envs.evaluation.comparison.paired_differences` output (any reference)
    :param metrics: the metrics that enter (default :data:`VERDICT_METRICS`); one absent from ``paired`` is left out
    :param reference_means: the reference's mean per metric (``metrics.csv`` units), for relative differences
    :param reference_kind: what the reference is, for the sentence
    :param level: the intervals' confidence, as text
    :param collided: collided vehicles per planner; a planner other than the reference with any cannot
        lead (a planner that crashes cars buys its flow, delay and stops with them), and a last line names them
    :return: Markdown lines (without a trailing empty line); a one-line "no verdict" when ``paired`` is empty
    """
    metrics = VERDICT_METRICS if metrics is None else metrics
    if paired is None or paired.empty:
        return [HEADING, "", "No verdict: a single planner ran (nothing to compare it with)."]
    reference = str(paired["baseline"].iloc[0])
    sentence = summary_sentence(paired, metrics, collided)
    paired, unsafe, left_out = without_collided(paired, collided)
    lines = [
        HEADING,
        "",
        sentence,
        "",
        f"Who leads, against {reference} ({reference_kind}): mean per-scenario difference and its {level} "
        "paired bootstrap interval.",
        "",
    ]
    for column, metric in metrics.items():
        rows = paired[paired["metric"] == column]
        if not rows.empty:
            mean = None if reference_means is None else reference_means.get(column)
            lines.append(metric_verdict(rows, metric, mean, level))
    crashed = ", ".join(f"{p} ({n:,} vehicles)" for p, n in unsafe.items())
    if left_out:
        lines.append(f"- not in the lead, as their vehicles collided: {crashed}")
    elif unsafe:  # every planner but the reference collided: the lead is among them, and says so
        lines.append(f"- every planner compared with {reference} collided: {crashed}")
    return lines


def reference_comparison(runs: pd.DataFrame, paired: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    """The paired table the verdict reads: ``paired`` (against the strongest baseline) or, when the run has no
    baseline planner, the comparison against the first planner listed.

    :param runs: ``metrics.csv`` rows of the runs that did not fail
    :param paired: :func:`envs.evaluation.comparison.paired_differences` of ``runs`` (may be empty)
    :return: ``(paired table, what its reference is)``
    """
    if not paired.empty:
        return paired, "the strongest baseline"
    planners = list(pd.unique(runs["planner"])) if "planner" in runs else []
    if len(planners) < 2:
        return paired, ""
    return paired_differences(runs, baseline=str(planners[0])), "the first planner listed; no baseline planner ran"


def reference_means(runs: pd.DataFrame, paired: pd.DataFrame, columns: Sequence[str]) -> dict[str, float]:
    """The reference planner's mean of each column over its runs (for the relative differences).

    :param runs: ``metrics.csv`` rows
    :param paired: the paired table (its ``baseline`` column names the reference)
    :param columns: ``metrics.csv`` columns
    """
    if paired.empty:
        return {}
    mine = runs[runs["planner"] == paired["baseline"].iloc[0]]
    return {c: float(mine[c].astype(float).mean()) for c in columns if c in mine and len(mine)}


def read_verdict(report: str | Path) -> list[str]:
    """The verdict section of a written ``report.md`` (its lines after the heading, blank lines dropped).

    :param report: the ``report.md`` file (or its folder)
    :return: the lines; empty when the report has no verdict
    """
    path = Path(report)
    path = path / "report.md" if path.is_dir() else path
    if not path.is_file():
        return []
    lines, inside = [], False
    for line in path.read_text().splitlines():
        if line.strip() == HEADING:
            inside = True
            continue
        if inside and line.startswith("#"):
            break
        if inside and line.strip():
            lines.append(line)
    return lines
