"""Read inD recordings (``XX_tracks.csv``, ``XX_tracksMeta.csv``, ``XX_recordingMeta.csv``) with pandas.

Only vehicles (:data:`~envs.ind.format.VEHICLE_CLASSES`) keep their per-frame rows: they are what
the simulation replays. Every other class (pedestrians, bicycles) is counted in
:attr:`Recording.class_counts` and reported as not modelled.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from envs.ind.format import (
    LOCATIONS,
    OPTIONAL_TRACKS_COLUMNS,
    REQUIRED_RECORDING_META_COLUMNS,
    REQUIRED_TRACKS_COLUMNS,
    REQUIRED_TRACKS_META_COLUMNS,
    VEHICLE_CLASSES,
    IndDataError,
    recording_file,
)

SPEED_SOURCES = ("norm", "lon")


@dataclass
class Recording:
    """One inD recording, vehicles only in the per-frame table.

    :param recording_id: the recording number
    :param location_id: the site (``locationId`` of the recording meta)
    :param frame_rate: frames per second
    :param duration: recording length [s]
    :param meta: the recording meta row as a dict
    :param tracks_meta: one row per track of every class, indexed by ``trackId``, with the
        published columns plus ``is_vehicle`` (bool)
    :param tracks: per-frame rows of the vehicle tracks: ``trackId``, ``frame``, ``xCenter``,
        ``yCenter``, ``heading``, ``xVelocity``, ``yVelocity`` and ``speed`` [m/s]
    :param class_counts: number of tracks of each class, vehicles and others
    """

    recording_id: int
    location_id: int
    frame_rate: float
    duration: float
    meta: dict
    tracks_meta: pd.DataFrame
    tracks: pd.DataFrame
    class_counts: dict[str, int] = field(default_factory=dict)

    @property
    def num_vehicles(self) -> int:
        """Number of vehicle tracks."""
        return int(self.tracks_meta["is_vehicle"].sum())

    @property
    def not_modelled(self) -> dict[str, int]:
        """Track counts of the classes the simulation does not model (pedestrians, bicycles, ...)."""
        return {c: n for c, n in self.class_counts.items() if c not in VEHICLE_CLASSES}


def _read_csv(path: Path, required: Sequence[str], optional: Sequence[str] = ()) -> pd.DataFrame:
    """Read the needed columns of one CSV file; a missing file or column names the file."""
    if not path.is_file():
        raise FileNotFoundError(
            f"inD file not found: {path} (expected the published file name XX_<kind>.csv)"
        )
    try:
        header = pd.read_csv(path, nrows=0).columns
    except (pd.errors.EmptyDataError, pd.errors.ParserError) as error:
        raise IndDataError(f"{path}: not a CSV file with a header row ({error})") from None
    missing = [c for c in required if c not in header]
    if missing:
        raise IndDataError(
            f"{path}: missing column(s) {', '.join(missing)}; the inD format requires {', '.join(required)}"
        )
    columns = list(required) + [c for c in optional if c in header]
    return pd.read_csv(path, usecols=columns)


def load_recording(
    data_dir: str | Path,
    recording_id: int,
    location_id: int | None = None,
    speed_source: str = "norm",
) -> Recording:
    """Load one inD recording.

    :param data_dir: folder with the CSV files (inD's ``data/`` folder)
    :param recording_id: recording number, e.g. ``7`` for ``07_*.csv``
    :param location_id: the site the caller expects; a recording of another site is an error.
        ``None`` accepts any site.
    :param speed_source: ``"norm"``: speed is the norm of ``(xVelocity, yVelocity)``; ``"lon"``:
        the absolute ``lonVelocity`` (falls back to the norm where that column is absent)
    :return: the recording
    :raises FileNotFoundError: a file of the recording is missing
    :raises IndDataError: a column is missing, ids disagree, or the site is not ``location_id``
    """
    if speed_source not in SPEED_SOURCES:
        raise ValueError(f"speed_source must be one of {SPEED_SOURCES}, got {speed_source!r}")
    meta_path = recording_file(data_dir, recording_id, "recordingMeta")
    tracks_meta_path = recording_file(data_dir, recording_id, "tracksMeta")
    tracks_path = recording_file(data_dir, recording_id, "tracks")
    for path in (meta_path, tracks_meta_path, tracks_path):  # all missing files before any parsing
        if not path.is_file():
            raise FileNotFoundError(
                f"inD file not found: {path} (recording {recording_id:02d} needs "
                f"{meta_path.name}, {tracks_meta_path.name} and {tracks_path.name})"
            )

    meta_frame = _read_csv(meta_path, REQUIRED_RECORDING_META_COLUMNS)
    if len(meta_frame) != 1:
        raise IndDataError(f"{meta_path}: expected exactly one row, found {len(meta_frame)}")
    meta = pd.read_csv(meta_path).iloc[0].to_dict()
    if int(meta["recordingId"]) != int(recording_id):
        raise IndDataError(
            f"{meta_path}: recordingId is {int(meta['recordingId'])}, expected {int(recording_id)}"
        )
    site = int(meta["locationId"])
    if location_id is not None and site != int(location_id):
        raise IndDataError(
            f"{meta_path}: locationId is {site} ({LOCATIONS.get(site, 'unknown site')}), expected "
            f"{int(location_id)} ({LOCATIONS.get(int(location_id), 'unknown site')})"
        )
    frame_rate = float(meta["frameRate"])
    if not np.isfinite(frame_rate) or frame_rate <= 0:
        raise IndDataError(f"{meta_path}: frameRate must be a positive number, got {meta['frameRate']!r}")

    tracks_meta = _read_csv(tracks_meta_path, REQUIRED_TRACKS_META_COLUMNS, ("numFrames", "width", "length"))
    if tracks_meta["trackId"].duplicated().any():
        raise IndDataError(f"{tracks_meta_path}: trackId values must be unique")
    tracks_meta["class"] = tracks_meta["class"].astype(str).str.strip().str.lower()
    tracks_meta["is_vehicle"] = tracks_meta["class"].isin(VEHICLE_CLASSES)
    tracks_meta = tracks_meta.set_index("trackId", drop=False).rename_axis(None)

    tracks = _read_csv(tracks_path, REQUIRED_TRACKS_COLUMNS, OPTIONAL_TRACKS_COLUMNS)
    unknown = np.setdiff1d(tracks["trackId"].unique(), tracks_meta["trackId"].to_numpy())
    if unknown.size:
        raise IndDataError(
            f"{tracks_path}: trackId(s) {unknown[:5].tolist()} have no row in {tracks_meta_path.name}"
        )
    vehicle_ids = tracks_meta.index[tracks_meta["is_vehicle"]]
    tracks = tracks[tracks["trackId"].isin(vehicle_ids)].sort_values(["trackId", "frame"], kind="stable")
    speed = np.hypot(tracks["xVelocity"].to_numpy(), tracks["yVelocity"].to_numpy())
    if speed_source == "lon" and "lonVelocity" in tracks:
        speed = np.abs(tracks["lonVelocity"].to_numpy())
    tracks = tracks.assign(speed=speed).reset_index(drop=True)

    return Recording(
        recording_id=int(recording_id),
        location_id=site,
        frame_rate=frame_rate,
        duration=float(meta["duration"]),
        meta=meta,
        tracks_meta=tracks_meta,
        tracks=tracks,
        class_counts={str(k): int(v) for k, v in tracks_meta["class"].value_counts().sort_index().items()},
    )


def load_recordings(
    data_dir: str | Path,
    recording_ids: Sequence[int],
    location_id: int | None = None,
    speed_source: str = "norm",
) -> list[Recording]:
    """Load several recordings of one site.

    :param data_dir: folder with the CSV files
    :param recording_ids: recording numbers
    :param location_id: the expected site; ``None``: the site of the first recording, so that
        all recordings come from one site
    :param speed_source: see :func:`load_recording`
    :return: the recordings in the order given
    """
    recordings: list[Recording] = []
    for recording_id in recording_ids:
        recording = load_recording(data_dir, recording_id, location_id, speed_source)
        location_id = recording.location_id if location_id is None else location_id
        recordings.append(recording)
    return recordings


def class_table(recordings: Sequence[Recording]) -> pd.DataFrame:
    """Track counts per recording and class, with whether the simulation models the class.

    :param recordings: loaded recordings
    :return: columns ``recording``, ``class``, ``tracks``, ``modelled``
    """
    rows = [
        {"recording": r.recording_id, "class": c, "tracks": n, "modelled": c in VEHICLE_CLASSES}
        for r in recordings
        for c, n in r.class_counts.items()
    ]
    return pd.DataFrame(rows, columns=["recording", "class", "tracks", "modelled"])
