"""Demand sweep: planners against the arrival rate, each planner's capacity, and the figure.

The sweep runs every planner on scenarios drawn at several demand levels (arrivals per second and
major-road lane; minor-road lanes get half: :func:`envs.simulation.traffic.demand_scenario`) with the
evaluation harness, and reduces each level's ``summary.json`` (:func:`envs.evaluation.metrics.summarize`)
to one row per planner and level (:data:`SWEEP_COLUMNS`):

- ``flow_rate``: mean over the level's runs [veh/s];
- ``delay_mean_s``, ``stop_ratio``, ``collision_rate``: pooled over every scheduled vehicle;
- ``speed_limit_violations``: vehicle-steps above the lane limit, summed over the runs;
- ``slow_ratio`` (speed below 2 m/s, every scheduled vehicle), ``hard_brakes_per_vehicle`` and
  ``energy_kj_per_vehicle`` (vehicles that crossed): pooled, :func:`envs.evaluation.metrics.motion_metrics`;
- ``failed_runs``: runs that a planner error voided (left out of the figures; a planner every run of which
  failed at a level has no figures there, and the other planners are kept).

**Capacity** of a planner: the highest demand level up to which (at that level and every lower
one) its flow still serves at least :data:`SERVED_FRACTION` of the offered flow, i.e. of the
scheduled vehicles that would have crossed within the run in free flow (``offered_flow``). It is
``None`` when even the lowest level is not served, and the highest level when every level is (the
capacity is then at least that). The highest flow a planner reaches over the sweep is its
saturation flow, shown beside it.

**Penetration sweep** (mixed traffic): the same with the share of human drivers
(``human_share``) as the level instead of the demand (:data:`SHARE_COLUMNS`: ``human_share`` in
place of ``demand``, plus ``collisions_automated`` and ``collisions_human``, summed over the runs:
vehicles in collisions between automated vehicles only, and in collisions with a human driver in
them). It has no capacity.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from envs.evaluation.comparison import PAIRED_METRICS  # noqa: E402
from envs.evaluation.report import PAIRED_DISPLAY, format_number, planner_colors, signed_number  # noqa: E402

SWEEP_COLUMNS = (
    "planner",
    "demand",
    "flow_rate",
    "delay_mean_s",
    "stop_ratio",
    "collision_rate",
    "speed_limit_violations",
    "slow_ratio",
    "hard_brakes_per_vehicle",
    "energy_kj_per_vehicle",
    "failed_runs",
)
SHARE_COLUMNS = (
    "planner",
    "human_share",
    *SWEEP_COLUMNS[2:-1],
    "collisions_automated",
    "collisions_human",
    "failed_runs",
)
AXIS_LABELS = {"demand": "demand [veh/s per major-road lane]", "human_share": "share of human drivers"}
SERVED_FRACTION = 0.9
SWEEP_FILES = ("sweep.csv", "sweep.png", "sweep.md")


def _share(value: float) -> str:
    """A share in percent: one decimal, more significant digits below 0.1 % (a rare collision stays visible)."""
    if value is None or not np.isfinite(value):
        return "n/a"
    return f"{100 * value:.2g} %" if 0 < value < 0.001 else f"{100 * value:.1f} %"


def _count(value: float) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:,.0f}"


#: ``sweep.csv`` column -> (its heading in ``sweep.md``, how a value is written): percent for shares, kJ whole
SWEEP_DISPLAY = {
    "flow_rate": ("flow [veh/s]", format_number),
    "delay_mean_s": ("mean delay [s]", lambda v: format_number(v, 2)),
    "stop_ratio": ("stopped (below 0.3 m/s)", _share),
    "collision_rate": ("collided vehicles", _share),
    "speed_limit_violations": ("speed-limit violations [vehicle-steps]", _count),
    "slow_ratio": ("slowed below 2 m/s", _share),
    "hard_brakes_per_vehicle": ("hard brakes per vehicle", lambda v: format_number(v, 2)),
    "energy_kj_per_vehicle": ("energy [kJ per crossed vehicle]", lambda v: format_number(v, 0)),
    "collisions_automated": ("vehicles in collisions of automated vehicles only", _count),
    "collisions_human": ("vehicles in collisions with a human driver", _count),
    "offered_flow": ("offered flow [veh/s]", format_number),
    "failed_runs": ("failed runs (planner errors)", _count),
}


def level_folder(demand: float, axis: str = "demand") -> str:
    """Name of a level's subfolder, e.g. ``demand_0.05`` or ``human_share_0.25``."""
    return f"{axis}_{demand:g}"


