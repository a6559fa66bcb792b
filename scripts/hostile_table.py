"""The hostile-planner table of docs/shield.md ("Measured"): every attack of
:mod:`envs.planners.hostile` behind the shield, on every layout, with the evaluation harness.

Per layout and planner: runs, collided vehicles, stuck runs (the watchdog: no crossing for
``STANDSTILL_LIMIT`` s while vehicles wait), interventions (share of vehicle-steps), planner errors
(steps), unresolved steps and the mean flow; printed as Markdown and written to ``--csv``::

    python scripts/hostile_table.py --scenarios 4 --duration 60 --seed 8383 --csv hostile.csv

``--faults bounds --shield-bounds declared`` runs them in the imperfect world at the declared bounds
(``scripts/fault_table.py``'s levels), the shields declared at them.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from envs.commands.evaluate import with_plant
from envs.evaluation.harness import evaluate, generate_scenarios
from envs.evaluation.metrics import STANDSTILL_LIMIT
from envs.planners.shield_bounds import ShieldBounds, parse_shield_bounds

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fault_table import LEVELS, level_faults  # noqa: E402

LAYOUTS = {"4way": "CoopIntersection4Way-v0", "3way": "CoopIntersection3Way-v0", "inD": "CoopIntersectionInD-v0"}
ATTACKS = (
    ("scene editing", "SceneEditor"),
    ("layout editing", "LayoutEditor"),
    ("collision seeking", "CollisionSeeker"),
    ("zone meeting and ramming", "ZoneMeeter"),
    ("random commands", "Fuzzer"),
    ("brake checks", "BrakeChecker"),
    ("parking inside the box", "BoxParker"),
    ("bang-bang", "BangBang"),
    ("NaN", "NaNPlanner"),
    ("holding before the line (watchdog takeovers)", "LineHolder"),
    ("crawling before the line (watchdog takeovers)", "Crawler"),
)


def hostile_table(
    scenarios: int,
    duration: float,
    seed: int,
    jobs: int,
    layouts=tuple(LAYOUTS),
    plant: str | None = None,
    human_share: float = 0.0,
    faults: str = "none",
    bounds: ShieldBounds | None = None,
) -> pd.DataFrame:
    """One row per layout and attack (see the module docstring); ``plant``: the env config's (``"sumo"``: SUMO,
    its drivers the humans), ``human_share``: the share of human drivers in the scenarios; ``faults``: a fault level
    of ``scripts/fault_table.py``; ``bounds``: the shields' declared bounds."""
    rows = []
    planners = [(f"envs.planners.hostile:{cls}+shield", attack) for attack, cls in ATTACKS]
    env_kwargs = with_plant({"config": {"faults": level_faults(faults)}} if faults != "none" else None, plant)
    with tempfile.TemporaryDirectory() as folder:
        for layout in layouts:
            files = generate_scenarios(
                Path(folder) / layout, scenarios, duration, seed, layout, human_share=human_share
            )
            runs, _ = evaluate(
                planners,
                files,
                LAYOUTS[layout],
                duration,
                seed=seed,
                jobs=jobs,
                env_kwargs=env_kwargs,
                progress=False,
                shield_bounds=bounds,
            )
            for (_, attack), cls in zip(planners, (c for _, c in ATTACKS)):
                r = runs[runs["planner"] == attack]
                rows.append(
                    {
                        "layout": layout,
                        "attack": attack,
                        "planner": cls,
                        "runs": len(r),
                        "collided": int(r["collided"].sum()),
                        "stuck_runs": int(r["stuck"].astype(bool).sum()),
                        "interventions": float(r["shield_interventions"].sum() / r["shield_vehicle_steps"].sum()),
                        "planner_errors": int(r["planner_errors"].sum()),
                        "unresolved": int(r["shield_unresolved"].sum()),
                        "flow_mean": float(r["flow_rate"].mean()),
                    }
                )
    return pd.DataFrame(rows)


def markdown(table: pd.DataFrame) -> str:
    lines = [
        "| layout | attack | runs | collided vehicles | stuck runs | interventions | planner errors [steps] "
        "| unresolved steps | flow [veh/s] |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in table.itertuples():
        lines.append(
            f"| {row.layout} | {row.attack} | {row.runs} | {row.collided} | {row.stuck_runs} "
            f"| {100 * row.interventions:.1f} % | {row.planner_errors} | {row.unresolved} | {row.flow_mean:.3f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", type=int, default=4, help="scenarios per layout (>= 1)")
    parser.add_argument("--duration", type=float, default=60.0, help="simulated seconds per run (> 0)")
    parser.add_argument("--seed", type=int, default=8383, help="base seed of the scenarios and runs")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (>= 1)")
    parser.add_argument("--layout", action="append", choices=sorted(LAYOUTS), help="layouts (default: all)")
    parser.add_argument("--csv", type=Path, default=None, help="also write the table here (never overwritten)")
    parser.add_argument("--plant", choices=["builtin", "sumo"], default=None, help="the plant (default: ours)")
    parser.add_argument("--human-share", type=float, default=0.0, help="share of human drivers, in [0, 1]")
    parser.add_argument("--faults", choices=LEVELS, default="none", help="fault level (scripts/fault_table.py)")
    parser.add_argument("--shield-bounds", default="none", help="the shields' declared bounds (none, declared, ...)")
    args = parser.parse_args(argv)
    try:
        bounds = parse_shield_bounds(args.shield_bounds)
    except ValueError as error:
        parser.error(str(error))
    if args.scenarios < 1 or args.jobs < 1 or not args.duration > 0:
        parser.error("--scenarios and --jobs must be >= 1 and --duration > 0")
    if not 0.0 <= args.human_share <= 1.0:
        parser.error("--human-share must be in [0, 1]")
    if args.csv is not None and args.csv.exists():
        parser.error(f"--csv: {args.csv} exists (never overwritten)")
    tic = time.perf_counter()
    layouts = tuple(args.layout or LAYOUTS)
    table = hostile_table(
        args.scenarios, args.duration, args.seed, args.jobs, layouts, args.plant, args.human_share, args.faults, bounds
    )
    print(markdown(table))
    print(
        f"\n{args.scenarios} scenarios x {args.duration:g} s per layout, seed {args.seed}, "
        f"plant {args.plant or 'builtin'}, human share {args.human_share:g}, faults {args.faults}, shield bounds "
        f"{bounds.text()}; stuck: no crossing for "
        f"{STANDSTILL_LIMIT:g} s while vehicles wait; {time.perf_counter() - tic:.0f} s wall"
    )
    if args.csv is not None:
        table.to_csv(args.csv, index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
