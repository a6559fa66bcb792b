"""``sb3-graph reward-check``: does a reward rank planners as the task metrics do? Check it before training.

A reward is a hypothesis about the task. Run the candidate planners once with ``sb3-graph
evaluate`` (every run's return under each reward preset is in ``metrics.csv``: ``return_task``,
``return_paper``, and ``return`` under the environment's configured reward), then::

    sb3-graph evaluate --planner pr --planner fifo --planner aim --planner signal \\
        --planner envs/planners/adversarial.py:FullThrottle+shield \\
        --planner envs/planners/adversarial.py:RandomAccel+shield \\
        --planner envs/pretrained/coop_4way_fair/best_model.safetensors+shield --scenarios 10 --trust-planner-files \\
        --out reports/reward_check
    sb3-graph reward-check reports/reward_check

Per planner: the mean flow rate, mean delay, stop ratio and the mean return under every reward;
per reward: Spearman's rank correlation of the planners' mean returns with their flow rate, with
their mean delay and with their stop ratio. A reward that ranks like the task has rho near +1 with
flow and near -1 with delay (and, since a stop costs its driver time and energy, below 0 with
stops). ``--min-rho`` makes the command fail (exit 1) when the reward named by ``--reward``
misses ``rho(flow) >= min`` or ``rho(delay) <= -min``, so a training script can refuse to start.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from sb3_graph.commands import UserError

if TYPE_CHECKING:  # pandas loads when the command runs, not for --help
    import pandas as pd

TASK_COLUMNS = ("flow_rate", "delay_mean", "stop_ratio_all", "collision_rate")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``sb3-graph reward-check``."""
    parser.add_argument("reports", nargs="+", metavar="REPORT", help="sb3-graph evaluate report folders or metrics.csv")
    parser.add_argument(
        "--reward",
        default="task",
        help="the reward whose ranking --min-rho checks (a return_<name> column; default: task)",
    )
    parser.add_argument(
        "--min-rho",
        type=float,
        default=None,
        help="fail unless rho(flow) >= MIN and rho(delay) <= -MIN (MIN in [0, 1])",
    )


def read_runs(reports: list[str]) -> pd.DataFrame:
    """The rows of the reports' ``metrics.csv`` files, concatenated.

    :raises UserError: a missing file, or a file without the task and return columns
    """
    import pandas as pd

    frames = []
    for report in reports:
        path = Path(report)
        path = path / "metrics.csv" if path.is_dir() else path
        if not path.is_file():
            raise UserError(f"REPORT: {str(report)!r} holds no metrics.csv (an sb3-graph evaluate report)")
        try:
            frame = pd.read_csv(path)
        except (OSError, ValueError, UnicodeDecodeError) as error:
            raise UserError(f"REPORT: {str(path)!r} is not a readable CSV ({error})") from None
        missing = [c for c in ("planner", *TASK_COLUMNS) if c not in frame]
        if missing or not any(c.startswith("return_") for c in frame):
            raise UserError(
                f"REPORT: {str(path)!r} lacks the columns {missing or ['return_<reward>']} "
                "(write it with this version of sb3-graph evaluate)"
            )
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def reward_table(runs: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per-planner means and, per reward, the rank correlations of its mean returns with flow and delay.

    :param runs: rows of ``metrics.csv`` (one per planner and scenario)
    :return: ``(planners, correlations)``: ``planners`` indexed by planner with the task columns and
        one column per reward; ``correlations`` indexed by reward with ``rho_flow``, ``rho_delay`` and ``rho_stops``
    """
    import pandas as pd

    returns = sorted(c for c in runs if c.startswith("return_"))
    for column in (*TASK_COLUMNS, *returns):
        runs[column] = pd.to_numeric(runs[column], errors="coerce")
    planners = runs.groupby("planner", sort=False)[[*TASK_COLUMNS, *returns]].mean()
    ranks = planners.rank()  # Spearman's rho is Pearson's on ranks (average ranks for ties); no SciPy needed
    rows = {}
    for column in returns:
        rows[column.removeprefix("return_")] = {
            "rho_flow": ranks[column].corr(ranks["flow_rate"]),
            "rho_delay": ranks[column].corr(ranks["delay_mean"]),
            "rho_stops": ranks[column].corr(ranks["stop_ratio_all"]),
        }
    return planners, pd.DataFrame.from_dict(rows, orient="index")


def run(args: argparse.Namespace) -> int:
    """Run the command (see the module docstring)."""
    if args.min_rho is not None and not 0 <= args.min_rho <= 1:
        raise UserError(f"--min-rho: must be in [0, 1], got {args.min_rho}")
    runs = read_runs(args.reports)
    planners, correlations = reward_table(runs)
    if len(planners) < 3:
        raise UserError(f"REPORT: {len(planners)} planner(s); a rank correlation needs at least 3")
    if args.reward not in correlations.index:
        raise UserError(f"--reward: {args.reward!r} is not in the reports; choose from {sorted(correlations.index)}")
    print(f"{len(planners)} planners, {len(runs)} runs (means over runs):")
    print(planners.sort_values("flow_rate", ascending=False).to_string(float_format=lambda v: f"{v:.3f}"))
    print("\nSpearman rank correlation of the planners' mean return with their flow rate, mean delay and stop ratio:")
    print(correlations.to_string(float_format=lambda v: f"{v:+.2f}"))
    if args.min_rho is None:
        return 0
    rho_flow, rho_delay = correlations.loc[args.reward, ["rho_flow", "rho_delay"]]
    ok = not (math.isnan(rho_flow) or math.isnan(rho_delay)) and rho_flow >= args.min_rho and rho_delay <= -args.min_rho
    verdict = "ranks like the task" if ok else "does NOT rank like the task"
    print(
        f"\nreward {args.reward!r} {verdict}: rho(flow) {rho_flow:+.2f}, rho(delay) {rho_delay:+.2f}, "
        f"min {args.min_rho}"
    )
    return 0 if ok else 1
