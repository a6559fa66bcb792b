"""Planners in an imperfect world: a table over fault levels (the environment's ``faults``, envs.simulation.faults),
with each planner's paired difference against full throttle behind the shield at the same level.

Per demand, fault level and perception (``tracker``: the planners and the shield see a Kalman tracker's estimate;
``raw``: the held, aged measurements): runs, flow [veh/s], mean delay [s], stop ratio, collided vehicles, stuck
runs, the shield's unresolved steps, and the paired mean differences against ``fullthrottle+shield`` (flow, delay,
with 95 % bootstrap intervals over scenarios); ``kept`` is the share of the planner's exact-state lead in delay over
full throttle that survives at that level (its difference at the level over its difference with no faults; only
where that exact-state lead's interval excludes zero: a lead within the noise has no share to keep);
``beyond`` the vehicle-steps planned on a measurement beyond the shields' declared bounds (``--shield-bounds``,
:mod:`envs.planners.shield_bounds`). A planner may be labelled (``advice=path/to/model.safetensors+shield``).
Printed as Markdown and written to ``--csv``::

    python scripts/fault_table.py --planner glide+shield --planner lookahead+shield --demand 0.3 0.5 \\
        --scenarios 4 --duration 100 --seed 9191 --shield-bounds declared --csv faults.csv
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from envs.evaluation.comparison import paired_differences
from envs.evaluation.harness import evaluate, generate_scenarios, layout_of
from envs.planners.shield_bounds import ShieldBounds, parse_shield_bounds

BASELINE = "fullthrottle+shield"
# The declared bounds of the imperfect world (position and speed error, loss and the age of a held state, latency,
# actuation lag); "mild" is half of them, "twice" twice.
BOUNDS = {
    "position_sigma": 1.0,
    "position_bound": 3.0,
    "position_tau": 1.0,
    "speed_sigma": 0.3,
    "speed_bound": 1.0,
    "loss": 0.05,
    "max_age": 1.0,
    "latency": 0.1,
    "lag": 0.3,
}
_SCALED = ("position_sigma", "position_bound", "speed_sigma", "speed_bound", "loss", "max_age", "latency", "lag")


def level_faults(level: str, custom: dict[str, dict] | None = None) -> dict:
    """The ``faults`` setting of a fault level: ``none``, ``mild`` (half the bounds), ``bounds``, ``twice``, or one
    of ``custom`` (name -> faults)."""
    if custom and level in custom:
        return dict(custom[level])
    factor = {"none": 0.0, "mild": 0.5, "bounds": 1.0, "twice": 2.0}[level]
    if factor == 0:
        return {}
    return {key: (value * factor if key in _SCALED else value) for key, value in BOUNDS.items()}


LEVELS = ("none", "mild", "bounds", "twice")


def fault_runs(
    planners: list[str], demands: list[float], levels: list[str], trackers: list[bool], env_id: str,
    scenarios: int, duration: float, seed: int, jobs: int, custom: dict[str, dict] | None = None,
    bounds: ShieldBounds | None = None,
) -> pd.DataFrame:  # fmt: skip
    """Every planner and the baseline at every demand, fault level and perception: the harness's run rows, tagged.
    ``planners``: words or ``LABEL=WORD`` (the label names the planner's rows)."""
    pairs = [_labelled(word) for word in dict.fromkeys([BASELINE, *planners])]
    frames = []
    with tempfile.TemporaryDirectory() as folder:
        for demand in demands:
            files = generate_scenarios(
                Path(folder) / f"demand_{demand:g}", scenarios, duration, seed, layout_of(env_id), demand=demand
            )
            for level in levels:
                for tracker in trackers if level != "none" else [True]:
                    faults = level_faults(level, custom)
                    if faults:
                        faults["tracker"] = tracker
                    runs, _ = evaluate(
                        pairs, files, env_id, duration, seed=seed, jobs=jobs,
                        env_kwargs={"config": {"faults": faults}}, progress=False, shield_bounds=bounds,
                    )  # fmt: skip
                    runs.insert(0, "perception", "tracker" if tracker else "raw")
                    runs.insert(0, "level", level)
                    runs.insert(0, "demand", demand)
                    frames.append(runs)
    return pd.concat(frames, ignore_index=True)


def _labelled(word: str) -> tuple[str, str]:
    """``(word, name)`` of ``LABEL=WORD`` (the label keeps its ``+shield``), or ``(word, word)``."""
    label, sep, spec = word.partition("=")
    if sep and "/" not in label:
        return spec, label + ("+shield" if spec.endswith("+shield") and not label.endswith("+shield") else "")
    return word, word


def fault_table(runs: pd.DataFrame, baseline: str = BASELINE) -> pd.DataFrame:
    """One row per demand, level, perception and planner (see the module docstring), paired against ``baseline``
    (a planner name of the runs)."""
    rows = []
    lead: dict[tuple[float, str], float] = {}
    for (demand, level, perception), group in runs.groupby(["demand", "level", "perception"], sort=False):
        ok = group[~group["failed"].astype(bool)] if "failed" in group else group
        diffs = paired_differences(ok, baseline=baseline).set_index(["planner", "metric"])
        for planner, r in ok.groupby("planner", sort=False):
            row = {
                "demand": demand, "level": level, "perception": perception, "planner": planner, "runs": len(r),
                "flow": r["flow_rate"].mean(), "delay": r["delay_mean"].mean(), "stops": r["stop_ratio_all"].mean(),
                "collided": int(r["collided"].sum()), "stuck_runs": int(r["stuck"].astype(bool).sum()),
                "unresolved": int(r.get("shield_unresolved", pd.Series([0])).sum()),
                "beyond": int(r["fault_excursions"].fillna(0).sum()) if "fault_excursions" in r else 0,
            }  # fmt: skip
            for metric, name in (("flow_rate", "d_flow"), ("delay_mean", "d_delay")):
                if (planner, metric) in diffs.index:
                    d = diffs.loc[(planner, metric)]
                    row.update({name: d["mean_difference"], f"{name}_low": d["ci_low"], f"{name}_high": d["ci_high"]})
            if level == "none" and "d_delay" in row:
                lead[demand, planner] = row["d_delay"] if row.get("d_delay_high", 0.0) < 0 else np.nan
            rows.append(row)
    table = pd.DataFrame(rows)
    if "d_delay" in table:
        exact = np.array([lead.get((d, p), np.nan) for d, p in zip(table["demand"], table["planner"])])
        table["kept"] = np.where(exact < 0, table["d_delay"] / exact, np.nan)
    return table


def _interval(row, name: str, decimals: int) -> str:
    value = row.get(name)
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value:+.{decimals}f} [{row[name + '_low']:+.{decimals}f}, {row[name + '_high']:+.{decimals}f}]"


