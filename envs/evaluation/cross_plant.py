"""The same planners on the same scenarios in two plants (our simulation and SUMO): does a ranking hold?

:func:`side_by_side` gives each planner's figures in each plant; :func:`rankings` the paired difference of every
pair of planners in each plant (:func:`envs.evaluation.comparison.paired_differences`, its bootstrap interval
over the scenarios), and a verdict per pair and metric. A ranking *holds* across plants when every plant gives
the difference the same sign with an interval that excludes zero; it is *reversed* when both intervals exclude
zero with opposite signs. ``sb3-graph evaluate --plant builtin --plant sumo`` writes both tables
(:func:`write_cross_plant`: ``plants.md`` and ``plants.csv``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from envs.evaluation.comparison import PAIRED_DISPLAY, paired_differences
from envs.evaluation.report import failed_runs, format_number, percent

#: metrics.csv columns whose paired differences are ranked across plants
RANKED_METRICS = ("flow_rate", "delay_mean", "stop_ratio_all")
CROSS_PLANT_FILES = ("plants.md", "plants.csv")
PLANT_NAMES = {"builtin": "ours", "sumo": "SUMO"}  # as the tables name them


def _measured(runs: pd.DataFrame) -> pd.DataFrame:
    """The runs that measure their scenario (failed runs left out)."""
    return runs[~failed_runs(runs)]


def side_by_side(runs_by_plant: Mapping[str, pd.DataFrame], planners: Sequence[str]) -> pd.DataFrame:
    """Each planner's figures in each plant.

    :param runs_by_plant: ``metrics.csv`` rows per plant
    :param planners: report names, in table order
    :return: one row per planner and plant: ``runs`` (measured), ``failed``, ``flow`` (mean of the runs' flow
        rates) [veh/s], ``delay`` (mean of the runs' mean delays) [s], ``stopped`` (stopped vehicles of all the
        scheduled ones, pooled over the runs), ``collided`` (vehicles), ``vehicles`` (scheduled), ``stuck`` (runs)
    """
    rows = []
    for planner in planners:
        for plant, runs in runs_by_plant.items():
            mine = runs[runs["planner"] == planner]
            ok = _measured(mine)
            scheduled = float(ok["vehicles_all"].sum()) if "vehicles_all" in ok and len(ok) else np.nan
            rows.append({
                "planner": planner,
                "plant": plant,
                "runs": len(ok),
                "failed": len(mine) - len(ok),
                "flow": ok["flow_rate"].mean() if len(ok) else np.nan,
                "delay": ok["delay_mean"].mean() if len(ok) else np.nan,
                "stopped": ok["stopped_all"].sum() / scheduled if scheduled else np.nan,
                "collided": int(ok["collided"].sum()) if len(ok) else 0,
                "vehicles": int(ok["vehicles"].sum()) if len(ok) else 0,
                "stuck": int(ok["stuck"].fillna(False).astype(bool).sum()) if "stuck" in ok else 0,
            })  # fmt: skip
    return pd.DataFrame(rows)


def verdict(lows: Sequence[float], highs: Sequence[float], plants: Sequence[str]) -> str:
    """What the plants' intervals of one difference say together.

    :param lows: lower bound per plant
    :param highs: upper bound per plant
    :param plants: the plants' names
    :return: ``"holds"`` (same sign, every interval excludes zero), ``"reversed"`` (intervals exclude zero with
        opposite signs), ``"only in <plant>"`` (one plant ranks, the others do not) or ``"no ranking"``
    """
    sign = [1 if low > 0 else -1 if high < 0 else 0 for low, high in zip(lows, highs)]
    ranked = [s for s in sign if s]
    if len(ranked) == len(sign) and len(set(ranked)) == 1:
        return "holds"
    if len(set(ranked)) > 1:
        return "reversed"
    if len(ranked) == 1:
        return f"only in {PLANT_NAMES.get(plants[sign.index(ranked[0])], plants[sign.index(ranked[0])])}"
    return "no ranking" if not ranked else "in " + ", ".join(p for p, s in zip(plants, sign) if s)


def rankings(
    runs_by_plant: Mapping[str, pd.DataFrame], planners: Sequence[str], metrics: Sequence[str] = RANKED_METRICS
) -> pd.DataFrame:
    """The paired difference of every pair of planners in every plant, and whether its ranking holds.

    :param runs_by_plant: ``metrics.csv`` rows per plant (the same scenarios in each)
    :param planners: report names; each pair ``(planners[j], planners[i])``, ``i < j``, is the later one minus
        the earlier one
    :param metrics: ``metrics.csv`` columns to compare
    :return: one row per pair and metric: ``planner``, ``baseline``, ``metric``, then per plant ``<plant>_mean``,
        ``<plant>_low``, ``<plant>_high``, ``<plant>_pairs``, and ``verdict`` (:func:`verdict`)
    """
    plants = list(runs_by_plant)
    frames = {
        plant: {p: rows for p, rows in _measured(runs).groupby("planner", sort=False)}
        for plant, runs in runs_by_plant.items()
    }
    rows = []
    for i, base in enumerate(planners):
        for planner in planners[i + 1 :]:
            per_plant = {}
            for plant in plants:
                both = [frames[plant][p] for p in (base, planner) if p in frames[plant]]
                table = paired_differences(pd.concat(both), baseline=base) if len(both) == 2 else None
                per_plant[plant] = None if table is None else table.set_index("metric")
            for metric in metrics:
                row = {"planner": planner, "baseline": base, "metric": metric}
                for plant in plants:
                    found = per_plant[plant] is not None and metric in per_plant[plant].index
                    cell = per_plant[plant].loc[metric] if found else None
                    row[f"{plant}_mean"] = cell["mean_difference"] if found else np.nan
                    row[f"{plant}_low"] = cell["ci_low"] if found else np.nan
                    row[f"{plant}_high"] = cell["ci_high"] if found else np.nan
                    row[f"{plant}_pairs"] = int(cell["pairs"]) if found else 0
                row["verdict"] = verdict([row[f"{p}_low"] for p in plants], [row[f"{p}_high"] for p in plants], plants)
                rows.append(row)
    columns = ["planner", "baseline", "metric"]
    columns += [f"{p}_{what}" for p in plants for what in ("mean", "low", "high", "pairs")] + ["verdict"]
    return pd.DataFrame(rows, columns=columns)


def _interval(mean: float, low: float, high: float, metric: str) -> str:
    """``"+0.087 [+0.065, +0.115]"`` in the metric's display unit (:data:`PAIRED_DISPLAY`)."""
    if not np.isfinite(mean):
        return "n/a"
    _, factor, digits = PAIRED_DISPLAY[metric]
    return f"{factor * mean:+.{digits}f} [{factor * low:+.{digits}f}, {factor * high:+.{digits}f}]"


