"""The recorded drivers' stop ratios and vehicle counts."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from envs.ind import dataset_metrics as dm
from envs.ind.format import recording_file
from envs.ind.loader import load_recording, load_recordings
from envs.ind.mapping import map_recordings
from envs.ind.synthetic import SyntheticSite, default_vehicles, make_recording, write_recording

SITE = SyntheticSite(centre=(518.0, 330.5), rotation_deg=-37.0)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ind")
    written = {rid: make_recording(rid, default_vehicles(seed=rid, num=30), SITE) for rid in (9, 10)}
    for recording in written.values():
        write_recording(folder, recording)
    recordings = load_recordings(folder, [9, 10])
    return folder, written, recordings, map_recordings(recordings)


def _expected_table(expected: pd.DataFrame, major: set[str]) -> pd.DataFrame:
    rows = expected[expected["reason"] == ""]
    priority = np.where(rows["entry"].isin(major), "major", "minor")
    groups = {"all": np.ones(len(rows), bool)}
    groups.update({p: priority == p for p in ("major", "minor")})
    groups.update({k: (rows["maneuver"] == k).to_numpy() for k in ("left", "straight", "right")})
    return pd.DataFrame(
        {name: [mask.sum(), rows["stopped"].to_numpy()[mask].sum()] for name, mask in groups.items()},
        index=["vehicles", "stopped"],
    ).T


def test_stop_table_counts_vehicles_and_stops_per_maneuver_and_priority(data):
    _, written, _, mapped = data
    expected = _expected_table(pd.concat([w.expected for w in written.values()]), {"east", "west"})
    table = dm.stop_table(mapped)
    assert list(table.index) == list(dm.CATEGORIES)
    np.testing.assert_array_equal(table["vehicles"].to_numpy(), expected["vehicles"].to_numpy())
    np.testing.assert_array_equal(table["stopped"].to_numpy(), expected["stopped"].to_numpy())
    np.testing.assert_allclose(table["stop_ratio"], expected["stopped"] / expected["vehicles"])
    # The synthetic drivers stop before left turns far more often, as at the real site.
    assert table.loc["left", "stop_ratio"] > table.loc["straight", "stop_ratio"]
    assert table.loc["major", "vehicles"] + table.loc["minor", "vehicles"] == table.loc["all", "vehicles"]


def test_stop_threshold_is_any_frame_below_0_3(data, tmp_path):
    _, written, _, _ = data
    write_recording(tmp_path, written[9])
    path = recording_file(tmp_path, 9, "tracks")
    tracks = pd.read_csv(path)
    movers = written[9].expected.query("reason == '' and not stopped").index[:2]
    for track_id, speed in zip(movers, (0.29, 0.31)):  # one frame, nothing else changes
        row = tracks.index[tracks["trackId"] == track_id][40]
        tracks.loc[row, ["xVelocity", "yVelocity"]] = [speed, 0.0]
    tracks.to_csv(path, index=False)
    table = map_recordings([load_recording(tmp_path, 9)]).tracks.set_index("track_id")
    assert table.loc[movers[0], "stopped"] and not table.loc[movers[1], "stopped"]


def test_per_recording_rows_and_summary_schema(data):
    _, written, recordings, mapped = data
    runs = dm.per_recording(mapped, recordings)
    assert list(runs["run"]) == [9, 10] and (runs["planner"] == dm.DATASET_NAME).all()
    for rid, w in written.items():
        row = runs.set_index("run").loc[rid]
        assert row["vehicles"] == (w.expected["reason"] == "").sum()
        assert row["flow_rate"] == pytest.approx(
            row["vehicles"] / float(w.recording_meta["duration"].iloc[0])
        )
    summary = dm.dataset_summary(mapped, recordings)
    assert {"runs", "vehicles", "flow_rate", "stop_ratio", "collision_rate", "delay_s"} <= set(summary)
    assert summary["runs"] == 2 and summary["vehicles"] == runs["vehicles"].sum()
    assert set(summary["stop_ratio"]) == {"all", "major", "minor", "left", "straight", "right"}
    assert set(summary["flow_rate"]) == {"median", "q1", "q3", "mean"}
    assert summary["not_modelled"] == {"pedestrian": 2, "bicycle": 2}
    assert sum(summary["unmapped"].values()) == 10  # five unmappable vehicle tracks per recording
    table = dm.stop_table(mapped)
    assert summary["stop_ratio"]["left"] == pytest.approx(table.loc["left", "stop_ratio"])


def test_empty_category_has_no_ratio(data):
    _, _, recordings, mapped = data
    only_right = type(mapped)(mapped.tracks[mapped.tracks["maneuver"] == "right"], mapped.arms, mapped.centre)
    table = dm.stop_table(only_right)
    assert table.loc["left", "vehicles"] == 0 and np.isnan(table.loc["left", "stop_ratio"])
    assert dm.dataset_summary(only_right, recordings)["stop_ratio"]["left"] is None
