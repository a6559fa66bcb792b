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
``--scenario-dir``), ``metrics.csv``, ``vehicles.csv``, ``summary.json``, ``report.md``, the
figures (see :mod:`envs.report`) and ``run.json`` (runs, wall time, runs per second, executor).
An existing ``--out`` is refused, never overwritten; without ``--out`` a fresh
``reports/synthetic-<date>-<time>`` folder is made. The report is written into a hidden temporary
folder that becomes ``--out`` only when the run succeeds, so a failed or interrupted run leaves
nothing that blocks the rerun.

The runs spread over ``--jobs`` processes on this machine, each scenario file read once and sent to
each worker once; ``--executor dask`` (or ``ray``) runs the same evaluation on a cluster instead, a
local one of ``--jobs`` workers or the existing one at ``--scheduler-address`` (docs/cluster.md);
the numbers are the same. The progress bar and ``run.json`` give the runs per second.

Model planners (``.safetensors`` policy files or SB3 ``.zip`` files) are loaded and checked
against the environment before any run starts, without running code from the file
(``--trust-planner-files`` loads a ``.zip`` with SB3's full ``TD3.load``, for one's own files).

A planner's answer is checked every step (:mod:`envs.planners.errors`): an invalid one (NaN, inf, out of
bounds, wrong shape or dtype) or a planner that raises voids that planner's run without the shield,
the other runs are still reported and the command exits with status 1; behind the shield the fallback
takes over and the step counts in ``planner_errors``.

A collision does not end a run: the vehicles involved are counted as collided and leave the
scene, and the run goes on for its whole duration (``--env-kwargs '{"config":
{"collision_handling": "terminate"}}'`` ends it instead, as in training).
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sb3_graph.cli import UserError
from sb3_graph.commands.arguments import finite_float, json_object

DEFAULT_ENV = "CoopIntersection4Way-v0"
# The GNN planner shipped with the package (trained by `sb3-graph train`, see its README.md), in
# the weights-only format (`sb3-graph export` of best_model.zip beside it).
DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "pretrained" / "coop_4way_fair" / "best_model.safetensors"
DEFAULT_BASELINES = ("pr", "fifo", "aim", "signal")
RUN_INFO_FILE = "run.json"
TRUST_HELP = (
    "load model .zip files with SB3's full TD3.load, which runs the pickled code inside them: only for "
    "files you made yourself (by default a .zip is read without unpickling)"
)


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
        help="repeatable: 'pr' (priority rules), 'fifo', 'aim', 'signal', a policy file .safetensors "
        "(sb3-graph export) or a saved model .zip, or a Planner class (path/to/file.py:ClassName or "
        "package.module:ClassName); '+shield' after any of them wraps it in the safety shield; default: pr, fifo, "
        "aim, signal and the GNN planner shipped in envs/pretrained/coop_4way_fair/best_model.safetensors, without "
        "and with the shield",
    )
    add_shield_argument(parser)
    parser.add_argument("--trust-planner-files", action="store_true", help=TRUST_HELP)
    parser.add_argument(
        "--scenarios", type=int, default=scenarios, help=f"scenarios to generate{per} (default: {scenarios})"
    )
    parser.add_argument(
        "--duration",
        type=finite_float,
        default=100.0,
        help="simulated seconds per run (default: 100; a scenario file that ends earlier ends its run)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="base seed of scenarios and environments, >= 0 (default: 0)"
    )
    add_executor_arguments(parser)
    parser.add_argument(
        "--out",
        default=None,
        help=f"report folder, must not exist (default: a fresh {out})",
    )
    parser.add_argument(
        "--env-kwargs",
        type=json_object,
        default=None,
        help="JSON dict passed to gym.make; its 'config' defaults to collision_handling 'remove' (a crash "
        "removes the vehicles involved and the run goes on)",
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def add_executor_arguments(parser: argparse.ArgumentParser) -> None:
    """``--jobs``, ``--executor`` and ``--scheduler-address`` (shared by the commands that run planners)."""
    from envs.executors import EXECUTORS

    parser.add_argument(
        "--jobs",
        type=int,
        default=2,
        help="parallel workers: processes on this machine, or the workers of the local cluster that --executor "
        "dask/ray starts (default: 2)",
    )
    parser.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="local",
        help="where the runs execute: local processes, a Dask cluster or a Ray cluster (pip install "
        "'sb3-graph[cluster]' or 'sb3-graph[ray]'); the numbers are the same (default: local)",
    )
    parser.add_argument(
        "--scheduler-address",
        default=None,
        metavar="ADDRESS",
        help="an existing cluster for --executor dask (e.g. tcp://SCHEDULER:8786) or ray (ray://host:10001, "
        "auto); its workers replace --jobs (default: start a local cluster of --jobs workers)",
    )


def check_executor_arguments(args: argparse.Namespace) -> None:
    """Refuse a bad ``--jobs``, or an executor that cannot run, before any work starts.

    :raises UserError: naming the flag
    """
    from envs.executors import ExecutorError, check_executor

    if args.jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {args.jobs}")
    try:
        check_executor(args.executor, args.scheduler_address)
    except (ExecutorError, ValueError) as error:
        raise UserError(str(error)) from None


