"""Evaluation report: tables (CSV, JSON, Markdown) and figures in the paper's style (PNG).

Files written into the report folder:

- ``metrics.csv``: one row per planner and run (:func:`envs.evaluation.metrics.run_metrics` columns);
- ``vehicles.csv``: every vehicle of every run (the vehicle log, for re-analysis);
- ``summary.json``: per planner, :func:`envs.evaluation.metrics.summarize`;
- ``report.md``: the verdict (:mod:`envs.evaluation.verdict`: who leads on flow, delay and stops, by how much,
  and whether the paired interval excludes zero), then the tables;
- ``flow_rate.png``: flow-rate distribution per planner (box plot, paper Fig. "flow rate"), with the
  offered flow (what a perfect planner reaches) as a dashed line;
- ``delay_collisions.png``: mean delay per run (box plot) and collided vehicles per planner (bars);
- ``stops_by_priority.png``: vehicles from the major and minor road and the share that stopped;
- ``stops_by_maneuver.png``: the same by maneuver;
- ``paired.csv``: per-scenario differences of every planner against the strongest baseline, with
  bootstrap 95 % intervals (:mod:`envs.evaluation.comparison`; no rows when no planner is a baseline).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from envs.evaluation.comparison import CONFIDENCE, PAIRED_DISPLAY, PAIRED_METRICS, paired_differences  # noqa: E402
from envs.evaluation.metrics import PRIORITIES, SPEED_TOLERANCE, stop_counts, summarize  # noqa: E402
from envs.evaluation.verdict import (  # noqa: E402
    VERDICT_METRICS,
    collided_by_planner,
    reference_comparison,
    reference_means,
    verdict_lines,
)
from envs.planners.shield_bounds import EXCURSION_COLUMNS  # noqa: E402
from envs.simulation.motion import HARD_BRAKE_ACCELERATION, SLOW_SPEED  # noqa: E402
from envs.simulation.scene import MANEUVERS, STOP_SPEED  # noqa: E402

NOTES = (
    "- Vehicles counted: every vehicle the scenario schedules within the run, the same set for every "
    "planner (`vehicles_scheduled`). A vehicle that could not appear because its lane was jammed back to "
    "the spawn point (`not spawned`) counts as stopped, with the delay from its scheduled appearance to "
    "the end of the run.",
    "- Flow rate: scheduled vehicles whose centre left the intersection area during the run, per simulated "
    "second. Offered flow: the scheduled vehicles that would have crossed within the run in free flow, per "
    "second (what a perfect planner reaches).",
    "- Delay: from the scheduled appearance, against the free-flow time along the route (lane and curve "
    "speed limits, the environment's acceleration bounds, from the scheduled initial speed). A vehicle still "
    "on its way at the end (or removed after a collision) gets the delay accumulated so far, a lower bound. "
    "Appearances and crossings happen at policy steps, so a delay includes up to two steps (0.4 s) of "
    "rounding; travel time: crossed vehicles, from the scheduled appearance to the crossing.",
    f"- Speed-limit violations: vehicle-steps faster than the lane limit by more than {SPEED_TOLERANCE} m/s. "
    "The simulation's speed governor prevents them for every planner; *governor held back* is the share of "
    "vehicle-steps in which it had to lower a planner's command (to the lane limit, or braking for a turn).",
    f"- Slow ratio: vehicles whose speed fell below {SLOW_SPEED:g} m/s at some simulation sub-step (a "
    f"vehicle that never appeared stands), so that creeping just above the {STOP_SPEED:g} m/s stop threshold "
    f"still shows; hard brakes: events of braking harder than {-HARD_BRAKE_ACCELERATION:g} m/s^2 (a maximal run "
    "of consecutive sub-steps), per scheduled vehicle; energy: traction energy at the wheels (positive power "
    "only, no recuperation) of a Euro 4 petrol passenger car (PHEMlight 5: mass, rolling and air resistance, "
    "inertia), per vehicle that crossed, from its appearance to its crossing. All three read the executed "
    "motion (after the shield and the speed governor), never a planner's command; see `docs/sweep.md`.",
    "- Paired differences: per scenario, planner minus the strongest baseline (the non-learned planner with "
    "the highest median flow, on a tie the lower mean delay); mean over scenarios with a "
    f"{100 * CONFIDENCE:.0f} % percentile bootstrap interval over scenarios.",
    "- Collisions: the vehicles involved are counted and removed, and the run goes on to its end "
    "(`collision_handling=\"remove\"`); only a run made with `\"terminate\"` ends early, and its flow rate "
    "is then taken over the simulated time until the collision (`terminated` in `metrics.csv`).",
)
FIGURES = ("flow_rate.png", "stops_by_priority.png", "stops_by_maneuver.png", "delay_collisions.png")
REPORT_FILES = ("metrics.csv", "vehicles.csv", "summary.json", "report.md", "paired.csv") + FIGURES


def percent(value: float | None) -> str:
    """A share as ``"12.3 %"`` (``"n/a"`` for a missing or non-finite value)."""
    return "n/a" if value is None or not np.isfinite(value) else f"{100 * value:.1f} %"


def collided_text(collided: int | None, vehicles: int) -> str:
    """``"2 / 9183 (0.022 %)"``: a count that a rounded rate would hide (``"n/a"`` without a count)."""
    if collided is None:
        return "n/a"
    share = f"{100 * collided / vehicles:.2g} %" if vehicles and collided else "0 %"
    return f"{collided} / {vehicles} ({share})"


def format_number(value: float | None, digits: int = 3) -> str:
    """``value`` with ``digits`` decimals, ``"n/a"`` for a missing or non-finite value."""
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def markdown_report(
    summary: Mapping[str, Mapping[str, Any]],
    runs: pd.DataFrame,
    vehicles: pd.DataFrame,
    meta: Mapping[str, Any],
    paired: pd.DataFrame | None = None,
    verdict: Sequence[str] = (),
) -> str:
    """The Markdown report: verdict, settings, flow rate, stops, collisions and delay tables, reading notes.

    :param summary: :func:`envs.evaluation.metrics.summarize` output
    :param runs: ``metrics.csv`` rows
    :param vehicles: all vehicle logs with a ``planner`` column
    :param meta: settings of the evaluation (env, scenarios, duration, seed, ...), shown as a list
    :param paired: :func:`envs.evaluation.comparison.paired_differences` output (a section when not empty)
    :param verdict: the verdict section's lines (:func:`envs.evaluation.verdict.verdict_lines`), first after the title
    :return: Markdown text
    """
    lines = ["# Planner evaluation", ""]
    if verdict:
        lines += [*verdict, "", "## Settings", ""]
    lines += [f"- {key}: {value}" for key, value in meta.items()]
    errors = {name: s for name, s in summary.items() if s.get("planner_error_lines")}
    summary = {name: s for name, s in summary.items() if "flow_rate" in s}  # planners with a measured run
    lines += ["", "## Flow rate [veh/s]", ""]
    lines += ["| planner | runs | median | q1 | q3 | mean | offered (mean) | not spawned (jam), per run |"]
    lines += ["|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, s in summary.items():
        f = s["flow_rate"]
        jam = s.get("not_spawned", 0) / s["runs"] if s["runs"] else np.nan
        lines.append(
            f"| {name} | {s['runs']} | {format_number(f['median'])} | {format_number(f['q1'])} "
            f"| {format_number(f['q3'])} | {format_number(f['mean'])} | {format_number(s.get('offered_flow'))} "
            f"| {format_number(jam, 1)} |"
        )
    groups = ("all",) + PRIORITIES + tuple(MANEUVERS)
    lines += ["", "## Stop ratio (vehicles whose speed fell below 0.3 m/s), stopped / vehicles", ""]
    lines += ["| planner | " + " | ".join(groups) + " |", "|---|" + "---:|" * len(groups)]
    for name, s in summary.items():
        counts = stop_counts(vehicles[vehicles["planner"] == name])
        cells = [f"{percent(s['stop_ratio'][g])} ({counts[g][1]}/{counts[g][0]})" for g in groups]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "## Collisions, delay and speed limits", ""]
    lines.append(
        "| planner | vehicles (scheduled) | collided vehicles | delay median [s] | delay mean [s] "
        "| speed-limit violations [vehicle-steps] | governor held back [% of vehicle-steps] |"
    )
    lines.append("|---|---:|---:|---:|---:|---:|---:|")
    for name, s in summary.items():
        d = s["delay_s"]
        lines.append(
            f"| {name} | {s['vehicles']} ({s.get('vehicles_scheduled', 'n/a')}) "
            f"| {collided_text(s.get('collided'), s['vehicles'])} "
            f"| {format_number(d['median'], 2)} | {format_number(d['mean'], 2)} "
            f"| {s.get('speed_limit_violations', 'n/a')} | {percent(s.get('governor_share'))} |"
        )
    lines += _motion_table(summary)
    if paired is not None and not paired.empty:
        lines += _paired_section(paired)
    shielded = [(name, s) for name, s in summary.items() if "shield_interventions" in s]
    if shielded:
        lines += ["", "## Safety shield: commands replaced, share of vehicle-steps", ""]
        lines += [
            "| planner | interventions | unresolved steps | planner errors (steps) | watchdog takeovers | stuck runs |"
        ]
        lines += ["|---|---:|---:|---:|---:|---:|"]
        lines += [
            f"| {name} | {percent(s['shield_interventions'])} | {s.get('shield_unresolved', 'n/a')} "
            f"| {s.get('planner_errors', 'n/a')} | {s.get('watchdog_takeovers', 'n/a')} "
            f"| {s.get('stuck_runs', 'n/a')} |"
            for name, s in shielded
        ]
    lines += _excursion_table(summary)
    if errors:
        lines += ["", "## Planner errors", ""]
        lines += ["Runs without the shield that a planner error voided are left out of every table above.", ""]
        for name, s in errors.items():
            lines.append(f"- {name}: {s.get('failed_runs', 0)} failed runs; first: `{s['planner_error_lines'][0]}`")
    lines += ["", "Figures: " + ", ".join(f"![{f}]({f})" for f in FIGURES), ""]
    lines += ["## How to read these numbers", "", *NOTES, ""]
    return "\n".join(lines)


def _excursion_table(summary: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Markdown table of the vehicle-steps planned on a measurement beyond the declared bounds (fault model)."""
    counted = [(name, s) for name, s in summary.items() if "fault_excursions" in s]
    if not counted:
        return []
    lines = ["", "## Beyond the declared bounds: vehicle-steps planned on a measurement beyond them", ""]
    lines += [
        "| planner | beyond any bound | position | speed | age | collided vehicles |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {name} | {s['fault_excursions']} | {s.get('excursions_position', 'n/a')} "
        f"| {s.get('excursions_speed', 'n/a')} | {s.get('excursions_age', 'n/a')} "
        f"| {collided_text(s.get('collided'), s['vehicles'])} |"
        for name, s in counted
    ]
    return lines