def _at(summary: Mapping[str, Any], key: str, statistic: str) -> Any:
    """``summary[key][statistic]``, or ``None`` where the planner has no such figure (every run of it failed)."""
    return (summary.get(key) or {}).get(statistic)


def sweep_rows(
    demand: float,
    summary: Mapping[str, Mapping[str, Any]],
    axis: str = "demand",
    runs: pd.DataFrame | None = None,
) -> list[dict[str, Any]]:
    """The ``sweep.csv`` rows of one level (plus ``offered_flow``, used for the capacity).

    :param demand: the level [veh/s per major-road lane, or the share of human drivers]
    :param summary: that level's :func:`envs.evaluation.metrics.summarize` output
    :param axis: what the level is: ``"demand"`` or ``"human_share"``
    :param runs: that level's runs (``metrics.csv`` rows); with the ``human_share`` axis, the
        collisions per kind of driver are summed from it
    :return: one row per planner (one every run of which failed at this level: its figures ``None``, its
        ``failed_runs`` counted)
    """
    rows = [
        {
            "planner": name,
            axis: float(demand),
            "flow_rate": _at(s, "flow_rate", "mean"),
            "delay_mean_s": _at(s, "delay_s", "mean"),
            "stop_ratio": _at(s, "stop_ratio", "all"),
            "collision_rate": s.get("collision_rate"),
            "speed_limit_violations": s.get("speed_limit_violations"),
            "slow_ratio": s.get("slow_ratio"),
            "hard_brakes_per_vehicle": s.get("hard_brakes_per_vehicle"),
            "energy_kj_per_vehicle": s.get("energy_kj_per_vehicle"),
            "failed_runs": s.get("failed_runs", 0),
            "offered_flow": s.get("offered_flow"),
        }
        for name, s in summary.items()
    ]
    if axis == "human_share":
        for row in rows:
            mine = runs[runs["planner"] == row["planner"]] if runs is not None else pd.DataFrame()
            for column in ("collisions_automated", "collisions_human"):
                row[column] = int(mine[column].sum()) if column in mine else None
    return rows


def capacities(table: pd.DataFrame, fraction: float = SERVED_FRACTION) -> dict[str, float | None]:
    """Each planner's capacity (definition in the module docstring).

    :param table: sweep rows with ``planner``, ``demand``, ``flow_rate`` and ``offered_flow``
    :param fraction: share of the offered flow that must be served
    :return: ``planner -> demand level`` (``None``: not even the lowest level is served; NaN: unknown, as every
        run of the planner failed at a level up to its first unserved one)
    """
    out: dict[str, float | None] = {}
    for planner, rows in table.groupby("planner", sort=False):
        rows = rows.sort_values("demand")
        flow = rows["flow_rate"].astype(float).to_numpy()
        served = flow >= fraction * rows["offered_flow"].astype(float).to_numpy()
        first_short = int(np.argmin(served)) if not served.all() else len(served)
        if np.isnan(flow[: first_short + 1]).any():
            out[str(planner)] = float("nan")
        else:
            out[str(planner)] = float(rows["demand"].iloc[first_short - 1]) if first_short else None
    return out


def capacity_text(capacity: float | None, top: float, unit: str = "") -> str:
    """A capacity for people: ``"0.2"``, ``">= 0.4"`` (every level served), ``"below the lowest level"``,
    ``"unknown (every run failed at a level)"``.

    :param capacity: a :func:`capacities` value
    :param top: the highest demand level of the sweep
    :param unit: appended to a level, e.g. ``" veh/s per major-road lane"``
    """
    if capacity is None:
        return "below the lowest level"
    if not np.isfinite(capacity):
        return "unknown (every run failed at a level)"
    return (f">= {capacity:g}" if capacity >= top else f"{capacity:g}") + unit


