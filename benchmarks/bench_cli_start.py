"""Start time of the ``sb3-graph`` command line: ``--help`` against a bare interpreter and the eager start.

Each side is a fresh ``python`` process (the import cache is what a user's shell gets), run ``--repeats``
times in turn, the median counts:

- ``python -c pass``: the floor (the interpreter alone);
- ``sb3-graph --help``: ``python -m sb3_graph.cli --help`` of the checkout (lists the commands from their
  one-line helps, importing no command module);
- ``sb3-graph <command> --help``: one command's parser (imports that command's module only), for every
  command by default;
- ``sb3-graph <command> --no-such-flag``: an argparse error of that command (builds the same parser);
- ``eager start``: what every command paid before the lazy start: the package's network modules
  (torch, torch-geometric, Stable-Baselines3) and every command's parser.

Printed: median wall seconds per side and the ratio to ``python -c pass`` and to the eager start, measured in
the same run (absolute figures swing with the machine's load; the ratios are what to compare), and whether each
command's ``--help`` and argparse error stay under the goal of :data:`GOAL_S` (exit status 1 when one does not).

Run: ``python benchmarks/bench_cli_start.py [--repeats 3] [--commands evaluate train]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
#: Wall seconds (median) within which every ``--help`` and every argparse error answers.
GOAL_S = 1.0
EAGER = (
    "import sb3_graph.td3, sb3_graph.sac, sb3_graph.ppo, sb3_graph.tqc, sb3_graph.crossq; "
    "from sb3_graph.cli import build_parser; build_parser().parse_args(['--help'])"
)


def _time(command: list[str], env: dict[str, str]) -> float:
    """Wall seconds of one fresh process running ``command`` (its output discarded; a failure raises)."""
    tic = time.perf_counter()
    subprocess.run(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    return time.perf_counter() - tic


def main(argv: list[str] | None = None) -> int:
    from sb3_graph.cli import all_commands

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs per side, in turn; the median counts (default: 3)")
    parser.add_argument(
        "--commands", nargs="*", default=None, help="commands whose own --help and error are timed (default: all)"
    )
    args = parser.parse_args(argv)
    commands = list(all_commands()) if args.commands is None else args.commands
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", "OMP_NUM_THREADS": "1"}
    cli = [sys.executable, "-m", "sb3_graph.cli"]
    sides = {
        "python -c pass": [sys.executable, "-c", "pass"],
        "sb3-graph --help": [*cli, "--help"],
        **{f"sb3-graph {c} --help": [*cli, c, "--help"] for c in commands},
        **{f"sb3-graph {c} --no-such-flag": [*cli, c, "--no-such-flag"] for c in commands},
        "eager start (before)": [sys.executable, "-c", EAGER],
    }
    times: dict[str, list[float]] = {name: [] for name in sides}
    for _ in range(args.repeats):  # in turn, so that a change of load hits every side alike
        for name, command in sides.items():
            times[name].append(_time(command, env))
    floor = statistics.median(times["python -c pass"])
    eager = statistics.median(times["eager start (before)"])
    header = f"{'side':<38} {'median [s]':>10} {'x python -c pass':>17} {'/ eager start':>14}  goal"
    print(f"{header}  (medians of {args.repeats}; goal: a command answers in under {GOAL_S:g} s)")
    slow = []
    for name, values in times.items():
        median = statistics.median(values)
        goal = ""
        if name.startswith("sb3-graph"):
            goal = "ok" if median < GOAL_S else "SLOW"
            slow += [name] if median >= GOAL_S else []
        print(f"{name:<38} {median:>10.3f} {median / floor:>17.1f} {median / eager:>14.3f}  {goal}")
    print(
        f"{len(slow)} of {sum(n.startswith('sb3-graph') for n in sides)} commands at or over {GOAL_S:g} s"
        + (f": {', '.join(slow)}" if slow else "")
    )
    return 1 if slow else 0


if __name__ == "__main__":
    sys.exit(main())
