"""``sb3-graph ind``: replay inD recordings through the planners, next to the recorded drivers.

Example (Bendplatz, the paper's comparison)::

    sb3-graph ind --data /path/to/inD/data --recordings 07-17 --planner fifo \\
        --planner path/to/model.zip --out reports/ind

Steps: load the recordings (vehicles only; pedestrians and bicycles are counted as not
modelled), map every vehicle track to an entry and exit arm, a maneuver and a route of the
``CoopIntersectionInD-v0`` layout (:mod:`envs.ind.mapping`), measure the recorded drivers' stops
(:mod:`envs.ind.dataset_metrics`), write one scenario file per recording (each vehicle timed to
reach the stop line when the recorded one entered the intersection, ``--arrival-timing``) and
run every planner on it with the evaluation harness (:mod:`envs.evaluation.harness`; a collision removes
the vehicles involved and the run goes on). The report folder holds the files of
``sb3-graph evaluate`` (``metrics.csv``, ``vehicles.csv``, ``summary.json``, ``report.md``, the
figures) with the dataset ``inD`` as the first column, plus ``tracks.csv`` (every track, mapped
or not, with the reason), ``arms.csv``, ``classes.csv``, ``dataset_stops.csv`` and
``scenarios/``. ``--dataset-only`` stops after the dataset's own figures.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from envs.commands.evaluate import (
    DEFAULT_PLANNERS_HELP,
    LABEL_HELP,
    PLANNER_WORDS_HELP,
    add_executor_arguments,
    add_shield_argument,
    check_executor_arguments,
)
from sb3_graph.commands import UserError
from sb3_graph.commands.arguments import json_object, seed_value

if TYPE_CHECKING:  # pandas loads when the command runs, not for --help
    import pandas as pd

DEFAULT_ENV = "CoopIntersectionInD-v0"
DEFAULT_LAYOUT = "inD"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data", required=True, help="folder with the inD CSV files (the dataset's data/ folder)"
    )
    parser.add_argument(
        "--recordings",
        default="07-17",
        help="recordings, e.g. 07-17 (Bendplatz), 18-29 (Frankenburg) or 7,9,12-14 (default: 07-17)",
    )
    parser.add_argument(
        "--location",
        type=int,
        default=None,
        help="expected locationId (1 Bendplatz, 2 Frankenburg); default: the four-way site whose "
        "published recordings contain --recordings, else the first recording's site",
    )
    parser.add_argument(
        "--planner",
        action="append",
        default=None,
        metavar="[LABEL=]PLANNER",
        help=f"repeatable: {PLANNER_WORDS_HELP}; {LABEL_HELP} (default: {DEFAULT_PLANNERS_HELP})",
    )
    parser.add_argument(
        "--trust-planner-files",
        action="store_true",
        help="load model .zip files with SB3's full load of their algorithm, which runs the pickled code inside them "
        "(your own files only)",
    )
    add_shield_argument(parser)
    parser.add_argument(
        "--dataset-only", action="store_true", help="only map and measure the recorded drivers"
    )
    parser.add_argument("--env", default=DEFAULT_ENV, help=f"environment id (default: {DEFAULT_ENV})")
    parser.add_argument("--env-kwargs", type=json_object, default=None, help="JSON dict passed to gym.make")
    parser.add_argument("--seed", type=seed_value, default=0, help="base seed of the environments, >= 0 (default: 0)")
    add_executor_arguments(parser)
    parser.add_argument(
        "--out", default=None, help="report folder, must not exist (default: reports/ind-<time>)"
    )
    mapping = parser.add_argument_group("mapping of tracks to the simulated intersection")
    mapping.add_argument(
        "--centre",
        type=float,
        nargs=2,
        metavar=("X", "Y"),
        default=None,
        help="intersection centre in the recordings' local frame [m] (default: estimated from the tracks)",
    )
    mapping.add_argument(
        "--major-road",
        nargs=2,
        metavar=("ARM", "ARM"),
        default=None,
        help="the recorded major road as two compass arms, e.g. east west (default: the opposite "
        "pair of arms with the most traffic)",
    )
    mapping.add_argument(
        "--inner-radius",
        type=float,
        default=10.0,
        help="a track end closer than this to the centre is inside the intersection [m] (default: 10)",
    )
    mapping.add_argument(
        "--min-travel",
        type=float,
        default=5.0,
        help="a vehicle travelling less than this is parked [m] (default: 5)",
    )
    mapping.add_argument(
        "--arm-tolerance",
        type=float,
        default=30.0,
        help="largest angle between a track end and its arm [deg] (default: 30)",
    )
    mapping.add_argument(
        "--arrival-timing",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="time each simulated appearance so that the vehicle, at its recorded initial speed (clipped to "
        "the lane's limit), reaches the stop line when the recorded one entered the intersection: the "
        "recorded tracks begin at the edge of the camera's view, a different distance out on every arm, "
        "the simulated ones at the start of the approach lane (default: on; --no-arrival-timing: "
        "appear at the recorded appearance time)",
    )
    mapping.add_argument(
        "--entry-radius",
        type=float,
        default=None,
        help="a recorded vehicle enters the intersection when its centre first comes this close to the "
        "centre [m] (default: the simulated layout's stop-line distance for its route, about 14 m)",
    )
    mapping.add_argument(
        "--min-timing-speed",
        type=float,
        default=3.0,
        help="slower recorded initial speeds count as this for the arrival timing [m/s] (default: 3)",
    )
    mapping.add_argument(
        "--speed-source",
        choices=("norm", "lon"),
        default="norm",
        help="speed from the velocity vector's norm or from |lonVelocity| (default: norm)",
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _planners(args: argparse.Namespace) -> list[tuple[str, str]]:
    """``(planner word, report name)`` pairs, validated; the recorded drivers are the column "inD"."""
    from envs.commands.evaluate import checked_planners

    return checked_planners(args.planner, reserved=("inD",), shield=args.shield)


def _destination(out: str | None) -> Path:
    """The report folder (not created yet): ``--out`` or a fresh ``reports/ind-<time>``."""
    if out is not None:
        return Path(out)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path, k = Path("reports") / f"ind-{stamp}", 1
    while path.exists():
        path, k = Path("reports") / f"ind-{stamp}-{k}", k + 1
    return path


def load_and_map(args: argparse.Namespace):
    """Load the recordings and map their tracks (user mistakes become :class:`UserError`).

    :param args: the parsed command line
    :return: ``(recordings, mapped)``
    """
    from envs.ind.format import IndDataError, location_of_recordings, parse_recordings
    from envs.ind.loader import load_recordings
    from envs.ind.mapping import MappingOptions, layout_arms, map_recordings

    data = Path(args.data)
    if not data.is_dir():
        raise UserError(
            f"--data: {str(data)!r} is not a folder (expected inD's data/ folder with XX_tracks.csv ...)"
        )
    try:
        ids = parse_recordings(args.recordings)
    except ValueError as error:
        raise UserError(f"--{error}") from None
    location = args.location if args.location is not None else location_of_recordings(ids)
    try:
        options = MappingOptions(
            centre=None if args.centre is None else tuple(args.centre),
            major_arms=None if args.major_road is None else tuple(args.major_road),
            inner_radius=args.inner_radius,
            min_travel=args.min_travel,
            arm_tolerance_deg=args.arm_tolerance,
            arrival_timing=args.arrival_timing,
            entry_radius=args.entry_radius,
            min_timing_speed=args.min_timing_speed,
        )
    except ValueError as error:
        raise UserError(f"mapping option: {error}") from None
    try:
        recordings = load_recordings(data, ids, location, speed_source=args.speed_source)
    except (FileNotFoundError, IndDataError) as error:
        raise UserError(str(error)) from None
    try:
        from envs.simulation.layouts import build_layout

        layout = layout_arms(build_layout(DEFAULT_LAYOUT))
    except ImportError:
        layout = None  # the built-in compass layout of envs.ind.mapping
    try:
        mapped = map_recordings(recordings, options, layout)
    except ValueError as error:
        raise UserError(f"mapping: {error}") from None
    return recordings, mapped


def dataset_vehicle_log(mapped, recording: int | None = None) -> pd.DataFrame:
    """The recorded drivers as a vehicle log of the evaluation harness (:mod:`envs.evaluation.metrics`).

    ``first_seen`` is the appearance time, ``crossed`` the time the vehicle passed closest to the
    centre, ``removed`` its last frame; path length and speed limit are unknown, so no delay.

    :param mapped: the mapping
    :param recording: keep one recording
    :return: vehicle log rows with ``planner = "inD"`` and ``scenario``
    """
    import pandas as pd

    from envs.evaluation.metrics import vehicle_frame

    rows = mapped.mapped
    if recording is not None:
        rows = rows[rows["recording"] == recording]
    columns = pd.DataFrame(
        {
            "vehicle_id": rows["track_id"].to_numpy(),
            "route": rows["route"].to_numpy(),
            "priority": rows["priority"].to_numpy(),
            "maneuver": rows["maneuver"].to_numpy(),
            "first_seen": rows["time"].to_numpy(),
            "crossed": rows["t_centre"].to_numpy(),
            "removed": rows["t_last"].to_numpy(),
            "stopped": rows["stopped"].to_numpy(bool),
            "collided": False,
            # the recorded motion, measured as the simulation's (envs.simulation.motion; energy up to "crossed")
            "min_speed": rows["min_speed"].to_numpy(float),
            "hard_brakes": rows["hard_brakes"].to_numpy(float),
            "traction_energy_j": rows["energy_to_centre_j"].to_numpy(float),
        }
    )
    frame = vehicle_frame(columns.to_dict("records"))  # the harness's columns and dtypes
    frame.insert(0, "scenario", rows["recording"].map(_scenario_name).to_numpy())
    frame.insert(0, "planner", "inD")
    return frame


def _scenario_name(recording: int) -> str:
    return f"recording_{recording:02d}.json"


def dataset_runs(mapped, recordings: Sequence) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The recorded drivers' ``metrics.csv`` rows (one per recording) and vehicle log.

    :param mapped: the mapping
    :param recordings: the recordings
    :return: ``(runs, vehicles)`` in the harness's schema, planner ``"inD"``
    """
    import pandas as pd

    from envs.evaluation.metrics import run_metrics

    runs, logs = [], []
    for recording in recordings:
        log = dataset_vehicle_log(mapped, recording.recording_id)
        row: dict[str, Any] = {
            "planner": "inD",
            "run": recording.recording_id,
            "scenario": _scenario_name(recording.recording_id),
        }
        row.update(run_metrics(log, recording.duration))
        row["collision_rate"] = float("nan")  # not measured on recorded drivers
        runs.append(row)
        logs.append(log)
    return pd.DataFrame(runs), pd.concat(logs, ignore_index=True)