def _check(args: argparse.Namespace) -> list[tuple[str, str]]:
    """Validate the arguments; return the ``(planner word, report name)`` pairs."""
    from sb3_graph.outputs import OutputError, check_destination

    if args.scenarios < 1:
        raise UserError(f"--scenarios must be at least 1, got {args.scenarios}")
    if not args.duration > 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    check_executor_arguments(args)
    if args.env_kwargs is not None and not isinstance(args.env_kwargs, dict):
        raise UserError("--env-kwargs must be a JSON object, e.g. '{\"duration\": 100}'")
    planners = checked_planners(args.planner, shield=args.shield)
    if args.out is not None:
        try:
            check_destination(Path(args.out))
        except OutputError as error:
            raise UserError(str(error)) from None
    check_env_id(args.env)
    if getattr(args, "scenario_dir", None) is not None and not Path(args.scenario_dir).is_dir():
        raise UserError(f"--scenario-dir: {args.scenario_dir!r} is not a folder")
    return planners


def check_env_id(env_id: str) -> None:
    """Refuse an environment id that is not one of this package's intersection environments.

    :raises UserError: naming ``--env`` and the accepted ids
    """
    import gymnasium as gym

    import envs  # noqa: F401  (registers the environments)

    known = sorted(k for k, spec in gym.registry.items() if str(spec.entry_point).startswith("envs."))
    if env_id not in known:
        what = "is not an intersection environment of this package" if env_id in gym.registry else "is unknown"
        raise UserError(f"--env: {env_id!r} {what}; expected one of {known}")


def checked_env(env_id: str, env_kwargs: dict[str, Any] | None) -> dict[str, Any]:
    """The environment's resolved configuration (its ``--env-kwargs`` checked by building it).

    :raises UserError: naming ``--env-kwargs``
    """
    from envs.evaluation import env_config

    try:
        return env_config(env_id, env_kwargs)
    except (TypeError, ValueError) as error:
        raise UserError(f"--env-kwargs: {error}") from None


def load_model_planners(
    planners: Sequence[tuple[str, str]], config: dict[str, Any], trust_files: bool = False
) -> None:
    """Load every model planner once, before any run: a file that cannot be loaded safely, or whose
    graphs are smaller than the environment's scenes, is a one-line error instead of a failed run.

    :param planners: ``(word, name)`` pairs
    :param config: the environment's configuration (:func:`checked_env`)
    :param trust_files: ``--trust-planner-files``
    :raises UserError: naming ``--planner``, the file and the problem
    """
    from envs.planners import BASELINES, make_planner

    for word, _ in planners:
        if word in BASELINES:
            continue
        try:
            planner = make_planner(word, trust_files=trust_files)
            check = getattr(planner, "check_capacity", None)
            if check is not None:
                check(int(config["max_vehicles"]), word)
        except ValueError as error:
            raise UserError(f"--planner: {error}") from None


def _destination(args: argparse.Namespace, prefix: str = "synthetic") -> Path:
    """The report folder (not created yet): ``--out`` or a fresh ``reports/<prefix>-<date>-<time>``."""
    if args.out is not None:
        return Path(args.out)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = Path("reports") / f"{prefix}-{stamp}"
    k = 1
    while out.exists():
        out = Path("reports") / f"{prefix}-{stamp}-{k}"
        k += 1
    return out


def duration_text(runs, requested: float) -> str:
    """What the runs really simulated: ``--duration``, or less where scenario files end earlier."""
    if "duration_s" not in getattr(runs, "columns", ()) or runs.empty:
        return f"{requested:g} s"
    low, high = float(runs["duration_s"].min()), float(runs["duration_s"].max())
    if abs(low - requested) < 1e-6 and abs(high - requested) < 1e-6:
        return f"{requested:g} s"
    span = f"{low:g} s" if abs(high - low) < 1e-6 else f"{low:g} to {high:g} s"
    return f"{span} (--duration {requested:g} s; a run ends with its scenario file)"


def run(args: argparse.Namespace) -> int:
    from envs.evaluation import check_scenarios, find_scenarios, generate_scenarios
    from envs.report import write_report
    from sb3_graph.outputs import OutputError, staged_folder

    planners = _check(args)
    config = checked_env(args.env, args.env_kwargs)
    layout = str(config["layout"])
    if args.scenario_dir is not None:
        try:
            scenarios = find_scenarios(args.scenario_dir)
            check_scenarios(scenarios, layout)
        except ValueError as error:
            raise UserError(f"--scenario-dir: {error}") from None
    load_model_planners(planners, config, args.trust_planner_files)
    out = _destination(args)
    tic = time.perf_counter()
    try:
        with staged_folder(out) as stage:
            if args.scenario_dir is None:
                scenarios = generate_scenarios(stage / "scenarios", args.scenarios, args.duration, args.seed, layout)
                source = f"generated into {out / 'scenarios'} (seed {args.seed} + index)"
            else:
                source = f"read from {args.scenario_dir}"
            runs, vehicles, stats = run_harness(args, planners, scenarios)
            wall = time.perf_counter() - tic
            meta = {
                "environment": args.env,
                "planners": ", ".join(f"{name} ({word})" for word, name in planners),
                "scenarios": f"{len(scenarios)}, {source}",
                "duration per run": duration_text(runs, args.duration),
                "seed": args.seed,
                "jobs": args.jobs,
                **harness_meta(stats),
                "wall time": f"{wall:.1f} s",
                "python": platform.python_version(),
            }
            summary = write_report(stage, runs, vehicles, meta)
            write_run_info(stage, stats, time.perf_counter() - tic)
    except OutputError as error:
        raise UserError(str(error)) from None
    print_summary(summary)
    print(run_line(stats))
    print(f"report written to {out} ({wall:.1f} s)")
    failed = sum(s.get("failed_runs", 0) for s in summary.values())
    if failed:
        print(f"{failed} runs failed on a planner error (see above and metrics.csv): exit status 1")
        return 1
    return 0


