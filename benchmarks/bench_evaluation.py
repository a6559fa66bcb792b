"""Wall time and runs per second of the evaluation harness: the main job and a small sweep.

The *main job* is ``sb3-graph evaluate`` with its default planners (pr, fifo, aim, signal, full
throttle behind the shield, the shipped GNN planner without and with the shield) on ``--scenarios``
generated scenarios of ``--duration`` simulated seconds; the *sweep* is ``sb3-graph sweep`` with pr
and fifo at two demand levels. Each runs as its own ``python -m sb3_graph.cli`` process with
``--jobs`` workers, so the wall time is what a user waits for (Python start, scenario generation,
worker start-up, the runs, the report). Runs per second: planner-scenario runs over that wall time.
CPU seconds: user + system time of the command and every worker it started (``RUSAGE_CHILDREN``),
which a busy shared machine inflates far less than the wall time.

``--checkout DIR`` (repeatable) names source trees to measure, each put first on ``PYTHONPATH``
(e.g. an older commit unpacked with ``git archive COMMIT | tar -x -C DIR``); the checkouts are
measured in turns, ``--repeat`` times, so a load change on a shared machine hits them alike.
``--executor dask`` adds the same jobs on a Dask ``LocalCluster`` of ``--jobs`` workers (checkouts
that have ``--executor`` only). ``--job read`` prints what reading one scenario file costs, which
the old harness paid once per run and the new one once per scenario. Prints a markdown table with
the machine, its load and the command.

Run: ``python benchmarks/bench_evaluation.py [--scenarios 4] [--duration 100] [--jobs 2]
[--checkout DIR ...] [--executor dask] [--job main|sweep|read ...] [--repeat 1]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
DEFAULT_PLANNERS = 7  # pr, fifo, aim, signal, fullthrottle+shield, GNN, GNN+shield (envs.commands.evaluate)
SWEEP_PLANNERS = ("pr", "fifo")
SWEEP_DEMAND = ("0.1", "0.3")


def _job(kind: str, args: argparse.Namespace, out: Path, executor: str) -> tuple[list[str], int]:
    """The command line of one job and the number of runs it makes."""
    common = ["--scenarios", str(args.scenarios), "--duration", str(args.duration), "--seed", "0"]
    common += ["--jobs", str(args.jobs), "--no-progress", "--out", str(out)]
    if executor != "local":
        common += ["--executor", executor]
    if kind == "main":
        return ["evaluate", *common], DEFAULT_PLANNERS * args.scenarios
    planners = [word for p in SWEEP_PLANNERS for word in ("--planner", p)]
    return ["sweep", *planners, "--demand", *SWEEP_DEMAND, *common], (
        len(SWEEP_PLANNERS) * len(SWEEP_DEMAND) * args.scenarios
    )


def _measure(checkout: Path, kind: str, args: argparse.Namespace, executor: str, scratch: Path) -> dict:
    out = scratch / f"{len(list(scratch.iterdir()))}"
    argv, runs = _job(kind, args, out, executor)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(checkout), os.environ.get("PYTHONPATH", "")])}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    tic = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "sb3_graph.cli", *argv], env=env, cwd=scratch, capture_output=True, text=True
    )
    wall = time.perf_counter() - tic
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed in {checkout}:\n{done.stderr[-2000:]}")
    row = {"checkout": checkout.name, "job": kind, "executor": executor, "runs": runs, "wall_s": wall, "cpu_s": cpu}
    row["runs_per_s"] = runs / wall
    info = out / "run.json"  # written by checkouts with the pluggable harness
    row["harness_runs_per_s"] = json.loads(info.read_text())["runs_per_s"] if info.is_file() else None
    row["load"] = os.getloadavg()[0]  # 1-minute load average at the end
    found = re.search(r"\((\d+\.\d) s\)\s*$", done.stdout)
    row["command_s"] = float(found.group(1)) if found else None  # the command's own figure
    return row


def _has_executors(checkout: Path) -> bool:
    """Whether a checkout's harness takes an executor (envs/ grouped by question since issue #25, flat before)."""
    return any((checkout / "envs" / sub / "executors.py").is_file() for sub in ("evaluation", "."))


def _read_cost(duration: float) -> str:
    """What a run paid before the table was shared: reading its scenario file (this tree's code)."""
    import pickle

    sys.path.insert(0, str(HERE))
    from envs.evaluation.harness import generate_scenarios
    from envs.simulation.traffic import Scenario

    with tempfile.TemporaryDirectory() as folder:
        path = generate_scenarios(folder, 1, duration, 0, "4way")[0]
        tic = time.perf_counter()
        for _ in range(50):
            scenario = Scenario.load(path)
        read = (time.perf_counter() - tic) / 50
        size = path.stat().st_size
    return (
        f"scenario file of {duration:g} s ({scenario.num_vehicles} vehicles, {size} B): read and checked in "
        f"{1e3 * read:.2f} ms (mean of 50); pickled for the workers: {len(pickle.dumps(scenario))} B"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", type=int, default=4, help="scenarios (per demand level) (default: 4)")
    parser.add_argument("--duration", type=float, default=100.0, help="simulated seconds per run (default: 100)")
    parser.add_argument("--jobs", type=int, default=2, help="workers (default: 2)")
    parser.add_argument("--checkout", action="append", default=None, help="source tree to measure (default: this one)")
    parser.add_argument("--executor", action="append", default=[], choices=["dask", "ray"], help="also measure this")
    parser.add_argument(
        "--job",
        action="append",
        default=None,
        choices=["main", "sweep", "read"],
        help="main job, sweep, or the cost of reading one scenario file (default: main and sweep)",
    )
    parser.add_argument("--repeat", type=int, default=1, help="turns over the checkouts (default: 1)")
    args = parser.parse_args()
    checkouts = [Path(c).resolve() for c in (args.checkout or [HERE])]
    jobs = args.job or ["main", "sweep"]
    print(f"machine: {platform.node()}, {os.cpu_count()} cores, load before {os.getloadavg()[0]:.2f}")
    print(f"command: python {' '.join(sys.argv)}\n")
    if "read" in jobs:
        print(_read_cost(args.duration) + "\n")
        jobs = [job for job in jobs if job != "read"]
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for _ in range(args.repeat):
            for kind in jobs:
                for checkout in checkouts:
                    for executor in ["local", *args.executor]:
                        if executor != "local" and not _has_executors(checkout):
                            continue
                        rows.append(_measure(checkout, kind, args, executor, Path(scratch)))
                        print(_line(rows[-1]), flush=True)
    if not rows:
        return
    print(f"\nload after: {os.getloadavg()[0]:.2f}\n")
    print("| job | checkout | executor | runs | wall [s] | CPU [s] | runs/s (wall) | runs/s (harness) | load |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        harness = "n/a" if row["harness_runs_per_s"] is None else f"{row['harness_runs_per_s']:.3f}"
        print(
            f"| {row['job']} | {row['checkout']} | {row['executor']} | {row['runs']} | {row['wall_s']:.1f} "
            f"| {row['cpu_s']:.1f} | {row['runs_per_s']:.3f} | {harness} | {row['load']:.1f} |"
        )


def _line(row: dict) -> str:
    return (
        f"{row['job']:>5} {row['checkout']:>12} {row['executor']:>6}: {row['runs']} runs in {row['wall_s']:.1f} s"
        f" ({row['runs_per_s']:.3f} runs/s), {row['cpu_s']:.1f} CPU s, load {row['load']:.1f}"
    )


if __name__ == "__main__":
    main()
