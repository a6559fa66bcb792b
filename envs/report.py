"""Evaluation report: tables (CSV, JSON, Markdown) and figures in the paper's style (PNG).

Files written into the report folder:

- ``metrics.csv``: one row per planner and run (:func:`envs.metrics.run_metrics` columns);
- ``vehicles.csv``: every vehicle of every run (the vehicle log, for re-analysis);
- ``summary.json``: per planner, :func:`envs.metrics.summarize`;
- ``report.md``: the tables;
- ``flow_rate.png``: flow-rate distribution per planner (box plot, paper Fig. "flow rate");
- ``stops_by_priority.png``: vehicles from the major and minor road and the share that stopped;
- ``stops_by_maneuver.png``: the same by maneuver.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from envs.metrics import PRIORITIES, stop_counts, summarize  # noqa: E402
from envs.scene import MANEUVERS  # noqa: E402

NOTES = (
    "- Vehicles counted: every vehicle that appeared in the scene during the run (stop ratio, collision "
    "rate). Scenario vehicles that could not appear because their lane was jammed back to the spawn "
    "point are not counted; `metrics.csv` reports them per run as `waiting_at_end`.",
    "- Flow rate: vehicles whose centre left the intersection area during the run, per simulated second.",
    "- Delay and travel time: vehicles that crossed during the run only, from their first appearance to "
    "leaving the intersection area; delay = travel time - (distance / approach speed limit). Vehicles "
    "still queued at the end are not in it, so a planner that starves one road can show a low delay.",
    "- Collisions: the vehicles involved are counted and removed, and the run goes on to its end "
    "(`collision_handling=\"remove\"`); only a run made with `\"terminate\"` ends early, and its flow rate "
    "is then taken over the simulated time until the collision (`terminated` in `metrics.csv`).",
)
FIGURES = ("flow_rate.png", "stops_by_priority.png", "stops_by_maneuver.png")
REPORT_FILES = ("metrics.csv", "vehicles.csv", "summary.json", "report.md") + FIGURES


def _pct(value: float | None) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{100 * value:.1f} %"


def format_number(value: float | None, digits: int = 3) -> str:
    """``value`` with ``digits`` decimals, ``"n/a"`` for a missing or non-finite value."""
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def markdown_report(
    summary: Mapping[str, Mapping[str, Any]],
    runs: pd.DataFrame,
    vehicles: pd.DataFrame,
    meta: Mapping[str, Any],
) -> str:
    """The Markdown report: settings, flow rate, stops, collisions and delay tables, reading notes.

    :param summary: :func:`envs.metrics.summarize` output
    :param runs: ``metrics.csv`` rows
    :param vehicles: all vehicle logs with a ``planner`` column
    :param meta: settings of the evaluation (env, scenarios, duration, seed, ...), shown as a list
    :return: Markdown text
    """
    lines = ["# Planner evaluation", ""]
    lines += [f"- {key}: {value}" for key, value in meta.items()]
    lines += ["", "## Flow rate [veh/s]", ""]
    lines += ["| planner | runs | median | q1 | q3 | mean | not spawned (jam), mean per run |"]
    lines += ["|---|---:|---:|---:|---:|---:|---:|"]
    for name, s in summary.items():
        f = s["flow_rate"]
        jam = (
            runs.loc[runs["planner"] == name, "waiting_at_end"].mean() if "waiting_at_end" in runs else np.nan
        )
        lines.append(
            f"| {name} | {s['runs']} | {format_number(f['median'])} | {format_number(f['q1'])} "
            f"| {format_number(f['q3'])} | {format_number(f['mean'])} | {format_number(jam, 1)} |"
        )
    groups = ("all",) + PRIORITIES + tuple(MANEUVERS)
    lines += ["", "## Stop ratio (vehicles whose speed fell below 0.3 m/s), stopped / vehicles", ""]
    lines += ["| planner | " + " | ".join(groups) + " |", "|---|" + "---:|" * len(groups)]
    for name, s in summary.items():
        counts = stop_counts(vehicles[vehicles["planner"] == name])
        cells = [f"{_pct(s['stop_ratio'][g])} ({counts[g][1]}/{counts[g][0]})" for g in groups]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Collisions and delay",
        "",
        "| planner | vehicles | collision rate | delay median [s] | delay mean [s] |",
    ]
    lines.append("|---|---:|---:|---:|---:|")
    for name, s in summary.items():
        d = s["delay_s"]
        lines.append(
            f"| {name} | {s['vehicles']} | {_pct(s['collision_rate'])} | {format_number(d['median'], 2)} "
            f"| {format_number(d['mean'], 2)} |"
        )
    shielded = [(name, s["shield_interventions"]) for name, s in summary.items() if "shield_interventions" in s]
    if shielded:
        lines += ["", "## Safety shield: commands replaced, share of vehicle-steps", ""]
        lines += ["| planner | interventions |", "|---|---:|"]
        lines += [f"| {name} | {_pct(rate)} |" for name, rate in shielded]
    lines += ["", "Figures: " + ", ".join(f"![{f}]({f})" for f in FIGURES), ""]
    lines += ["## How to read these numbers", "", *NOTES, ""]
    return "\n".join(lines)


def flow_rate_figure(runs: pd.DataFrame, planners: Sequence[str], path: Path) -> None:
    """Box plot of the flow rate per planner (one point per run).

    :param runs: ``metrics.csv`` rows
    :param planners: planners in display order
    :param path: PNG file to write
    """
    fig, ax = plt.subplots(figsize=(5, 3.2))
    data = [runs.loc[runs["planner"] == p, "flow_rate"].to_numpy(float) for p in planners]
    ax.boxplot(data, tick_labels=list(planners), showfliers=True, widths=0.5)
    ax.set_ylabel("flow rate [veh/s]")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


def stop_figure(
    vehicles: pd.DataFrame, planners: Sequence[str], column: str, groups: Sequence[str], path: Path
) -> None:
    """Grouped bars: vehicles per group (light) and those that stopped (dark), ratio on top.

    :param vehicles: all vehicle logs with a ``planner`` column
    :param planners: planners in display order
    :param column: ``"priority"`` or ``"maneuver"``
    :param groups: the values of ``column`` to show
    :param path: PNG file to write
    """
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(groups) * max(len(planners), 1) / 2, 3.4))
    width = 0.8 / max(len(planners), 1)
    x = np.arange(len(groups))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    top = 1.0
    for k, planner in enumerate(planners):
        sub = vehicles[vehicles["planner"] == planner]
        totals = np.array([(sub[column] == g).sum() for g in groups])
        stopped = np.array([((sub[column] == g) & sub["stopped"]).sum() for g in groups])
        pos = x - 0.4 + width * (k + 0.5)
        color = colors[k % len(colors)]
        ax.bar(pos, totals, width, color=color, alpha=0.35, label=f"{planner}: vehicles")
        ax.bar(pos, stopped, width, color=color, label=f"{planner}: stopped")
        for p, t, s in zip(pos, totals, stopped):
            label = f"{100 * s / t:.0f}%" if t else "n/a"
            ax.text(p, t, label, ha="center", va="bottom", fontsize=7)
        top = max(top, float(totals.max(initial=0)))
    ax.set_xticks(x, list(groups))
    ax.set_ylabel("vehicles")
    ax.set_ylim(0, top * 1.15)
    ax.legend(fontsize=7, ncol=max(len(planners), 1), loc="upper center", bbox_to_anchor=(0.5, -0.12))
    ax.set_title(f"stops by {'road priority' if column == 'priority' else column}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)


def add_shield_interventions(summary: dict, runs: pd.DataFrame) -> None:
    """Add ``shield_interventions`` (share of vehicle-steps whose command the shield replaced, over
    all runs) to the summary of every shielded planner (in place).

    :param summary: :func:`envs.metrics.summarize` output
    :param runs: ``metrics.csv`` rows; shielded runs carry ``shield_interventions`` and ``shield_vehicle_steps``
    """
    if "shield_interventions" not in runs:
        return
    for name, s in summary.items():
        rows = runs[(runs["planner"] == name) & runs["shield_vehicle_steps"].notna()]
        steps = float(rows["shield_vehicle_steps"].sum())
        if len(rows):
            s["shield_interventions"] = float(rows["shield_interventions"].sum()) / steps if steps else None


def write_report(
    out: str | Path, runs: pd.DataFrame, vehicles: pd.DataFrame, meta: Mapping[str, Any]
) -> dict:
    """Write every report file (:data:`REPORT_FILES`) into ``out`` (which must exist).

    :param out: report folder
    :param runs: one row per planner and run, with ``planner`` and ``scenario`` columns
    :param vehicles: all vehicle logs with ``planner`` and ``scenario`` columns
    :param meta: settings shown at the top of ``report.md``
    :return: the summary written to ``summary.json``
    """
    out = Path(out)
    planners = list(pd.unique(runs["planner"]))
    summary = summarize(runs, vehicles)
    add_shield_interventions(summary, runs)
    runs.to_csv(out / "metrics.csv", index=False)
    vehicles.to_csv(out / "vehicles.csv", index=False)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "report.md").write_text(markdown_report(summary, runs, vehicles, meta))
    flow_rate_figure(runs, planners, out / FIGURES[0])
    stop_figure(vehicles, planners, "priority", PRIORITIES, out / FIGURES[1])
    stop_figure(vehicles, planners, "maneuver", MANEUVERS, out / FIGURES[2])
    return summary