def write_scenarios(mapped, recordings: Sequence, folder: Path, layout: str = DEFAULT_LAYOUT) -> list[Path]:
    """One scenario file per recording: the mapped vehicles at their recorded times.

    Vehicle size comes from tracksMeta; where it is missing or zero the scenario's defaults
    (5 m x 2 m) apply. Appearance times are the mapping's ``spawn_time`` (see ``--arrival-timing``).

    :param mapped: the mapping
    :param recordings: the recordings
    :param folder: where to write (created; must not exist)
    :param layout: layout name of the scenarios
    :return: the files, in recording order
    """
    from envs.ind.mapping import DEFAULT_VEHICLE_LENGTH, DEFAULT_VEHICLE_WIDTH, scenario_records
    from envs.simulation.traffic import Scenario

    folder.mkdir(parents=True, exist_ok=False)
    paths = []
    for recording in recordings:
        records = scenario_records(mapped, recording.recording_id)
        length = records["length"].where(records["length"] > 0, DEFAULT_VEHICLE_LENGTH)
        width = records["width"].where(records["width"] > 0, DEFAULT_VEHICLE_WIDTH)
        scenario = Scenario(
            layout=layout,
            duration=recording.duration,
            seed=None,
            vehicle_id=records["vehicle_id"].to_numpy(),
            time=records["time"].to_numpy(),
            route=tuple(records["route"]),
            speed=records["speed"].to_numpy(),
            length=length.to_numpy(),
            width=width.to_numpy(),
            meta={
                "source": "inD",
                "recording": recording.recording_id,
                "locationId": recording.location_id,
                "maneuver": list(records["maneuver"]),
            },
        )
        paths.append(scenario.save(folder / _scenario_name(recording.recording_id)))
    return paths


