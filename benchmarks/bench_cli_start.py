"""Start time of the ``sb3-graph`` command line: ``--help`` against a bare interpreter and the eager start.

Each side is a fresh ``python`` process (the import cache is what a user's shell gets), run ``--repeats``
times in turn, the median counts:

- ``python -c pass``: the floor (the interpreter alone);
- ``sb3-graph --help``: ``python -m sb3_graph.cli --help`` of the checkout (lists the commands from their
  one-line helps, importing no command module);
- ``sb3-graph <command> --help``: one command's parser (imports that command's module only);
- ``eager start``: what every command paid before the lazy start: the package's network modules
  (torch, torch-geometric, Stable-Baselines3) and every command's parser.

Printed: median wall seconds per side and the ratio to ``python -c pass`` and to the eager start, measured in
the same run (absolute figures swing with the machine's load; the ratios are what to compare).

Run: ``python benchmarks/bench_cli_start.py [--repeats 5] [--commands evaluate train]``
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
EAGER = (
    "import sb3_graph.td3, sb3_graph.sac, sb3_graph.ppo, sb3_graph.tqc, sb3_graph.crossq; "
    "from sb3_graph.cli import build_parser; build_parser().parse_args(['--help'])"
)


def _time(command: list[str], env: dict[str, str]) -> float:
    """Wall seconds of one fresh process running ``command`` (its output discarded; a failure raises)."""
    tic = time.perf_counter()
    subprocess.run(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    return time.perf_counter() - tic


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs per side, in turn; the median counts (default: 5)")
    parser.add_argument(
        "--commands", nargs="*", default=["evaluate", "train"], help="commands whose own --help is timed too"
    )
    args = parser.parse_args(argv)
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", "OMP_NUM_THREADS": "1"}
    sides = {
        "python -c pass": [sys.executable, "-c", "pass"],
        "sb3-graph --help": [sys.executable, "-m", "sb3_graph.cli", "--help"],
        **{f"sb3-graph {c} --help": [sys.executable, "-m", "sb3_graph.cli", c, "--help"] for c in args.commands},
        "eager start (before)": [sys.executable, "-c", EAGER],
    }
    times: dict[str, list[float]] = {name: [] for name in sides}
    for _ in range(args.repeats):  # in turn, so that a change of load hits every side alike
        for name, command in sides.items():
            times[name].append(_time(command, env))
    floor = statistics.median(times["python -c pass"])
    eager = statistics.median(times["eager start (before)"])
    header = f"{'side':<28} {'median [s]':>10} {'x python -c pass':>17} {'/ eager start':>14}"
    print(f"{header}  (medians of {args.repeats})")
    for name, values in times.items():
        median = statistics.median(values)
        print(f"{name:<28} {median:>10.3f} {median / floor:>17.1f} {median / eager:>14.3f}")


if __name__ == "__main__":
    main()
