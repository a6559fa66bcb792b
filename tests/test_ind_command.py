"""``sb3-graph ind``: files written, clear errors, scenarios, and a replay end to end."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from envs.ind.format import recording_file
from envs.ind.synthetic import (
    SyntheticSite,
    SyntheticVehicle,
    default_vehicles,
    make_recording,
    write_recording,
)
from sb3_graph.cli import main

SITE = SyntheticSite(centre=(-75.0, 140.0), rotation_deg=17.0, location_id=1)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ind_data")
    written = {rid: make_recording(rid, default_vehicles(seed=rid, num=16), SITE) for rid in (7, 8)}
    for recording in written.values():
        write_recording(folder, recording)
    return folder, written


def _mapped_count(written) -> int:
    return int(sum((w.expected["reason"] == "").sum() for w in written.values()))


def test_dataset_only_writes_the_report_files(data, tmp_path, capsys):
    folder, written = data
    out = tmp_path / "report"
    rc = main(["ind", "--data", str(folder), "--recordings", "07-08", "--dataset-only", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    for name in (
        "metrics.csv",
        "vehicles.csv",
        "summary.json",
        "report.md",
        "flow_rate.png",
        "stops_by_priority.png",
        "stops_by_maneuver.png",
        "tracks.csv",
        "arms.csv",
        "classes.csv",
        "dataset_stops.csv",
    ):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary) == ["inD"]
    assert summary["inD"]["vehicles"] == _mapped_count(written)
    assert summary["inD"]["runs"] == 2 and summary["inD"]["collision_rate"] is None
    assert summary["inD"]["not_modelled"] == {"pedestrian": 2, "bicycle": 2}
    assert sum(summary["inD"]["unmapped"].values()) == 10
    tracks = pd.read_csv(out / "tracks.csv", keep_default_na=False)
    assert len(tracks) == sum(len(w.tracks_meta) for w in written.values())
    assert (tracks.loc[tracks["mapped"].astype(str) == "False", "reason"] != "").all()
    report = (out / "report.md").read_text()
    assert "not modelled: pedestrian" in report and "| inD |" in report
    stops = pd.read_csv(out / "dataset_stops.csv", index_col=0)
    left = pd.concat([w.expected for w in written.values()]).query("reason == '' and maneuver == 'left'")
    assert (
        stops.loc["left", "vehicles"] == len(left) and stops.loc["left", "stopped"] == left["stopped"].sum()
    )


def _error(capsys, argv) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


def test_user_errors_are_one_line_and_name_the_problem(data, tmp_path, capsys):
    folder, written = data
    base = ["ind", "--dataset-only", "--out", str(tmp_path / "never")]
    assert "is not a folder" in _error(capsys, ["ind", "--data", str(tmp_path / "nope"), *base[1:]])
    assert "09_recordingMeta.csv" in _error(
        capsys, ["ind", "--data", str(folder), "--recordings", "09", *base[1:]]
    )
    err = _error(capsys, ["ind", "--data", str(folder), "--recordings", "07", "--location", "2", *base[1:]])
    assert "07_recordingMeta.csv" in err and "locationId is 1" in err and "expected 2" in err
    assert "--recordings" in _error(capsys, ["ind", "--data", str(folder), "--recordings", "7-x", *base[1:]])
    broken = tmp_path / "broken"
    write_recording(broken, written[7])
    path = recording_file(broken, 7, "tracks")
    pd.read_csv(path).drop(columns=["heading"]).to_csv(path, index=False)
    err = _error(capsys, ["ind", "--data", str(broken), "--recordings", "07", *base[1:]])
    assert "07_tracks.csv" in err and "heading" in err
    err = _error(
        capsys, ["ind", "--data", str(folder), "--recordings", "07", "--major-road", "east", "up", *base[1:]]
    )
    assert "major_arms" in err
    replay = ["ind", "--data", str(folder), "--recordings", "07", "--out", str(tmp_path / "never")]
    assert "--planner" in _error(capsys, [*replay, "--planner", "missing_model.zip"])
    assert "--env" in _error(capsys, [*replay, "--planner", "fifo", "--env", "NoSuchEnv-v0"])
    (tmp_path / "taken").mkdir()
    err = _error(capsys, ["ind", "--data", str(folder), "--dataset-only", "--out", str(tmp_path / "taken")])
    assert "exists" in err
    assert not (tmp_path / "never").exists()


def test_scenario_files_hold_the_mapped_vehicles(data, tmp_path):
    traffic = pytest.importorskip("envs.simulation.traffic")
    from envs.commands import ind

    folder, written = data
    args = ind.argparse.Namespace(
        data=str(folder),
        recordings="07-08",
        location=None,
        centre=None,
        major_road=None,
        inner_radius=10.0,
        min_travel=5.0,
        arm_tolerance=30.0,
        speed_source="norm",
        arrival_timing=True,
        entry_radius=None,
        min_timing_speed=3.0,
    )
    recordings, mapped = ind.load_and_map(args)
    paths = ind.write_scenarios(mapped, recordings, tmp_path / "scenarios")
    assert [p.name for p in paths] == ["recording_07.json", "recording_08.json"]
    for path, w in zip(paths, written.values()):
        scenario = traffic.Scenario.load(path)
        expected = w.expected[w.expected["reason"] == ""].sort_values("time", kind="stable")
        assert scenario.layout == "inD" and scenario.num_vehicles == len(expected)
        # Appearances are timed for the stop line (the mapping's spawn_time), never after the
        # recorded appearance here: the simulated approach is longer than the recorded arms.
        table = mapped.mapped.set_index(["recording", "track_id"]).loc[scenario.meta["recording"]]
        spawn = table.loc[scenario.vehicle_id, "spawn_time"].to_numpy()
        np.testing.assert_allclose(scenario.time, spawn)
        assert (scenario.time >= 0).all()
        assert (scenario.time <= table.loc[scenario.vehicle_id, "time"].to_numpy() + 1e-9).all()
        by_id = dict(zip(scenario.vehicle_id.tolist(), scenario.route))
        lengths = dict(zip(scenario.vehicle_id.tolist(), scenario.length))
        for track_id, row in expected.iterrows():
            assert by_id[track_id] == f"{row['entry']}->{row['exit']}"  # site rotated by 17 deg only
            assert lengths[track_id] == (10.0 if row["class"] == "truck_bus" else 4.5)
        assert scenario.duration == pytest.approx(float(w.recording_meta["duration"].iloc[0]))
    with pytest.raises(FileExistsError):
        ind.write_scenarios(mapped, recordings, tmp_path / "scenarios")


def _replay_ready() -> bool:
    try:
        import gymnasium as gym

        import envs  # noqa: F401
        import envs.evaluation.harness  # noqa: F401
        import envs.simulation.traffic  # noqa: F401

        return "CoopIntersectionInD-v0" in gym.registry
    except Exception:
        return False


@pytest.mark.skipif(not _replay_ready(), reason="the environment and the evaluation harness are not ready")
def test_replay_end_to_end(tmp_path, capsys, monkeypatch):
    import envs.simulation.traffic as traffic

    # The harness reads scenario files with load_scenario; --jobs 1 runs in this process.
    if not hasattr(traffic, "load_scenario"):
        monkeypatch.setattr(traffic, "load_scenario", traffic.Scenario.load, raising=False)
    folder = tmp_path / "data"
    routes = [
        ("east", "west", 0.0),
        ("west", "north", 2.0),
        ("south", "north", 1.0),
        ("north", "east", 0.0),
        ("east", "south", 0.0),
        ("west", "east", 0.0),
        ("south", "west", 0.0),
        ("north", "south", 0.0),
    ]
    vehicles = [
        SyntheticVehicle(e, x, time=3.0 * k, speed=8.0, stop=stop) for k, (e, x, stop) in enumerate(routes)
    ]
    write_recording(folder, make_recording(7, vehicles, SITE, extras=True))
    out = tmp_path / "report"
    argv = ["ind", "--data", str(folder), "--recordings", "07", "--planner", "fifo", "--jobs", "1"]
    argv += ["--no-progress", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary) == ["inD", "FIFO"]
    assert summary["inD"]["vehicles"] == len(vehicles)
    assert summary["FIFO"]["vehicles"] == len(vehicles)
    runs = pd.read_csv(out / "metrics.csv")
    assert list(runs["planner"]) == ["inD", "FIFO"] and set(runs["run"]) == {7}
    # Every planner meets the recorded vehicles on the same routes.
    logged = pd.read_csv(out / "vehicles.csv")
    routes = logged.groupby("planner")["route"].apply(lambda r: sorted(r))
    assert routes["FIFO"] == routes["inD"]
    assert (out / "scenarios" / "recording_07.json").is_file()


def test_arrival_timing_switch_and_help(data, tmp_path, capsys):
    folder, _ = data
    with pytest.raises(SystemExit) as exit_:
        main(["ind", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--arrival-timing, --no-arrival-timing" in text and "stop line" in text and "--entry-radius" in text
    tracks = {}
    for flag in ("--arrival-timing", "--no-arrival-timing"):
        out = tmp_path / flag
        argv = ["ind", "--data", str(folder), "--recordings", "07", "--dataset-only", flag, "--out", str(out)]
        assert main(argv) == 0, capsys.readouterr().err
        tracks[flag] = pd.read_csv(out / "tracks.csv").query("mapped")
    raw, timed = tracks["--no-arrival-timing"], tracks["--arrival-timing"]
    np.testing.assert_allclose(raw["spawn_time"], raw["time"])
    assert raw["t_entry"].isna().all() and timed["t_entry"].notna().all()
    # Recorded arms (45 m) are shorter than the simulated approach: vehicles appear earlier, never before 0.
    assert (timed["spawn_time"] <= timed["time"]).all() and (timed["spawn_time"] < timed["time"]).any()
    assert (timed["spawn_time"] >= 0).all()
    assert (timed["t_entry"] > timed["time"]).all()
