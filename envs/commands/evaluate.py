"""``sb3-graph evaluate``: compare planners on the same scenarios and write a report.

Example (the paper's synthetic experiment)::

    sb3-graph evaluate --env CoopIntersection4Way-v0 --planner pr --planner fifo \\
        --planner runs/coop/best_model.zip --scenarios 100 --duration 100 --seed 0 --jobs 2 \\
        --out reports/synthetic

Any class implementing :class:`envs.planners.Planner` runs as ``--planner path/to/file.py:ClassName``
or ``--planner package.module:ClassName``; ``--shield`` wraps every planner of the run in the
safety shield (:mod:`envs.planners.shield`, reported as ``<name>+shield``, its share of overridden
vehicle-steps as ``shield_interventions`` in ``summary.json``), e.g. the shield's stress test::

    sb3-graph evaluate --planner envs/planners/adversarial.py:FullThrottle \
        --planner envs.planners.adversarial:RandomAccel --shield --scenarios 20 --duration 100

The report folder receives ``scenarios/`` (the generated scenario files, reusable with
``--scenario-dir``), ``metrics.csv``, ``vehicles.csv``, ``summary.json``, ``report.md`` and the
figures (see :mod:`envs.report`). An existing ``--out`` is refused, never overwritten; without
``--out`` a fresh ``reports/synthetic-<date>-<time>`` folder is made.

A collision does not end a run: the vehicles involved are counted as collided and leave the
scene, and the run goes on for its whole duration (``--env-kwargs '{"config":
{"collision_handling": "terminate"}}'`` ends it instead, as in training).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Sequence
from pathlib import Path

from sb3_graph.cli import UserError

DEFAULT_ENV = "CoopIntersection4Way-v0"
# The GNN planner shipped with the package (trained by `sb3-graph train`, see its README.md).
DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "pretrained" / "coop_4way" / "best_model.zip"
DEFAULT_BASELINES = ("pr", "fifo", "aim", "signal")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser, scenarios=100, out="reports/synthetic-<date>-<time>")
    parser.add_argument(
        "--scenario-dir",
        default=None,
        help="read the scenario files (*.json) from this folder instead of generating --scenarios of them",
    )


def add_run_arguments(parser: argparse.ArgumentParser, scenarios: int, out: str, per: str = "") -> None:
    """The arguments ``evaluate`` shares with ``sweep``.

    :param parser: the command's parser
    :param scenarios: default of ``--scenarios``
    :param out: the default report folder, as shown in the help
    :param per: what ``--scenarios`` counts per, in its help (e.g. ``" per demand level"``)
    """
    parser.add_argument("--env", default=DEFAULT_ENV, help=f"environment id (default: {DEFAULT_ENV})")
    parser.add_argument(
        "--planner",
        action="append",
        default=None,
        metavar="PLANNER",
        help="repeatable: 'pr' (priority rules), 'fifo', 'aim', 'signal', a saved model .zip, or a Planner class "
        "(path/to/file.py:ClassName or package.module:ClassName); '+shield' after any of them wraps it in the "
        "safety shield; default: pr, fifo, aim, signal and the GNN planner shipped in "
        "envs/pretrained/coop_4way/best_model.zip, without and with the shield",
    )
    add_shield_argument(parser)
    parser.add_argument(
        "--scenarios", type=int, default=scenarios, help=f"scenarios to generate{per} (default: {scenarios})"
    )
    parser.add_argument(
        "--duration", type=float, default=100.0, help="simulated seconds per run (default: 100)"
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="base seed of scenarios and environments (default: 0)"
    )
    parser.add_argument("--jobs", type=int, default=2, help="parallel worker processes (default: 2)")
    parser.add_argument(
        "--out",
        default=None,
        help=f"report folder, must not exist (default: a fresh {out})",
    )
    parser.add_argument(
        "--env-kwargs",
        type=json.loads,
        default=None,
        help="JSON dict passed to gym.make; its 'config' defaults to collision_handling 'remove' (a crash "
        "removes the vehicles involved and the run goes on)",
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _check(args: argparse.Namespace) -> list[tuple[str, str]]:
    """Validate the arguments; return the ``(planner word, report name)`` pairs."""

    if args.scenarios < 1:
        raise UserError(f"--scenarios must be at least 1, got {args.scenarios}")
    if not args.duration > 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    if args.jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {args.jobs}")
    if args.env_kwargs is not None and not isinstance(args.env_kwargs, dict):
        raise UserError("--env-kwargs must be a JSON object, e.g. '{\"duration\": 100}'")
    planners = checked_planners(args.planner, shield=args.shield)
    if args.out is not None and Path(args.out).exists():
        raise UserError(f"--out: {args.out!r} exists; choose a new folder (reports are never overwritten)")
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)

    if args.env not in gym.registry:
        known = sorted(k for k in gym.registry if k.startswith("Coop"))
        raise UserError(f"--env: unknown environment {args.env!r}; expected one of {known}")
    if getattr(args, "scenario_dir", None) is not None and not Path(args.scenario_dir).is_dir():
        raise UserError(f"--scenario-dir: {args.scenario_dir!r} is not a folder")
    return planners


def _out_folder(args: argparse.Namespace, prefix: str = "synthetic") -> Path:
    """Create the report folder (default ``reports/<prefix>-<date>-<time>``); an existing one is refused."""
    if args.out is None:
        stamp = time.strftime("%Y%m%d-%H%M%S")
        out = Path("reports") / f"{prefix}-{stamp}"
        k = 1
        while out.exists():
            out = Path("reports") / f"{prefix}-{stamp}-{k}"
            k += 1
    else:
        out = Path(args.out)
        if out.exists():
            raise UserError(
                f"--out: {str(out)!r} exists; choose a new folder (reports are never overwritten)"
            )
    out.mkdir(parents=True)
    return out


def run(args: argparse.Namespace) -> int:
    from envs.evaluation import check_scenarios, find_scenarios, generate_scenarios, layout_of
    from envs.report import format_number, write_report

    planners = _check(args)
    try:
        layout = layout_of(args.env, args.env_kwargs)
    except (TypeError, ValueError) as error:
        raise UserError(f"--env-kwargs: {error}") from None
    if args.scenario_dir is not None:
        try:
            scenarios = find_scenarios(args.scenario_dir)
            check_scenarios(scenarios, layout)
        except ValueError as error:
            raise UserError(f"--scenario-dir: {error}") from None
    out = _out_folder(args)
    tic = time.perf_counter()
    if args.scenario_dir is None:
        scenarios = generate_scenarios(out / "scenarios", args.scenarios, args.duration, args.seed, layout)
        source = f"generated into {out / 'scenarios'} (seed {args.seed} + index)"
    else:
        source = f"read from {args.scenario_dir}"
    runs, vehicles = run_harness(args, planners, scenarios)
    wall = time.perf_counter() - tic
    meta = {
        "environment": args.env,
        "planners": ", ".join(f"{name} ({word})" for word, name in planners),
        "scenarios": f"{len(scenarios)}, {source}",
        "duration per run": f"{args.duration:g} s",
        "seed": args.seed,
        "jobs": args.jobs,
        "wall time": f"{wall:.1f} s",
        "python": platform.python_version(),
    }
    summary = write_report(out, runs, vehicles, meta)
    for name, s in summary.items():
        f, sr = s["flow_rate"], s["stop_ratio"]
        print(
            f"{name:>10}: flow median {format_number(f['median'])} veh/s,"
            f" stops major {format_number(sr['major'])} minor {format_number(sr['minor'])},"
            f" collisions {format_number(s['collision_rate'])}, delay mean {format_number(s['delay_s']['mean'], 2)} s,"
            f" {s['speed_limit_violations']} speed-limit violations ({s['vehicles']} scheduled vehicles,"
            f" {s['not_spawned']} never appeared)"
        )
    print(f"report written to {out} ({wall:.1f} s)")
    return 0


def run_harness(args: argparse.Namespace, planners: Sequence[tuple[str, str]], scenarios: Sequence[Path]):
    """Every planner on every scenario with the command's settings (:func:`envs.evaluation.evaluate`).

    :param args: the parsed ``evaluate``/``sweep`` arguments
    :param planners: ``(planner spec, report name)`` pairs
    :param scenarios: scenario files
    :return: ``(runs, vehicles)``
    """
    from envs.evaluation import evaluate

    return evaluate(
        planners,
        scenarios,
        args.env,
        args.duration,
        seed=args.seed,
        jobs=args.jobs,
        env_kwargs=args.env_kwargs,
        progress=not args.no_progress,
    )


def add_shield_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--shield`` flag (shared by the commands that run planners)."""
    parser.add_argument(
        "--shield",
        action="store_true",
        help="wrap every planner of the run in the safety shield (reported as '<name>+shield', with its "
        "intervention rate in summary.json)",
    )