def sweep_figure(
    table: pd.DataFrame, capacity: Mapping[str, float | None], path: Path, axis: str = "demand"
) -> None:
    """Flow, mean delay, stop ratio (top row), slow ratio, hard brakes per vehicle and energy per vehicle
    (bottom row) against the level, one line per planner, capacities marked.

    :param table: sweep rows (with ``offered_flow``)
    :param capacity: :func:`capacities` output (empty for the ``human_share`` axis)
    :param path: PNG file to write
    :param axis: the level's column, ``"demand"`` or ``"human_share"``
    """
    panels = (
        ("flow_rate", "flow [veh/s]"),
        ("delay_mean_s", "mean delay [s]"),
        ("stop_ratio", "stop ratio (below 0.3 m/s)"),
        ("slow_ratio", "slow ratio (below 2 m/s)"),
        ("hard_brakes_per_vehicle", "hard brakes per vehicle"),
        ("energy_kj_per_vehicle", "energy per crossed vehicle [kJ]"),
    )
    fig, axes = plt.subplots(2, 3, figsize=(12, 7.2))
    axes = axes.ravel()
    colors = planner_colors(table["planner"].nunique())  # never black: the offered flow's line
    offered = table.groupby(axis)["offered_flow"].mean()
    axes[0].plot(offered.index, offered.to_numpy(float), "k--", lw=1, label="offered (free flow)")
    for k, (planner, rows) in enumerate(table.groupby("planner", sort=False)):
        rows = rows.sort_values(axis)
        color = colors[k % len(colors)]
        cap = capacity.get(str(planner))
        label = str(planner) if axis != "demand" else f"{planner} (capacity {capacity_text(cap, table[axis].max())})"
        for ax, (column, _) in zip(axes, panels):
            values = rows[column].astype(float) if column in rows else np.full(len(rows), np.nan)
            ax.plot(rows[axis], values, "o-", color=color, label=label)
            if cap is not None and np.isfinite(cap):
                ax.axvline(cap, color=color, ls=":", lw=1)
        if cap is not None and np.isfinite(cap):
            at = rows[rows[axis] == cap]
            axes[0].plot(at[axis], at["flow_rate"].astype(float), "*", ms=14, color=color, mec="k")
    for ax, (_, label) in zip(axes, panels):
        ax.set_xlabel(AXIS_LABELS[axis])
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if axis == "demand":
        axes[0].set_title(f"★ / dotted: capacity (flow >= {100 * SERVED_FRACTION:.0f} % of offered)", fontsize=8)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


