"""``sb3-graph record``: watch one episode, a planner on a scenario, as a GIF, an MP4 or an HTML animation.

Examples::

    sb3-graph record --seed 3 --duration 30 --out gnn.gif   # the shipped planner behind the shield
    sb3-graph record --planner aim --planner envs/pretrained/coop_4way_advice/best_model.safetensors+shield \\
        --seed 3 --duration 30 --out aim_vs_gnn.gif          # side by side, the same scenario
    sb3-graph record --planner gnn=envs/pretrained/coop_4way_advice/best_model.safetensors+shield \\
        --seed 3 --out gnn.html                              # labelled: the panel's title is "gnn"
    sb3-graph record --report reports/main100 --run 33 --planner aim --out aim_run33.mp4

One frame per policy step (``--duration`` x the policy frequency, or what follows ``--from``; played
in real time at ``--speed 1``):
the time, the planner, the conflict zones and the vehicles coloured by state (moving, stopped, held by
the speed governor, overridden by the shield, collided), drawn with matplotlib; no display is needed.

The scenario is one generated with ``--seed`` (the scenario and environment seed of
``sb3-graph evaluate --seed S``'s first run), a scenario file (``--scenario``), or a run of an
``evaluate`` report (``--report DIR --run N``: its scenario file, environment, seed and planners),
so that a stuck or colliding run of a report can be watched; the episode runs through the evaluation
harness's own loop and environment (:func:`envs.evaluation.harness.run_episode`), and a replayed run prints
its crossed and collided vehicles beside the report's.

``.gif`` needs Pillow (installed with matplotlib), ``.html`` nothing more (frames embedded, one
self-contained file), ``.mp4`` an ffmpeg encoder (``pip install 'sb3-graph[video]'``). An existing
``--out`` is refused; the file appears only when it is complete.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from sb3_graph.cli import UserError
from sb3_graph.commands.arguments import finite_float, json_object

DEFAULT_DURATION = 30.0
# The planner recorded when neither --planner nor --report is given: the shipped GNN planner behind the shield.
_SHIPPED = "coop_4way_advice/best_model.safetensors"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from envs.commands.evaluate import DEFAULT_ENV, LABEL_HELP, TRUST_HELP, add_shield_argument

    parser.add_argument(
        "--planner",
        action="append",
        default=None,
        metavar="[LABEL=]PLANNER",
        help="repeatable, one panel each: a planner as evaluate's --planner takes it ('aim', a .safetensors "
        f"file, 'fifo+shield' ...); {LABEL_HELP} (the panel's title); default: the report's planners with "
        f"--report, else the shipped planner behind the shield (envs/pretrained/{_SHIPPED})",
    )
    parser.add_argument("--env", default=None, help=f"environment id (default: {DEFAULT_ENV}, or the report's)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--seed", type=int, default=None, help="generate the scenario with this seed, >= 0 (default 0)")
    source.add_argument("--scenario", default=None, metavar="FILE", help="a scenario file (*.json)")
    source.add_argument("--report", default=None, metavar="DIR", help="an evaluate report folder: replay its --run")
    parser.add_argument("--run", type=int, default=None, metavar="N", help="with --report: the run (scenario index)")
    parser.add_argument(
        "--duration",
        type=finite_float,
        default=None,
        help=f"simulated seconds (default: {DEFAULT_DURATION:g}, with --report the run's duration)",
    )
    parser.add_argument(
        "--from", dest="from_time", type=finite_float, default=0.0, metavar="SECONDS",
        help="draw only what happens after this simulated time (the run still starts at 0; default: 0)",
    )  # fmt: skip
    add_shield_argument(parser, "wrap every planner in the safety shield (its panel is titled '<name>+shield')")
    parser.add_argument("--out", required=True, help="the file to write, .gif, .mp4 or .html; must not exist")
    parser.add_argument(
        "--speed", type=finite_float, default=1.0, help="playback speed, 1 = real time (default: 1)"
    )
    parser.add_argument("--dpi", type=int, default=80, help="pixels per inch of a 5-inch panel (default: 80)")
    parser.add_argument(
        "--view", type=finite_float, default=50.0, metavar="METRES",
        help="half-width of the drawn area around the intersection (default: 50; 95 shows the whole approaches)",
    )  # fmt: skip
    parser.add_argument("--still", default=None, metavar="PNG", help="also write one frame as a PNG image")
    parser.add_argument(
        "--still-at", type=finite_float, default=None, metavar="SECONDS",
        help="simulated time of the --still frame (default: the last frame)",
    )  # fmt: skip
    parser.add_argument("--trust-planner-files", action="store_true", help=TRUST_HELP)
    parser.add_argument("--env-kwargs", type=json_object, default=None, help="JSON dict passed to gym.make")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def _read_report(folder: Path, run: int) -> dict[str, Any]:
    """The replay settings of run ``run`` of an evaluate report: scenario file, env, seed, planners.

    Reports written since ``record`` exists keep them in ``run.json`` (``replay``); older ones in
    ``report.md``'s settings list.

    :raises UserError: naming ``--report`` or ``--run``
    """
    import pandas as pd

    metrics = folder / "metrics.csv"
    if not metrics.is_file():
        raise UserError(f"--report: {str(folder)!r} is not an evaluate report (no metrics.csv)")
    runs = pd.read_csv(metrics)
    if "run" not in runs:
        raise UserError(f"--report: {metrics} has no 'run' column")
    known = sorted(int(r) for r in pd.unique(runs["run"]))
    if run not in known:
        raise UserError(f"--run: {run} is not a run of {str(folder)!r}; expected one of {known[0]}..{known[-1]}")
    rows = runs[runs["run"] == run]
    replay: dict[str, Any] = {}
    info = folder / "run.json"
    if info.is_file():
        try:
            replay = dict(json.loads(info.read_text()).get("replay") or {})
        except (ValueError, AttributeError):
            replay = {}
    if not replay:
        replay = _settings_from_markdown(folder / "report.md")
    scenario = folder / "scenarios" / str(rows["scenario"].iloc[0])
    if not scenario.is_file():
        raise UserError(
            f"--report: run {run}'s scenario file {scenario.name!r} is not in {str(folder / 'scenarios')!r} "
            "(the report read its scenarios from another folder): pass it with --scenario instead"
        )
    replay["scenario"] = scenario
    replay["seed"] = int(replay.get("seed", 0)) + run
    replay["duration"] = float(rows["duration_s"].max()) if "duration_s" in rows else replay.get("duration")
    replay["results"] = {str(r["planner"]): r for _, r in rows.iterrows()}
    return replay


def _settings_from_markdown(path: Path) -> dict[str, Any]:
    """``environment``, ``seed`` and ``planners`` of an older report, from the settings list of its ``report.md``."""
    if not path.is_file():
        raise UserError(f"--report: {str(path.parent)!r} has neither run.json's replay settings nor report.md")
    settings = {}
    for line in path.read_text().splitlines():
        match = re.match(r"- (environment|seed|planners): (.+)$", line)
        if match:
            settings[match.group(1)] = match.group(2)
    replay: dict[str, Any] = {}
    if "environment" in settings:
        replay["env"] = settings["environment"]
    if "seed" in settings and settings["seed"].isdigit():
        replay["seed"] = int(settings["seed"])
    if "planners" in settings:
        replay["planners"] = [[spec, name] for name, spec in re.findall(r"([^,]+?) \(([^()]+)\)(?:, |$)",
                                                                         settings["planners"])]  # fmt: skip
    return replay


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    """Scenario, env, seed, duration and planners of the episode, from the flags (and the report)."""
    from envs.commands.evaluate import DEFAULT_ENV

    if args.run is not None and args.report is None:
        raise UserError("--run needs --report DIR (the evaluate report whose run to replay)")
    if args.report is not None:
        if args.run is None:
            raise UserError("--report needs --run N (the run to replay, as in the report's metrics.csv)")
        settings = _read_report(Path(args.report), args.run)
    else:
        settings = {"seed": 0 if args.seed is None else args.seed, "scenario": args.scenario}
        if args.scenario is not None and not Path(args.scenario).is_file():
            raise UserError(f"--scenario: file not found: {args.scenario!r}")
    if settings["seed"] < 0:
        raise UserError(f"--seed must be >= 0, got {settings['seed']}")
    settings["env"] = args.env or settings.get("env") or DEFAULT_ENV
    if args.env_kwargs is not None:
        settings["env_kwargs"] = args.env_kwargs
    if args.duration is not None:
        settings["duration"] = args.duration
    settings["duration"] = float(settings.get("duration") or DEFAULT_DURATION)
    if not settings["duration"] > 0:
        raise UserError(f"--duration must be positive, got {settings['duration']}")
    if not 0 <= args.from_time < settings["duration"]:
        raise UserError(f"--from must be in [0, {settings['duration']:g}) s (the duration), got {args.from_time:g}")
    # a report's planners keep their report names (labels), so that the replay matches the report's rows
    words = args.planner or [_labelled(spec, name) for spec, name in settings.get("planners", [])]
    if not words and args.report is None:
        from envs.commands.evaluate import DEFAULT_MODEL
        from envs.planners import SHIELD_SUFFIX

        words = [str(DEFAULT_MODEL) + SHIELD_SUFFIX] if DEFAULT_MODEL.is_file() else []
    if not words:
        raise UserError("--planner: give at least one planner (e.g. --planner aim)")
    settings["words"] = words
    return settings


def _labelled(spec: str, name: str) -> str:
    """A report's planner as a ``--planner`` word that keeps its report name (``LABEL=SPEC``)."""
    from envs.commands.evaluate import LABEL_PATTERN

    return f"{name}={spec}" if LABEL_PATTERN.fullmatch(name) else spec