def checked_planners(
    words: Sequence[str] | None, reserved: Sequence[str] = (), shield: bool = False
) -> list[tuple[str, str]]:
    """The ``--planner`` words as ``(planner spec, report name)`` pairs, validated.

    :param words: the words given; ``None`` or empty: PR, FIFO and the shipped GNN planner without and
        with the shield
    :param reserved: report names that a planner must not take (e.g. ``"inD"`` for the recorded drivers)
    :param shield: wrap every planner in the safety shield (``--shield``)
    :raises UserError: an unknown planner, a missing model file, or two planners with one report name
    """
    from envs.planners import SHIELD_SUFFIX, check_planner_spec, planner_name

    if not words:
        model = [str(DEFAULT_MODEL), str(DEFAULT_MODEL) + SHIELD_SUFFIX] if DEFAULT_MODEL.is_file() else []
        words = list(DEFAULT_BASELINES) + model
    planners: list[tuple[str, str]] = []
    for word in words:
        try:
            key = check_planner_spec(word)
            if shield and not key.endswith(SHIELD_SUFFIX):
                key += SHIELD_SUFFIX
            name = planner_name(key)
        except ValueError as error:
            raise UserError(f"--planner: {error}") from None
        if name in [n for _, n in planners] or name in reserved:
            raise UserError(f"--planner: {word!r} given twice or named like a reserved column (report name {name!r})")
        planners.append((key, name))
    return planners