def side_by_side_markdown(table: pd.DataFrame) -> list[str]:
    """:func:`side_by_side` as a Markdown table."""
    lines = [
        "| planner | plant | runs | flow [veh/s] | delay [s] | stopped | collided vehicles | stuck runs |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in table.itertuples():
        runs = f"{row.runs}" + (f" ({row.failed} failed)" if row.failed else "")
        lines.append(
            f"| {row.planner} | {PLANT_NAMES.get(row.plant, row.plant)} | {runs} | {format_number(row.flow)} "
            f"| {format_number(row.delay, 2)} | {percent(row.stopped)} | {row.collided} / {row.vehicles} "
            f"| {row.stuck} |"
        )
    return lines


def rankings_markdown(table: pd.DataFrame, plants: Sequence[str]) -> list[str]:
    """:func:`rankings` as a Markdown table: one row per pair, per metric each plant's difference and the verdict."""
    names = [PLANT_NAMES.get(p, p) for p in plants]
    metrics = list(pd.unique(table["metric"])) if len(table) else list(RANKED_METRICS)
    head = ["difference"]
    for metric in metrics:
        head += [f"{PAIRED_DISPLAY[metric][0]} {name}" for name in names] + ["holds?"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    if table.empty:
        return ["One planner: no pair to rank."]
    for (planner, base), rows in table.groupby(["planner", "baseline"], sort=False):
        cells = [f"{planner} − {base}"]
        for metric in metrics:
            row = rows[rows["metric"] == metric].iloc[0]
            cells += [_interval(row[f"{p}_mean"], row[f"{p}_low"], row[f"{p}_high"], metric) for p in plants]
            cells.append(str(row["verdict"]))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def holding_counts(table: pd.DataFrame, reference: str) -> dict[str, int]:
    """How many rankings of ``reference`` (its interval excluding zero) hold in every plant, and how many reverse.

    :param table: :func:`rankings`
    :param reference: the plant whose rankings are counted
    :return: ``{"ranked": ..., "holds": ..., "reversed": ...}``
    """
    ranked = (table[f"{reference}_low"] > 0) | (table[f"{reference}_high"] < 0)
    return {
        "ranked": int(ranked.sum()),
        "holds": int((ranked & (table["verdict"] == "holds")).sum()),
        "reversed": int((ranked & (table["verdict"] == "reversed")).sum()),
    }


def write_cross_plant(out: str | Path, runs_by_plant: Mapping[str, pd.DataFrame], planners: Sequence[str]) -> str:
    """Write ``plants.md`` (both tables) and ``plants.csv`` (:func:`rankings`) into ``out``.

    :param out: the report folder (each plant's own report in a subfolder named after it)
    :param runs_by_plant: ``metrics.csv`` rows per plant, the reference plant first
    :param planners: report names, in table order
    :return: one line: how many of the first plant's rankings hold in the others
    """
    out = Path(out)
    plants = list(runs_by_plant)
    ranks = rankings(runs_by_plant, planners)
    ranks.to_csv(out / "plants.csv", index=False)
    counts = holding_counts(ranks, plants[0])
    others = ", ".join(PLANT_NAMES.get(p, p) for p in plants[1:])
    line = (
        f"{counts['holds']} of the {counts['ranked']} rankings in {PLANT_NAMES.get(plants[0], plants[0])} (a pair "
        f"and a metric whose interval excludes zero) hold in {others}; {counts['reversed']} reverse"
    )
    text = [
        "# The planners in both plants",
        "",
        f"Each plant's own report: {', '.join(f'`{p}/`' for p in plants)}. Flow and delay: means over the runs; "
        "stopped: of all the scheduled vehicles, pooled over the runs; failed runs left out.",
        "",
        *side_by_side_markdown(side_by_side(runs_by_plant, planners)),
        "",
        "Paired differences over the scenarios (mean and 95 % bootstrap interval; later planner minus earlier one). "
        "A ranking *holds* when every plant gives it the same sign with an interval that excludes zero.",
        "",
        f"**{line}.**",
        "",
        *rankings_markdown(ranks, plants),
        "",
    ]
    (out / "plants.md").write_text("\n".join(text))
    return line