def _check_outputs(args: argparse.Namespace) -> None:
    from envs.simulation.rendering import check_format

    for flag, path in (("--out", args.out), ("--still", args.still)):
        if path is not None and (Path(path).exists() or Path(path).is_symlink()):
            raise UserError(f"{flag}: {path!r} exists; choose a new file name (nothing is overwritten)")
    try:
        check_format(args.out)
    except ValueError as error:
        raise UserError(f"--out: {error}") from None
    if args.still is not None and Path(args.still).suffix.lower() != ".png":
        raise UserError(f"--still: must end in .png, got {args.still!r}")
    if not args.speed > 0:
        raise UserError(f"--speed must be positive, got {args.speed}")
    if not args.view > 0:
        raise UserError(f"--view must be positive, got {args.view}")
    if not 10 <= args.dpi <= 600:
        raise UserError(f"--dpi must be in 10..600, got {args.dpi}")


def _scenario(settings: dict[str, Any], layout: str):
    from envs.simulation.traffic import Scenario, generate_scenario

    if settings.get("scenario") is None:
        return generate_scenario(layout, settings["duration"], settings["seed"])
    try:
        scenario = Scenario.load(settings["scenario"])
    except (ValueError, KeyError, TypeError) as error:
        raise UserError(f"--scenario: {error}") from None
    if scenario.layout != layout:
        raise UserError(f"--scenario: {settings['scenario']} is for layout {scenario.layout!r}, "
                        f"{settings['env']} uses {layout!r}")  # fmt: skip
    return scenario


