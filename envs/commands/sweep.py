"""``sb3-graph sweep``: planners against traffic demand, with each planner's capacity.

Example::

    sb3-graph sweep --env CoopIntersection4Way-v0 --planner aim --planner fifo \\
        --planner envs/pretrained/coop_4way_fair/best_model.zip --demand 0.05 0.1 0.2 0.3 0.4 \\
        --scenarios 20 --duration 100 --seed 0 --jobs 2 --out reports/sweep

``--demand`` is the arrival rate per major-road lane [veh/s]; minor-road lanes get half of it (as
in the paper). For each level, ``--scenarios`` scenario files are drawn into
``<out>/demand_<level>/scenarios`` (scenario ``i`` of every level with seed ``seed + i``), and every
planner runs on all of them in one pool of ``--jobs`` workers with one progress bar (the harness of
``evaluate``). The folder receives ``sweep.csv`` (one row per planner and level, columns of
:data:`envs.evaluation.sweep.SWEEP_COLUMNS`), ``sweep.png``, ``sweep.md`` (capacities, the table, the paired
differences against the strongest baseline of each level) and, per level, the full ``evaluate``
report in ``demand_<level>/``, and ``run.json`` (runs, wall time, runs per second, executor). The
runs execute where ``--executor`` says, as for ``evaluate`` (``--executor dask
--scheduler-address tcp://host:8786`` runs the sweep on an existing Dask cluster, docs/cluster.md).
An existing ``--out`` is refused, never overwritten.

**Penetration sweep** (mixed traffic): ``--human-share 0 0.25 0.5 0.75 1`` sweeps the share of
human drivers instead of the demand. Scenario ``i`` of every share has the same arrivals (seed
``seed + i``; a share only flags vehicles as human-driven), drawn at the paper's rates or at one
``--demand`` level; each share's report is in ``human_share_<share>/``, ``sweep.csv`` has a
``human_share`` column in place of ``demand`` plus ``collisions_automated`` and ``collisions_human``
(:data:`envs.evaluation.sweep.SHARE_COLUMNS`), and ``sweep.png`` shows the metrics over the share.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Sequence

from envs.commands.evaluate import (
    _check,
    _destination,
    add_run_arguments,
    bounds_meta,
    checked_env,
    harness_meta,
    load_model_planners,
    run_harness,
    run_line,
    warn_beyond_bounds,
    write_run_info,
)
from sb3_graph.commands import UserError

DEFAULT_DEMAND = (0.05, 0.1, 0.2, 0.3, 0.4)
# Lowest demand level: one vehicle per lane in about 17 minutes (below, a run holds no traffic to compare).
MIN_DEMAND = 0.001


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser, scenarios=20, out="reports/sweep-<date>-<time>", per=" per demand level")
    parser.add_argument(
        "--demand",
        type=float,
        nargs="+",
        default=None,
        metavar="RATE",
        help=f"arrival rates per major-road lane [veh/s], each in [{MIN_DEMAND:g}, 1); minor-road lanes get half "
        f"(default: {' '.join(f'{d:g}' for d in DEFAULT_DEMAND)}; with --human-share: at most one level, default "
        "the paper's rates drawn per scenario)",
    )
    parser.add_argument(
        "--human-share",
        type=float,
        nargs="+",
        default=None,
        metavar="SHARE",
        help="sweep the share of human drivers instead of the demand (mixed traffic): each share in [0, 1], "
        "e.g. 0 0.25 0.5 0.75 1",
    )


def checked_demand(values: Sequence[float]) -> list[float]:
    """The ``--demand`` levels, sorted.

    :param values: the levels given
    :raises UserError: a level outside [MIN_DEMAND, 1) veh/s, or one given twice
    """
    for value in values:
        if not MIN_DEMAND <= value < 1:
            raise UserError(
                f"--demand: each level must be in [{MIN_DEMAND:g}, 1) veh/s per major-road lane (1 s minimum "
                f"headway), got {value:g}"
            )
    if len(set(values)) != len(values):
        raise UserError(f"--demand: a level is given twice in {' '.join(f'{v:g}' for v in values)}")
    return sorted(float(v) for v in values)


def checked_shares(values: Sequence[float]) -> list[float]:
    """The ``--human-share`` levels, sorted.

    :param values: the shares given
    :raises UserError: a share outside [0, 1], or one given twice
    """
    for value in values:
        if not 0 <= value <= 1:
            raise UserError(f"--human-share: each share must be in [0, 1], got {value:g}")
    if len(set(values)) != len(values):
        raise UserError(f"--human-share: a share is given twice in {' '.join(f'{v:g}' for v in values)}")
    return sorted(float(v) for v in values)


def _levels(args: argparse.Namespace) -> tuple[str, list[float], float | None]:
    """``(axis, levels, demand of every scenario)`` of the sweep asked for."""
    if args.human_share is None:
        return "demand", checked_demand(args.demand or DEFAULT_DEMAND), None
    shares = checked_shares(args.human_share)
    if args.demand is not None and len(args.demand) > 1:
        raise UserError("--demand: with --human-share, give at most one level (the sweep is over the share)")
    return "human_share", shares, checked_demand(args.demand)[0] if args.demand else None


def level_name(axis: str, level: float) -> str:
    """``demand 0.1`` or ``human share 0.25``: a level for people."""
    return f"{axis.replace('_', ' ')} {level:g}"


def run(args: argparse.Namespace) -> int:
    import pandas as pd

    from envs.evaluation.sweep import capacities, capacity_text
    from sb3_graph.files.output_folders import OutputError, staged_folder

    axis, demand, fixed = _levels(args)
    planners = _check(args)
    config = checked_env(args.env, args.env_kwargs)
    layout = str(config["layout"])
    load_model_planners(planners, config, args.trust_planner_files)
    warn_beyond_bounds(planners, args.shield_bounds, config)
    out = _destination(args, prefix="sweep")
    tic = time.perf_counter()
    try:
        with staged_folder(out) as stage:
            bounds = bounds_meta(args, config)
            table, wall, stats = _sweep(args, planners, demand, layout, stage, tic, axis, fixed, bounds)
    except OutputError as error:
        raise UserError(str(error)) from None
    if axis == "demand":
        for planner, cap in capacities(table).items():
            flow = table.loc[table["planner"] == planner, "flow_rate"].max()
            text = capacity_text(cap, demand[-1], " veh/s per major-road lane")
            highest = "n/a (every run failed)" if pd.isna(flow) else f"{flow:.3f} veh/s"
            print(f"{planner:>10}: capacity {text}, highest flow {highest}")
    print(run_line(stats))
    print_level_verdicts(out, demand, axis)
    print(f"sweep written to {out} ({wall:.1f} s)")
    failed = int(table["failed_runs"].fillna(0).sum())
    if failed:
        print_first_errors(out, demand, axis)
        print(f"{failed} runs failed on a planner error (sweep.md, and each level's report.md): exit status 1")
        return 1
    return 0


def print_first_errors(out, levels: Sequence[float], axis: str = "demand") -> None:
    """The first planner-error line of each planner that had one, from the levels' ``summary.json``."""
    import json

    from envs.evaluation.sweep import level_folder

    shown: set[str] = set()
    for level in levels:
        path = out / level_folder(level, axis) / "summary.json"
        summary = json.loads(path.read_text()) if path.is_file() else {}
        for name, s in summary.items():
            if s.get("planner_error_lines") and name not in shown:
                shown.add(name)
                print(f"{name}, {level_name(axis, level)}: {s['planner_error_lines'][0]}")