def _mapping_section(mapped, recordings: Sequence, dataset_table: pd.DataFrame) -> str:
    """Markdown about the data and its mapping, appended to ``report.md``."""
    import numpy as np

    from envs.ind.format import LOCATIONS
    from envs.ind.loader import class_table

    site = recordings[0].location_id
    classes = class_table(recordings).groupby(["class", "modelled"], as_index=False)["tracks"].sum()
    lines = ["", "## inD data and mapping", ""]
    lines.append(
        f"- site: locationId {site} ({LOCATIONS.get(site, 'unknown')}), recordings "
        f"{', '.join(f'{r.recording_id:02d}' for r in recordings)}, "
        f"{sum(r.duration for r in recordings) / 3600:.2f} h"
    )
    how = "estimated from the tracks" if mapped.centre_estimated else "given"
    lines.append(f"- intersection centre ({mapped.centre[0]:.2f}, {mapped.centre[1]:.2f}) m, {how}")
    lines.append(f"- vehicle tracks mapped: {int(mapped.tracks['mapped'].sum())}")
    lines += ["", "| class | tracks | modelled |", "|---|---:|---|"]
    lines += [
        f"| {c} | {n} | {'yes' if m else 'no (counted only)'} |"
        for c, m, n in classes.itertuples(index=False)
    ]
    lines += [
        "",
        "| recorded arm | direction [deg] | entries | exits | major road | layout arm |",
        "|---|---:|---:|---:|---|---|",
    ]
    for name, a in mapped.arms.iterrows():
        lines.append(
            f"| {name} | {a['angle_deg']:.1f} | {a['entries']} | {a['exits']} | "
            f"{'yes' if a['major'] else 'no'} | {a['layout_arm']} |"
        )
    reasons = mapped.reasons()
    lines += [
        "",
        "Tracks not mapped (every one is listed in tracks.csv):",
        "",
        "| reason | tracks |",
        "|---|---:|",
    ]
    lines += [f"| {reason} | {n} |" for reason, n in reasons.items()] or ["| (none) | 0 |"]
    lines += [
        "",
        "Recorded drivers (speed below 0.3 m/s in any frame):",
        "",
        "| group | vehicles | stopped | stop ratio |",
        "|---|---:|---:|---:|",
    ]
    for group, row in dataset_table.iterrows():
        ratio = "n/a" if not np.isfinite(row["stop_ratio"]) else f"{100 * row['stop_ratio']:.1f} %"
        lines.append(f"| {group} | {int(row['vehicles'])} | {int(row['stopped'])} | {ratio} |")
    lines += [
        "",
        "The inD column has no collision rate or delay: neither is measured on recorded drivers.",
        "",
    ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from sb3_graph.files.output_folders import OutputError, check_destination, staged_folder

    check_executor_arguments(args)
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    if args.env_kwargs is not None and not isinstance(args.env_kwargs, dict):
        raise UserError("--env-kwargs must be a JSON object")
    if args.out is not None:
        try:
            check_destination(Path(args.out))
        except OutputError as error:
            raise UserError(str(error)) from None
    planners = [] if args.dataset_only else _planners(args)
    if planners:
        from envs.commands.evaluate import check_env_id, checked_env, load_model_planners

        check_env_id(args.env)
        config = checked_env(args.env, args.env_kwargs)
        if config["layout"] != DEFAULT_LAYOUT:
            raise UserError(
                f"--env: {args.env!r} uses layout {config['layout']!r}; the inD scenarios are written for layout "
                f"{DEFAULT_LAYOUT!r} (CoopIntersectionInD-v0)"
            )
        load_model_planners(planners, config, args.trust_planner_files)
    tic = time.perf_counter()
    recordings, mapped = load_and_map(args)
    if not mapped.tracks["mapped"].any():
        raise UserError(
            "no vehicle track could be mapped; see the reasons with --dataset-only or set --centre"
        )
    out = _destination(args.out)
    try:
        with staged_folder(out) as stage:
            summary = _write(args, stage, recordings, mapped, planners, tic)
    except OutputError as error:
        raise UserError(str(error)) from None
    from envs.evaluation.report import percent

    for name, s in summary.items():
        sr = s["stop_ratio"]
        print(
            f"{name:>10}: {s['vehicles']} vehicles, stopped: left {percent(sr['left'])} "
            f"straight {percent(sr['straight'])} right {percent(sr['right'])}, "
            f"collided vehicles {percent(s['collision_rate'])}"
        )
    from envs.commands.evaluate import print_verdict

    print_verdict(out)
    print(f"report written to {out} ({time.perf_counter() - tic:.1f} s)")
    return 0


def _write(args: argparse.Namespace, out: Path, recordings, mapped, planners, tic: float) -> dict:
    """Every report file into ``out`` (the staging folder); returns the summary."""
    import pandas as pd

    from envs.ind.dataset_metrics import dataset_summary, stop_table
    from envs.ind.loader import class_table

    mapped.tracks.to_csv(out / "tracks.csv", index=False)
    mapped.arms.to_csv(out / "arms.csv")
    class_table(recordings).to_csv(out / "classes.csv", index=False)
    dataset_table = stop_table(mapped)
    dataset_table.to_csv(out / "dataset_stops.csv")
    runs, vehicles = dataset_runs(mapped, recordings)

    stats = None
    if planners:
        from envs.commands.evaluate import harness

        scenarios = write_scenarios(mapped, recordings, out / "scenarios")
        # One pool for every planner and recording: each episode ends at its own scenario's duration.
        r, v, stats = harness(args, planners, scenarios, max(recording.duration for recording in recordings))
        recording_of = {path.name: rec.recording_id for rec, path in zip(recordings, scenarios)}
        runs = pd.concat([runs, r.assign(run=r["scenario"].map(recording_of))], ignore_index=True)
        vehicles = pd.concat([vehicles, v], ignore_index=True)
        # Planners in the given order after the dataset, runs by recording.
        order = {name: k for k, name in enumerate(["inD"] + [n for _, n in planners])}
        runs = runs.sort_values(["planner", "run"], key=lambda c: c.map(order) if c.name == "planner" else c)
        runs = runs.reset_index(drop=True)

    from envs.commands.evaluate import harness_meta, write_run_info
    from envs.evaluation.report import markdown_report, write_report
    from envs.evaluation.verdict import HEADING, read_verdict

    wall = time.perf_counter() - tic
    meta = {
        "environment": args.env,
        "data": f"{args.data}, recordings {args.recordings}",
        "planners": ", ".join(["inD (recorded drivers)"] + [f"{name} ({word})" for word, name in planners]),
        "runs": "one per recording"
        + ("" if args.dataset_only else ", each simulated for the recording's duration"),
        "seed": f"{args.seed} (+ index of the recording)",
        **(harness_meta(stats) if stats else {}),
        "wall time": f"{wall:.1f} s",
        "python": platform.python_version(),
    }
    summary = write_report(out, runs, vehicles, meta)
    # Recorded drivers are not judged for collisions: no rate rather than a made-up 0 %.
    summary["inD"]["collision_rate"] = None
    facts = dataset_summary(mapped, recordings)
    summary["inD"]["unmapped"] = facts["unmapped"]  # vehicle tracks left out, per reason
    summary["inD"]["not_modelled"] = facts["not_modelled"]  # pedestrians, bicycles, ...
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    verdict = read_verdict(out / "report.md")  # write_report's, kept in the rewritten report
    verdict = [HEADING, "", verdict[0], "", *verdict[1:]] if verdict else []
    report = markdown_report(summary, runs, vehicles, meta, verdict=verdict).replace(
        "# Planner evaluation", "# inD replay", 1
    )
    (out / "report.md").write_text(report + _mapping_section(mapped, recordings, dataset_table))
    if stats:
        write_run_info(out, stats, time.perf_counter() - tic)
    return summary