def sweep_markdown(
    table: pd.DataFrame,
    capacity: Mapping[str, float | None],
    paired: pd.DataFrame,
    meta: Mapping[str, Any],
    axis: str = "demand",
) -> str:
    """``sweep.md``: settings, capacities (demand axis), the sweep table and the paired differences per level.

    :param table: sweep rows (with ``offered_flow``)
    :param capacity: :func:`capacities` output
    :param paired: every level's :func:`envs.evaluation.comparison.paired_differences` with the ``axis`` column
    :param meta: settings shown as a list
    :param axis: the level's column, ``"demand"`` or ``"human_share"``
    :return: Markdown text
    """
    title = "Demand sweep" if axis == "demand" else "Penetration sweep (share of human drivers)"
    lines = [f"# {title}", "", *(f"- {key}: {value}" for key, value in meta.items()), ""]
    if axis == "demand":
        top = table["demand"].max()
        lines += ["## Capacity", ""]
        lines += [f"Highest demand level up to which a planner serves >= {100 * SERVED_FRACTION:.0f} %"]
        lines += ["of the offered flow; saturation flow: the highest flow it reaches in the sweep.", ""]
        lines += ["| planner | capacity [veh/s per major lane] | saturation flow [veh/s] |", "|---|---:|---:|"]
        for planner, rows in table.groupby("planner", sort=False):
            text = capacity_text(capacity.get(str(planner)), top)
            lines.append(f"| {planner} | {text} | {format_number(rows['flow_rate'].astype(float).max())} |")
        lines.append("")
    failed = table[table["failed_runs"].fillna(0) > 0] if "failed_runs" in table else table.iloc[:0]
    if not failed.empty:
        lines += ["## Failed runs", "", "Runs voided by a planner error (each level's report.md: the error lines):", ""]
        for row in failed.itertuples():
            every = " (every run)" if pd.isna(row.flow_rate) else ""
            level = f"{axis.replace('_', ' ')} {getattr(row, axis):g}"
            lines.append(f"- {row.planner}, {level}: {row.failed_runs:.0f}{every}")
        lines.append("")
    lines += ["## Every level", "", "![sweep](sweep.png)", ""]
    columns = [*(SWEEP_COLUMNS if axis == "demand" else SHARE_COLUMNS), "offered_flow"]
    headings = ["planner", AXIS_LABELS[axis], *(SWEEP_DISPLAY.get(c, (c, format_number))[0] for c in columns[2:])]
    lines += ["| " + " | ".join(headings) + " |", "|---|" + "---:|" * (len(columns) - 1)]
    for _, row in table.iterrows():
        cells = [str(row["planner"]), f"{row[axis]:g}"]
        cells += [SWEEP_DISPLAY.get(c, (c, format_number))[1](row[c]) for c in columns[2:]]
        lines.append("| " + " | ".join(cells) + " |")
    if not paired.empty:
        lines += ["", "## Against the strongest baseline of each level (mean per-scenario difference, 95 % CI)", ""]
        lines += ["pp: percentage points (a difference of two shares).", ""]
        headings = [PAIRED_DISPLAY.get(m, (f"Δ {x}", 1.0, 3))[0] for m, x in PAIRED_METRICS.items()]
        lines += [f"| {axis} | planner | baseline | " + " | ".join(headings) + " |"]
        lines.append("|---:|---|---|" + "---:|" * len(headings))
        for (level, planner), rows in paired.groupby([axis, "planner"], sort=False):
            by = rows.set_index("metric").reindex(list(PAIRED_METRICS))  # a missing metric reads n/a
            cells = []
            for m in PAIRED_METRICS:
                _, scale, digits = PAIRED_DISPLAY.get(m, ("", 1.0, 3))
                mean, low, high = (scale * float(by.loc[m, c]) for c in ("mean_difference", "ci_low", "ci_high"))
                cells.append(
                    f"{signed_number(mean, digits)} [{signed_number(low, digits)}, {signed_number(high, digits)}]"
                )
            lines.append(f"| {level:g} | {planner} | {rows['baseline'].iloc[0]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_sweep(
    out: str | Path,
    levels: Sequence[tuple[float, Mapping[str, Mapping[str, Any]], pd.DataFrame]],
    meta: Mapping[str, Any],
    axis: str = "demand",
    runs: Sequence[pd.DataFrame] | None = None,
) -> pd.DataFrame:
    """Write :data:`SWEEP_FILES` into ``out``.

    :param out: the sweep folder (exists)
    :param levels: per level: ``(level, summary, paired differences)``
    :param meta: settings shown at the top of ``sweep.md``
    :param axis: what the levels are: ``"demand"`` (:data:`SWEEP_COLUMNS`) or ``"human_share"``
        (:data:`SHARE_COLUMNS`, no capacity)
    :param runs: per level, its runs (needed for the collisions per kind of driver of the share axis)
    :return: the sweep table (``sweep.csv`` plus ``offered_flow``)
    """
    if axis not in AXIS_LABELS:
        raise ValueError(f"axis must be one of {', '.join(AXIS_LABELS)}, got {axis!r}")
    out = Path(out)
    per_level = list(runs) if runs is not None else [None] * len(levels)
    table = pd.DataFrame(
        [row for (level, summary, _), r in zip(levels, per_level) for row in sweep_rows(level, summary, axis, r)]
    )
    numbers = [c for c in table.columns if c != "planner"]
    table[numbers] = table[numbers].apply(pd.to_numeric)  # JSON's None -> NaN
    paired = [p.assign(**{axis: d}) for d, _, p in levels if not p.empty]
    paired = pd.concat(paired, ignore_index=True) if paired else pd.DataFrame(columns=[axis, "planner"])
    capacity = capacities(table) if axis == "demand" else {}
    table[list(SWEEP_COLUMNS if axis == "demand" else SHARE_COLUMNS)].to_csv(out / "sweep.csv", index=False)
    sweep_figure(table, capacity, out / "sweep.png", axis)
    (out / "sweep.md").write_text(sweep_markdown(table, capacity, paired, meta, axis))
    return table