def _motion_table(summary: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Markdown table of the crawling, hard-braking and energy figures (pooled per planner)."""
    lines = ["", "## Crawling, hard braking and energy (the executed motion)", ""]
    lines.append(
        f"| planner | slow ratio (below {SLOW_SPEED:g} m/s) | stop ratio (below {STOP_SPEED:g} m/s) "
        f"| hard brakes per vehicle (below {HARD_BRAKE_ACCELERATION:g} m/s²) | energy per crossed vehicle [kJ] |"
    )
    lines.append("|---|---:|---:|---:|---:|")
    for name, s in summary.items():
        lines.append(
            f"| {name} | {percent(s.get('slow_ratio'))} | {percent(s['stop_ratio']['all'])} "
            f"| {format_number(s.get('hard_brakes_per_vehicle'), 2)} "
            f"| {format_number(s.get('energy_kj_per_vehicle'), 0)} |"
        )
    return lines


def signed_number(value: float, digits: int) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:+.{digits}f}"


def _paired_section(paired: pd.DataFrame) -> list[str]:
    """Markdown table of the paired differences (one row per planner, one column per metric)."""
    baseline = paired["baseline"].iloc[0]
    level = f"{100 * CONFIDENCE:.0f} %"
    lines = ["", f"## Against the strongest baseline ({baseline}): per-scenario differences", ""]
    lines.append(
        f"Mean of (planner - {baseline}) over paired scenarios, [{level} bootstrap interval]; "
        "pp: percentage points (a difference of two shares)."
    )
    metrics = [metric for metric in PAIRED_METRICS if metric in set(paired["metric"])]
    heading = [PAIRED_DISPLAY.get(m, (f"Δ {PAIRED_METRICS[m]}", 1.0, 3))[0] for m in metrics]
    lines += ["", "| planner | scenarios | " + " | ".join(heading) + " |"]
    lines.append("|---|---:|" + "---:|" * len(metrics))
    for planner, rows in paired.groupby("planner", sort=False):
        by_metric = rows.set_index("metric")
        cells = []
        for metric in metrics:
            r = by_metric.loc[metric]
            _, scale, digits = PAIRED_DISPLAY.get(metric, ("", 1.0, 3))
            low, mean, high = (scale * float(r[c]) for c in ("ci_low", "mean_difference", "ci_high"))
            cells.append(f"{signed_number(mean, digits)} [{signed_number(low, digits)}, {signed_number(high, digits)}]")
        lines.append(f"| {planner} | {int(rows['pairs'].max())} | " + " | ".join(cells) + " |")
    return lines


def _planner_axis(ax, planners: Sequence[str]) -> None:
    """Planner names as x tick labels that do not overlap (slanted when there are several)."""
    ax.set_xticks(np.arange(1, len(planners) + 1), list(planners))
    if len(planners) > 2 or max((len(p) for p in planners), default=0) > 12:
        plt.setp(ax.get_xticklabels(), rotation=30, ha="right", rotation_mode="anchor", fontsize=8)


def _figure_width(planners: Sequence[str]) -> float:
    return max(4.0, 1.5 + 0.9 * len(planners))


#: Widest figure, width over height: wider ones shrink their labels below reading size in a Markdown viewer.
MAX_ASPECT = 2.2  # the stop figures gain a little width when their legend is cropped to fit
#: Grey and black are the key swatches of the stop figures ("vehicles", "stopped"): no planner is drawn in them.
KEY_COLORS = ("black",)


def _figsize(width: float, height: float) -> tuple[float, float]:
    """``(width, height)`` in inches, the height raised where the figure would be wider than :data:`MAX_ASPECT`."""
    return width, max(height, width / MAX_ASPECT)


def planner_colors(count: int) -> list[str]:
    """One colour per planner, none grey or black (those are the legends' key swatches): matplotlib's
    ``tab10`` without its grey, then ``tab20``'s light shades without theirs, repeated beyond 18 planners.

    :param count: number of planners
    :return: hex colours, in planner order
    """
    from matplotlib import colors as mcolors

    palette = [
        mcolors.to_hex(c)
        for name in ("tab10", "tab20")
        for c in plt.get_cmap(name).colors[(0 if name == "tab10" else 1) :: (1 if name == "tab10" else 2)]
    ]
    palette = [c for c in palette if len({c[1:3], c[3:5], c[5:7]}) > 1]  # an equal R, G and B is a grey
    return [palette[k % len(palette)] for k in range(count)]


def flow_rate_figure(runs: pd.DataFrame, planners: Sequence[str], path: Path) -> None:
    """Box plot of the flow rate per planner (one point per run), and the offered flow (mean over
    runs, dashed): the flow a perfect planner reaches.

    :param runs: ``metrics.csv`` rows
    :param planners: planners in display order
    :param path: PNG file to write
    """
    fig, ax = plt.subplots(figsize=_figsize(_figure_width(planners), 3.6))
    data = [runs.loc[runs["planner"] == p, "flow_rate"].to_numpy(float) for p in planners]
    ax.boxplot(data, showfliers=True, widths=0.5)
    _planner_axis(ax, planners)
    if "offered_flow" in runs:
        offered = runs["offered_flow"].astype(float)
        if offered.notna().any():
            ax.axhline(float(offered.mean()), color="tab:green", ls="--", lw=1, label="offered flow (mean)")
            ax.legend(fontsize=8, loc="lower right")
    ax.set_ylabel("flow rate [veh/s]")
    ax.set_title("Flow rate per run (higher is better)", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


def dwarfed(values: Sequence[float], ratio: float = 20.0) -> bool:
    """Whether one bar dwarfs another so that a linear axis hides it: the largest value is more than ``ratio``
    times the smallest non-zero one.

    :param values: the bars' heights (zeros are drawn as no bar on any axis and do not count)
    :param ratio: the largest ratio a linear axis shows legibly
    """
    positive = np.asarray(values, float)
    positive = positive[np.isfinite(positive) & (positive > 0)]
    return positive.size > 1 and positive.max() > ratio * positive.min()


def delay_collision_figure(runs: pd.DataFrame, planners: Sequence[str], path: Path) -> None:
    """Mean delay per run (box plot, one point per run) and collided vehicles over all runs (bars,
    the count on top), per planner.

    :param runs: ``metrics.csv`` rows (``delay_mean`` and ``collided`` columns)
    :param planners: planners in display order
    :param path: PNG file to write
    """
    width = _figure_width(planners)
    if 2 * width <= 2.5 * 3.6:  # side by side (no legend below it widens a cropped figure), up to 3 planners
        fig, (left, right) = plt.subplots(1, 2, figsize=(2 * width, 3.6))
    else:  # one above the other: side by side, many planners make the figure too wide to read
        fig, (left, right) = plt.subplots(2, 1, figsize=_figsize(width, 7.2))
    delays = [runs.loc[runs["planner"] == p, "delay_mean"].to_numpy(float) for p in planners]
    left.boxplot([d[np.isfinite(d)] for d in delays], showfliers=True, widths=0.5)
    _planner_axis(left, planners)
    left.set_ylabel("mean delay per run [s]")
    left.set_title("Mean delay per run (lower is better)", fontsize=10)
    left.grid(axis="y", alpha=0.3)
    collided = [int(runs.loc[runs["planner"] == p, "collided"].fillna(0).sum()) if "collided" in runs else 0
                for p in planners]  # fmt: skip
    x = np.arange(1, len(planners) + 1)
    right.bar(x, collided, width=0.5, color="tab:red")
    for xi, count in zip(x, collided):
        right.text(xi, count, str(count), ha="center", va="bottom", fontsize=8)
    _planner_axis(right, planners)
    right.set_title("Collided vehicles, all runs (lower is better)", fontsize=10)
    if dwarfed(collided):  # e.g. 5229 beside 2: a linear axis would hide the small bars
        right.set_yscale("symlog", linthresh=1)
        right.set_ylim(0, max(collided) * 3)
        right.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        right.set_ylabel("collided vehicles (all runs, log scale)")
    else:
        right.set_ylabel("collided vehicles (all runs)")
        right.set_ylim(0, max(collided + [1]) * 1.2)
        right.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    right.grid(axis="y", alpha=0.3)
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
    fig, ax = plt.subplots(figsize=_figsize(min(10.0, 1.6 + 0.7 * len(groups) * max(len(planners), 1)), 3.4))
    width = 0.8 / max(len(planners), 1)
    x = np.arange(len(groups))
    colors = planner_colors(len(planners))
    top = 1.0
    for k, planner in enumerate(planners):
        sub = vehicles[vehicles["planner"] == planner]
        totals = np.array([(sub[column] == g).sum() for g in groups])
        stopped = np.array([((sub[column] == g) & sub["stopped"]).sum() for g in groups])
        pos = x - 0.4 + width * (k + 0.5)
        color = colors[k % len(colors)]
        ax.bar(pos, totals, width, color=color, alpha=0.35)
        ax.bar(pos, stopped, width, color=color, label=planner)
        for p, t, s in zip(pos, totals, stopped):
            label = f"{100 * s / t:.0f}%" if t else "n/a"
            ax.text(p, t, label, ha="center", va="bottom", fontsize=7)
        top = max(top, float(totals.max(initial=0)))
    ax.set_xticks(x, list(groups))
    ax.set_ylabel("vehicles")
    ax.set_ylim(0, top * 1.15)
    # one entry per planner (its colour), and what light and dark mean once, not once per planner
    from matplotlib.patches import Patch

    handles, _ = ax.get_legend_handles_labels()
    key = KEY_COLORS[0]
    handles += [Patch(color=key, alpha=0.35, label="vehicles (light)"), Patch(color=key, label="stopped (dark)")]
    columns = min(len(handles), max(2, int(fig.get_figwidth() // 1.8)))
    ax.legend(handles=handles, fontsize=9, ncol=columns, loc="upper center", bbox_to_anchor=(0.5, -0.12))
    what = "road priority" if column == "priority" else column
    ax.set_title(f"Vehicles that stopped, by {what} (share on top; lower is better)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)


def add_collided_counts(summary: dict, vehicles: pd.DataFrame) -> None:
    """Add ``collided`` (vehicles involved in a collision, over all runs; ``None`` where the log has no
    collision column, e.g. recorded drivers) to every planner's summary (in place).

    :param summary: :func:`envs.evaluation.metrics.summarize` output
    :param vehicles: all vehicle logs with a ``planner`` column
    """
    for name, s in summary.items():
        rows = vehicles.loc[vehicles["planner"] == name, "collided"] if "collided" in vehicles else None
        known = None if rows is None else rows.dropna()
        s["collided"] = None if known is None or (len(rows) and not len(known)) else int(known.astype(bool).sum())


def add_shield_interventions(summary: dict, runs: pd.DataFrame) -> None:
    """Add ``shield_interventions`` (share of vehicle-steps whose command the shield replaced, over
    all runs) and the run sums of ``shield_unresolved``, ``planner_errors`` and ``watchdog_takeovers``
    to the summary of every shielded planner (in place).

    :param summary: :func:`envs.evaluation.metrics.summarize` output
    :param runs: ``metrics.csv`` rows; shielded runs carry ``shield_interventions`` and ``shield_vehicle_steps``
    """
    if "shield_interventions" not in runs:
        return
    for name, s in summary.items():
        rows = runs[(runs["planner"] == name) & runs["shield_vehicle_steps"].notna()]
        steps = float(rows["shield_vehicle_steps"].sum())
        if len(rows):
            s["shield_interventions"] = float(rows["shield_interventions"].sum()) / steps if steps else None
            for column in ("shield_unresolved", "planner_errors", "watchdog_takeovers"):
                if column in rows:
                    s[column] = int(rows[column].fillna(0).sum())


def add_fault_excursions(summary: dict, runs: pd.DataFrame) -> None:
    """Add the run sums of :data:`envs.planners.shield_bounds.EXCURSION_COLUMNS` (vehicle-steps whose perceived state
    was beyond the declared bounds; runs with a fault model carry them) to every planner's summary (in place).

    :param summary: :func:`envs.evaluation.metrics.summarize` output
    :param runs: ``metrics.csv`` rows
    """
    if "fault_excursions" not in runs:
        return
    for name, s in summary.items():
        rows = runs[(runs["planner"] == name) & runs["fault_excursions"].notna()]
        if len(rows):
            for column in EXCURSION_COLUMNS:
                if column in rows:
                    s[column] = int(rows[column].sum())


def add_failures(summary: dict, runs: pd.DataFrame) -> None:
    """Add ``failed_runs`` and the planner-error lines to the summary of every planner with a planner
    error (in place); a planner all of whose runs failed gets an entry of its own.

    :param summary: :func:`envs.evaluation.metrics.summarize` output of the runs that did not fail
    :param runs: every ``metrics.csv`` row, with ``failed`` and ``planner_error``
    """
    if "planner_error" not in runs:
        return
    for name in pd.unique(runs["planner"]):
        rows = runs[runs["planner"] == name]
        failed = rows["failed"].fillna(False).astype(bool) if "failed" in rows else pd.Series(False, rows.index)
        lines = [str(x) for x in rows["planner_error"].dropna()]
        if not lines:
            continue
        entry = summary.setdefault(str(name), {"runs": 0})
        entry["failed_runs"] = int(failed.sum())
        entry["planner_error_lines"] = "\n".join(lines).splitlines()


def failed_runs(runs: pd.DataFrame) -> pd.Series:
    """``(rows,)`` bool: the runs that a planner error voided (``failed`` in ``metrics.csv``)."""
    if "failed" not in runs:
        return pd.Series(False, index=runs.index)
    return runs["failed"].fillna(False).astype(bool)


def report_verdict(runs: pd.DataFrame, paired: pd.DataFrame) -> list[str]:
    """The verdict section of ``report.md``: against the strongest baseline, or the first planner without one.

    :param runs: ``metrics.csv`` rows of the runs that did not fail
    :param paired: :func:`envs.evaluation.comparison.paired_differences` of ``runs``
    """
    table, kind = reference_comparison(runs, paired)
    means = reference_means(runs, table, list(VERDICT_METRICS))
    return verdict_lines(
        table,
        reference_means=means,
        reference_kind=kind,
        level=f"{100 * CONFIDENCE:.0f} %",
        collided=collided_by_planner(runs),
    )


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
    every = runs
    runs = runs[~failed_runs(every)]  # what the tables and figures measure; metrics.csv keeps every row
    if runs.empty:  # every run failed on a planner error: the errors are the report
        summary: dict = {}
        add_failures(summary, every)
        every.to_csv(out / "metrics.csv", index=False)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        (out / "report.md").write_text(markdown_report(summary, runs, vehicles, meta).split("Figures: ")[0])
        return summary
    planners = list(pd.unique(runs["planner"]))
    summary = summarize(runs, vehicles)
    paired = paired_differences(runs)
    verdict = report_verdict(runs, paired)
    add_collided_counts(summary, vehicles)
    add_shield_interventions(summary, runs)
    add_fault_excursions(summary, runs)
    add_failures(summary, every)
    every.to_csv(out / "metrics.csv", index=False)
    vehicles.to_csv(out / "vehicles.csv", index=False)
    paired.to_csv(out / "paired.csv", index=False)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "report.md").write_text(markdown_report(summary, runs, vehicles, meta, paired, verdict))
    flow_rate_figure(runs, planners, out / FIGURES[0])
    stop_figure(vehicles, planners, "priority", PRIORITIES, out / FIGURES[1])
    stop_figure(vehicles, planners, "maneuver", MANEUVERS, out / FIGURES[2])
    delay_collision_figure(runs, planners, out / FIGURES[3])
    return summary