def run(args: argparse.Namespace) -> int:
    import gymnasium as gym
    from tqdm.auto import tqdm

    from envs.commands.evaluate import check_env_id, checked_env, checked_planners, load_model_planners
    from envs.evaluation.harness import evaluation_env_kwargs
    from envs.evaluation.recording import record_episode
    from envs.planners import make_planner, parse_shield_bounds
    from envs.simulation.rendering import write_animation
    from sb3_graph.files.output_folders import OutputError, write_file_atomically

    _check_outputs(args)
    settings = _settings(args)
    check_env_id(settings["env"])
    trust = args.trust_planner_files or bool(settings.get("trust_planner_files") and args.report)
    planners = checked_planners(settings["words"], shield=args.shield)
    try:  # a replayed report's shields keep their declared bounds
        bounds = parse_shield_bounds(settings.get("shield_bounds"))
    except ValueError as error:
        raise UserError(f"--report: run.json's replay settings: {error}") from None
    config = checked_env(settings["env"], settings.get("env_kwargs"))
    load_model_planners(planners, config, trust)
    scenario = _scenario(settings, str(config["layout"]))
    frequency = int(config["policy_frequency"])
    steps = int(round(settings["duration"] * frequency))
    hidden = args.no_progress
    env = gym.make(settings["env"], **evaluation_env_kwargs(settings.get("env_kwargs")))
    episodes = []
    with tqdm(total=steps * len(planners), desc="record: simulate", unit="step", disable=hidden) as bar:
        for spec, name in planners:
            planner = make_planner(spec, trust_files=trust, shield_bounds=bounds)
            episodes.append(
                record_episode(env, planner, name, scenario, settings["duration"], settings["seed"], bar.update)
            )
    env.close()
    for episode in episodes:
        print(_result_line(episode, settings.get("results", {}).get(episode.name), args.run))
        episode.frames = [f for f in episode.frames if f.time > args.from_time + 1e-9]
    total = max(len(e.frames) for e in episodes)
    try:
        with tqdm(total=total, desc="record: draw", unit="frame", disable=hidden) as bar:

            def progress(done: int, _total: int) -> None:
                bar.update(done - bar.n)

            def write(path: Path) -> None:
                write_animation(episodes, path, frequency * args.speed, args.dpi, progress=progress,
                                view=args.view, file_format=Path(args.out).suffix.lower())  # fmt: skip

            write_file_atomically(args.out, write, flag="--out")
        if args.still is not None:
            times = np.array([f.time for f in max(episodes, key=lambda e: len(e.frames)).frames])
            at = total - 1 if args.still_at is None else int(np.argmin(np.abs(times - args.still_at)))
            write_file_atomically(args.still, lambda path: _write_png(episodes, path, at, args.view), flag="--still")
    except OutputError as error:
        raise UserError(str(error)) from None
    seconds = total / (frequency * args.speed)
    shown = settings["duration"] - args.from_time
    print(f"wrote {args.out}: {total} frames ({shown:g} s at {frequency} Hz, plays {seconds:g} s)")
    return 0


def _write_png(episodes, path: Path, index: int, view: float) -> None:
    import shutil
    import tempfile

    from envs.simulation.rendering import write_frame

    with tempfile.TemporaryDirectory(prefix=".record-", dir=Path(path).parent) as folder:
        target = Path(folder) / "frame.png"
        write_frame(episodes, target, index, view=view)
        shutil.move(target, path)


def _result_line(episode, reported, run: int | None) -> str:
    """The episode's crossed and collided vehicles, beside the report's row of the same run if there is one."""
    facts = episode.facts
    line = f"{episode.name:>10}: {facts['crossed']} crossed, {facts['collided']} collided in {facts['duration']:g} s"
    if reported is not None:
        same = int(reported["crossed"]) == facts["crossed"] and int(reported["collided"]) == facts["collided"]
        line += (
            f" (report, run {run}: {int(reported['crossed'])} crossed, {int(reported['collided'])} collided"
            f"{'' if same else '; differs: another version or setting than the report'})"
        )
    return line
