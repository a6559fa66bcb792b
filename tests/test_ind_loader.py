"""The inD loader reads the published file format and fails clearly on bad input."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from envs.ind.format import (
    RECORDING_META_COLUMNS,
    TRACKS_COLUMNS,
    TRACKS_META_COLUMNS,
    IndDataError,
    location_of_recordings,
    parse_recordings,
    recording_file,
)
from envs.ind.loader import class_table, load_recording, load_recordings
from envs.ind.synthetic import SyntheticSite, default_vehicles, make_recording, write_recording

SITE = SyntheticSite(centre=(-312.5, 87.25), rotation_deg=23.0, location_id=1)
OTHER_SITE = SyntheticSite(centre=(40.0, 12.0), rotation_deg=-61.0, location_id=2)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ind")
    recording = make_recording(7, default_vehicles(seed=0, num=24), SITE)
    write_recording(folder, recording)
    write_recording(folder, make_recording(18, default_vehicles(seed=1, num=12), OTHER_SITE))
    return folder, recording


def test_written_files_have_the_published_columns(data):
    folder, _ = data
    assert tuple(pd.read_csv(recording_file(folder, 7, "tracks"), nrows=0).columns) == TRACKS_COLUMNS
    assert tuple(pd.read_csv(recording_file(folder, 7, "tracksMeta"), nrows=0).columns) == TRACKS_META_COLUMNS
    assert (
        tuple(pd.read_csv(recording_file(folder, 7, "recordingMeta"), nrows=0).columns)
        == RECORDING_META_COLUMNS
    )
    assert recording_file(folder, 7, "tracks").name == "07_tracks.csv"


def test_load_keeps_vehicle_frames_and_counts_every_class(data):
    folder, written = data
    recording = load_recording(folder, 7, location_id=1)
    assert recording.recording_id == 7 and recording.location_id == 1
    assert recording.frame_rate == pytest.approx(25.0)
    classes = written.tracks_meta["class"].value_counts().to_dict()
    assert recording.class_counts == classes
    assert recording.not_modelled == {"pedestrian": 1, "bicycle": 1}
    assert recording.num_vehicles == classes.get("car", 0) + classes.get("truck_bus", 0)
    # Per-frame rows: vehicles only, every one of their frames, sorted by track and frame.
    vehicle_ids = written.tracks_meta.loc[written.tracks_meta["class"].isin(["car", "truck_bus"]), "trackId"]
    assert set(recording.tracks["trackId"]) == set(vehicle_ids)
    assert len(recording.tracks) == written.tracks["trackId"].isin(vehicle_ids).sum()
    assert (recording.tracks.groupby("trackId")["frame"].diff().dropna() == 1).all()
    speed = np.hypot(recording.tracks["xVelocity"], recording.tracks["yVelocity"])
    np.testing.assert_allclose(recording.tracks["speed"], speed)


def test_speed_from_lon_velocity(data):
    folder, _ = data
    recording = load_recording(folder, 7, speed_source="lon")
    np.testing.assert_allclose(recording.tracks["speed"], recording.tracks["lonVelocity"].abs())
    with pytest.raises(ValueError, match="speed_source"):
        load_recording(folder, 7, speed_source="abs")


def test_missing_file_names_the_file(data, tmp_path):
    folder, written = data
    write_recording(tmp_path, written)
    recording_file(tmp_path, 7, "tracksMeta").unlink()
    with pytest.raises(FileNotFoundError, match="07_tracksMeta.csv"):
        load_recording(tmp_path, 7)
    with pytest.raises(FileNotFoundError, match="09_recordingMeta.csv"):
        load_recording(folder, 9)


@pytest.mark.parametrize(
    ("kind", "column"), [("tracks", "yCenter"), ("tracksMeta", "class"), ("recordingMeta", "frameRate")]
)
def test_missing_column_names_file_and_column(data, tmp_path, kind, column):
    _, written = data
    write_recording(tmp_path, written)
    path = recording_file(tmp_path, 7, kind)
    pd.read_csv(path).drop(columns=[column]).to_csv(path, index=False)
    with pytest.raises(IndDataError, match=rf"07_{kind}\.csv.*{column}"):
        load_recording(tmp_path, 7)


def test_recording_of_another_site_is_an_error(data):
    folder, _ = data
    with pytest.raises(
        IndDataError, match=r"18_recordingMeta\.csv.*locationId is 2 \(Frankenburg\).*expected 1"
    ):
        load_recording(folder, 18, location_id=1)
    # Without an expected site, the first recording fixes it.
    with pytest.raises(IndDataError, match="locationId is 2"):
        load_recordings(folder, [7, 18])
    assert [r.recording_id for r in load_recordings(folder, [18])] == [18]


def test_track_without_meta_row_is_an_error(data, tmp_path):
    _, written = data
    write_recording(tmp_path, written)
    path = recording_file(tmp_path, 7, "tracksMeta")
    meta = pd.read_csv(path)
    meta[meta["trackId"] != 3].to_csv(path, index=False)
    with pytest.raises(IndDataError, match=r"07_tracks\.csv.*\[3\]"):
        load_recording(tmp_path, 7)


def test_a_header_only_tracks_file_is_named(data, tmp_path):
    _, written = data
    write_recording(tmp_path, written)
    path = recording_file(tmp_path, 7, "tracks")
    path.write_text(path.read_text().splitlines()[0] + "\n")
    with pytest.raises(IndDataError, match=r"07_tracks\.csv: no track rows, only the header"):
        load_recording(tmp_path, 7)


def test_existing_files_are_not_overwritten(data):
    folder, written = data
    with pytest.raises(FileExistsError, match="07_tracks.csv"):
        write_recording(folder, written)


def test_class_table(data):
    folder, _ = data
    table = class_table([load_recording(folder, 7)])
    assert set(table.loc[~table["modelled"], "class"]) == {"pedestrian", "bicycle"}
    assert table["tracks"].sum() == 24 + 7  # the vehicles plus the seven extra tracks


def test_parse_recordings_and_sites():
    assert parse_recordings("07-17") == list(range(7, 18))
    assert parse_recordings("7, 9,18-19,9") == [7, 9, 18, 19]
    for bad in ("17-07", "x", "", "1-2-3"):
        with pytest.raises(ValueError, match="recordings"):
            parse_recordings(bad)
    assert location_of_recordings([7, 17]) == 1
    assert location_of_recordings([18, 29]) == 2
    assert location_of_recordings([17, 18]) is None