def markdown(table: pd.DataFrame) -> str:
    lines = [
        "| demand | faults | perception | planner + shield | flow [veh/s] | delay [s] | stops | collided | stuck runs "
        "| unresolved | beyond the bounds | Δ flow vs full throttle | Δ delay vs full throttle | lead kept |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in table.to_dict("records"):
        kept = row.get("kept")
        kept_text = f"{100 * kept:.0f} %" if kept is not None and np.isfinite(kept) and row["level"] != "none" else ""
        lines.append(
            f"| {row['demand']:g} | {row['level']} | {row['perception']} | {row['planner'].removesuffix('+shield')} "
            f"| {row['flow']:.3f} | {row['delay']:.2f} | {100 * row['stops']:.0f} % | {row['collided']} "
            f"| {row['stuck_runs']} | {row['unresolved']} | {row.get('beyond', 0)} | {_interval(row, 'd_flow', 3)} "
            f"| {_interval(row, 'd_delay', 2)} | {kept_text} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planner", action="append", help="planners beside full throttle (default: glide+shield)")
    parser.add_argument("--demand", type=float, nargs="+", default=[0.3, 0.5], help="veh/s per major lane")
    parser.add_argument("--level", action="append", choices=LEVELS, help="fault levels (default: all)")
    parser.add_argument(
        "--custom", action="append", default=[], metavar="NAME=JSON",
        help="a fault level of one's own, e.g. 'lag=' + '{\"lag\": 0.3}' (repeatable; an ablation of one fault)",
    )  # fmt: skip
    parser.add_argument("--perception", choices=("tracker", "raw", "both"), default="both")
    parser.add_argument("--env", default="CoopIntersection4Way-v0", help="environment id")
    parser.add_argument("--scenarios", type=int, default=4, help="scenarios per demand (>= 1)")
    parser.add_argument("--duration", type=float, default=100.0, help="simulated seconds per run (> 0)")
    parser.add_argument("--seed", type=int, default=9191, help="base seed of the scenarios, runs and fault draws")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (>= 1)")
    parser.add_argument("--csv", type=Path, default=None, help="also write the runs here (never overwritten)")
    parser.add_argument("--runs", type=Path, default=None, help="read the runs of an earlier --csv instead of running")
    parser.add_argument("--baseline", default=BASELINE, help=f"the planner paired against (default: {BASELINE})")
    parser.add_argument(
        "--shield-bounds", default="none", help="the faults the shields are declared to tolerate: none, declared, or "
        "KEY=VALUE,... (as sb3-graph evaluate); excursions beyond them are counted",
    )  # fmt: skip
    args = parser.parse_args(argv)
    try:
        bounds = parse_shield_bounds(args.shield_bounds)
    except ValueError as error:
        parser.error(str(error))
    if args.scenarios < 1 or args.jobs < 1 or not args.duration > 0:
        parser.error("--scenarios and --jobs must be >= 1 and --duration > 0")
    if args.csv is not None and args.csv.exists():
        parser.error(f"--csv: {args.csv} exists (never overwritten)")
    trackers = {"tracker": [True], "raw": [False], "both": [True, False]}[args.perception]
    custom = {}
    for item in args.custom:
        name, _, text = item.partition("=")
        try:
            custom[name] = json.loads(text)
        except json.JSONDecodeError as error:
            parser.error(f"--custom {item!r}: not NAME=JSON ({error.msg})")
    chosen = args.level or ([] if custom else list(LEVELS))
    levels = list(dict.fromkeys(["none", *chosen, *custom]))  # the exact world: the lead to compare with
    tic = time.perf_counter()
    if args.runs is not None:
        runs = pd.read_csv(args.runs)
        print(markdown(fault_table(runs, args.baseline)).replace("vs full throttle", f"vs {args.baseline}"))
        return 0
    runs = fault_runs(
        args.planner or ["glide+shield"], args.demand, levels, trackers, args.env, args.scenarios, args.duration,
        args.seed, args.jobs, custom, bounds,
    )  # fmt: skip
    print(markdown(fault_table(runs, args.baseline)).replace("vs full throttle", f"vs {args.baseline}"))
    print(
        f"\n{args.env}, {args.scenarios} scenarios x {args.duration:g} s per demand, seed {args.seed}; faults at "
        f"'bounds': {BOUNDS} ('mild' half, 'twice' double); shield bounds {bounds.text()}; "
        f"{time.perf_counter() - tic:.0f} s wall"
    )
    if args.csv is not None:
        runs.to_csv(args.csv, index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