def print_level_verdicts(out, demand: Sequence[float], axis: str = "demand") -> None:
    """Who leads at each level, one line each (the full verdict opens each level's report.md).

    :param out: the sweep folder
    :param demand: the levels
    :param axis: ``"demand"`` or ``"human_share"``
    """
    import pandas as pd

    from envs.evaluation.sweep import level_folder
    from envs.evaluation.verdict import collided_by_planner, compact_verdict

    what = "demand level" if axis == "demand" else "human share"
    print(f"Who leads at each {what}, against its strongest baseline (each level's report.md: by how much):")
    for level in demand:
        path = out / level_folder(level, axis) / "paired.csv"
        paired = pd.read_csv(path) if path.is_file() and path.stat().st_size else pd.DataFrame()
        runs = out / level_folder(level, axis) / "metrics.csv"
        collided = None
        if runs.is_file() and not paired.empty:
            collided = collided_by_planner(pd.read_csv(runs, usecols=lambda c: c in ("planner", "collided")))
        print(f"  {level_name(axis, level)}: {compact_verdict(paired, collided=collided)}")
    return 0


def _sweep(args, planners, demand, layout, out, tic, axis="demand", fixed=None, bounds=None):
    """Run every level into ``out`` (the staging folder); return the sweep table, the wall time and the
    harness's stats. ``bounds``: the report's line on the shields' declared bounds (:func:`bounds_meta`)."""
    from envs.evaluation.comparison import paired_differences
    from envs.evaluation.harness import generate_scenarios
    from envs.evaluation.report import failed_runs, write_report
    from envs.evaluation.sweep import level_folder, write_sweep

    def draw(level: float) -> list:
        folder = out / level_folder(level, axis) / "scenarios"
        if axis == "demand":
            return generate_scenarios(folder, args.scenarios, args.duration, args.seed, layout, demand=level)
        return generate_scenarios(
            folder, args.scenarios, args.duration, args.seed, layout, demand=fixed, human_share=level
        )

    scenarios = [path for level in demand for path in draw(level)]
    runs, vehicles, stats = run_harness(args, planners, scenarios)
    wall = time.perf_counter() - tic
    meta = {
        "environment": args.env,
        "planners": ", ".join(f"{name} ({word})" for word, name in planners),
        **(
            {"demand levels": ", ".join(f"{d:g}" for d in demand) + " veh/s per major-road lane (minor: half)"}
            if axis == "demand"
            else {
                "human shares": ", ".join(f"{d:g}" for d in demand),
                "demand": "the paper's rates, drawn per scenario"
                if fixed is None
                else f"{fixed:g} veh/s per major-road lane (minor: half)",
            }
        ),
        "scenarios per level": f"{args.scenarios} (scenario i: seed {args.seed} + i)",
        "duration per run": f"{args.duration:g} s",
        **(bounds or {}),
        "jobs": args.jobs,
        **harness_meta(stats),
        "wall time": f"{wall:.1f} s",
        "python": platform.python_version(),
    }
    levels, level_runs_all = [], []
    for k, level in enumerate(demand):
        # evaluate() numbered the runs over all levels: level k holds runs k*N .. (k+1)*N - 1
        first = k * args.scenarios
        mine = runs["run"].between(first, first + args.scenarios - 1)
        level_runs = runs[mine].assign(run=runs.loc[mine, "run"] - first)
        taken = vehicles["run"].between(first, first + args.scenarios - 1)
        level_vehicles = vehicles[taken].assign(run=vehicles.loc[taken, "run"] - first)
        if axis == "demand":
            level_meta = {**meta, "demand": f"{level:g} veh/s per major-road lane (minor: half)"}
        else:
            level_meta = {**meta, "human share": f"{level:g}"}
        summary = write_report(out / level_folder(level, axis), level_runs, level_vehicles, level_meta)
        levels.append((level, summary, paired_differences(level_runs[~failed_runs(level_runs)])))
        level_runs_all.append(level_runs)
    table = write_sweep(out, levels, meta, axis, level_runs_all)
    write_run_info(out, stats, time.perf_counter() - tic)
    return table, wall, stats