def print_summary(summary: dict[str, dict[str, Any]]) -> None:
    """One line per planner on the console, the shield's counters and the planner errors after it."""
    from envs.report import format_number

    for name, s in summary.items():
        if "flow_rate" in s:
            f, sr = s["flow_rate"], s["stop_ratio"]
            print(
                f"{name:>10}: flow median {format_number(f['median'])} veh/s,"
                f" stops major {format_number(sr['major'])} minor {format_number(sr['minor'])},"
                f" collisions {format_number(s['collision_rate'])},"
                f" delay mean {format_number(s['delay_s']['mean'], 2)} s,"
                f" {s['speed_limit_violations']} speed-limit violations ({s['vehicles']} scheduled vehicles,"
                f" {s['not_spawned']} never appeared), {s.get('stuck_runs', 0)} stuck runs"
            )
        if "shield_interventions" in s:
            print(
                f"{'':>10}  shield: interventions {format_number(s['shield_interventions'])},"
                f" unresolved steps {s.get('shield_unresolved', 0)}, planner errors {s.get('planner_errors', 0)}"
            )
        if s.get("failed_runs"):
            print(f"{name:>10}: {s['failed_runs']} runs failed (left out of the report's tables)")
        for line in s.get("planner_error_lines", [])[:3]:
            print(f"{'':>10}  {line}")


def run_harness(args: argparse.Namespace, planners: Sequence[tuple[str, str]], scenarios: Sequence[Path]):
    """Every planner on every scenario with the command's settings (:func:`envs.evaluation.evaluate`).

    :param args: the parsed ``evaluate``/``sweep`` arguments
    :param planners: ``(planner spec, report name)`` pairs
    :param scenarios: scenario files
    :return: ``(runs, vehicles, stats)``, stats as :func:`envs.evaluation.evaluate` fills them
    """
    return harness(args, planners, scenarios, args.duration)


def harness(args: argparse.Namespace, planners: Sequence[tuple[str, str]], scenarios: Sequence[Path], duration):
    """:func:`envs.evaluation.evaluate` with a command's ``--jobs``, ``--executor``, ``--scheduler-address``,
    ``--seed``, ``--env``, ``--env-kwargs`` and ``--no-progress``.

    :return: ``(runs, vehicles, stats)``
    :raises UserError: the executor cannot start (naming its flag)
    """
    from envs.evaluation import evaluate
    from envs.executors import ExecutorError

    stats: dict[str, Any] = {}
    try:
        runs, vehicles = evaluate(
            planners,
            scenarios,
            args.env,
            duration,
            seed=args.seed,
            jobs=args.jobs,
            env_kwargs=args.env_kwargs,
            progress=not args.no_progress,
            trust_planner_files=args.trust_planner_files,
            executor=args.executor,
            scheduler_address=args.scheduler_address,
            stats=stats,
        )
    except ExecutorError as error:
        raise UserError(str(error)) from None
    return runs, vehicles, stats


def harness_meta(stats: dict[str, Any]) -> dict[str, str]:
    """The report's lines on the harness: where the runs executed and how fast.

    :param stats: :func:`envs.evaluation.evaluate`'s stats
    """
    rate = stats.get("runs_per_s")
    rate_text = "n/a" if rate is None else f"{rate:.3g} runs/s"
    return {
        "executor": stats["executor"],
        "harness": f"{stats['runs']} runs in {stats['wall_s']:.1f} s ({rate_text})",
    }


def run_line(stats: dict[str, Any]) -> str:
    """One line for the terminal: runs, wall time, runs per second and executor."""
    meta = harness_meta(stats)
    return f"{meta['harness']} on {meta['executor']}"


def write_run_info(out: Path, stats: dict[str, Any], wall: float) -> None:
    """``run.json``: the harness's runs, wall time, runs per second and executor (kept out of
    ``summary.json``, whose keys are the planners and whose numbers do not depend on where they ran).

    :param out: the report folder
    :param stats: :func:`envs.evaluation.evaluate`'s stats
    :param wall: the command's wall time so far [s] (scenario generation, runs and report)
    """
    import json

    info = {**stats, "command_wall_s": wall}
    (Path(out) / RUN_INFO_FILE).write_text(json.dumps(info, indent=2) + "\n")


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
