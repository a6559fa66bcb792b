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
from envs.simulation.traffic import MAX_DURATION

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


# Columns read as numbers (all that this package reads, except the class name), and those that
# must hold whole numbers. A cell that is empty (a truncated file's last row) or not a number is an
# error naming the file, the column and the row.
NUMERIC_COLUMNS = frozenset(
    REQUIRED_TRACKS_COLUMNS + OPTIONAL_TRACKS_COLUMNS + REQUIRED_RECORDING_META_COLUMNS
    + ("recordingId", "trackId", "initialFrame", "finalFrame", "numFrames", "width", "length")
)  # fmt: skip
INTEGER_COLUMNS = frozenset(
    ("recordingId", "trackId", "frame", "locationId", "initialFrame", "finalFrame", "numFrames")
)
GZIP_MAGIC = b"\x1f\x8b"


def _first_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def _read_csv(path: Path, required: Sequence[str], optional: Sequence[str] = ()) -> pd.DataFrame:
    """Read the needed columns of one CSV file as numbers (``class`` as text).

    :raises FileNotFoundError: the file is missing
    :raises IndDataError: naming the file: compressed or binary content, no header, a missing
        column, or a cell that is empty or not a number (with its column and row)
    """
    if not path.is_file():
        raise FileNotFoundError(
            f"inD file not found: {path} (expected the published file name XX_<kind>.csv)"
        )
    try:
        with path.open("rb") as file:
            magic = file.read(2)
    except OSError as error:
        raise IndDataError(f"{path}: cannot read ({error.strerror or error})") from None
    if magic == GZIP_MAGIC:
        raise IndDataError(f"{path}: the file is gzip-compressed; unpack it first (gunzip, or inD's own archive)")
    try:
        header = pd.read_csv(path, nrows=0).columns
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError, ValueError) as error:
        raise IndDataError(f"{path}: not a CSV file with a header row ({_first_line(error)})") from None
    missing = [c for c in required if c not in header]
    if missing:
        raise IndDataError(
            f"{path}: missing column(s) {', '.join(missing)}; the inD format requires {', '.join(required)}"
        )
    columns = list(dict.fromkeys(list(required) + [c for c in optional if c in header]))
    try:
        frame = pd.read_csv(path, usecols=columns, dtype=str, keep_default_na=False)
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError, MemoryError) as error:
        raise IndDataError(f"{path}: not a readable CSV file ({_first_line(error)})") from None
    for column in columns:
        if column in NUMERIC_COLUMNS:
            frame[column] = _numbers(frame[column], path, column)
    return frame


def _numbers(cells: pd.Series, path: Path, column: str) -> pd.Series:
    """A column of text cells as numbers, or an error naming the first bad cell."""
    values = pd.to_numeric(cells.str.strip(), errors="coerce")
    bad = values.isna() | ~np.isfinite(values.to_numpy(dtype=float, na_value=np.nan))
    if column in INTEGER_COLUMNS:
        bad |= values.notna() & (values.round() != values)
    if bad.any():
        row = int(np.flatnonzero(bad.to_numpy())[0])
        cell = cells.iloc[row]
        what = "is empty (a truncated file?)" if not str(cell).strip() else f"{cell!r} is not a"
        kind = "whole number" if column in INTEGER_COLUMNS else "finite number"
        text = what if what.endswith("?)") else f"{what} {kind}"
        raise IndDataError(f"{path}: column {column!r}, line {row + 2}: {text}")
    return values.astype(np.int64) if column in INTEGER_COLUMNS else values.astype(float)


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
    duration = float(meta["duration"])
    if not np.isfinite(duration) or not 0 < duration <= MAX_DURATION:
        raise IndDataError(
            f"{meta_path}: duration must be a number of seconds in (0, {MAX_DURATION:g}], got {meta['duration']!r}"
        )

    tracks_meta = _read_csv(tracks_meta_path, REQUIRED_TRACKS_META_COLUMNS, ("numFrames", "width", "length"))
    if tracks_meta["trackId"].duplicated().any():
        raise IndDataError(f"{tracks_meta_path}: trackId values must be unique")
    tracks_meta["class"] = tracks_meta["class"].astype(str).str.strip().str.lower()
    tracks_meta["is_vehicle"] = tracks_meta["class"].isin(VEHICLE_CLASSES)
    tracks_meta = tracks_meta.set_index("trackId", drop=False).rename_axis(None)

    tracks = _read_csv(tracks_path, REQUIRED_TRACKS_COLUMNS, OPTIONAL_TRACKS_COLUMNS)
    if tracks.empty and len(tracks_meta):
        raise IndDataError(
            f"{tracks_path}: no track rows, only the header ({len(tracks_meta)} tracks listed in "
            f"{tracks_meta_path.name}; a truncated file?)"
        )
    unknown = np.setdiff1d(tracks["trackId"].unique(), tracks_meta["trackId"].to_numpy())
    if unknown.size:
        raise IndDataError(
            f"{tracks_path}: trackId(s) {unknown[:5].tolist()} have no row in {tracks_meta_path.name}"
        )
    _check_complete(tracks, tracks_meta, tracks_path, tracks_meta_path)
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
        duration=duration,
        meta=meta,
        tracks_meta=tracks_meta,
        tracks=tracks,
        class_counts={str(k): int(v) for k, v in tracks_meta["class"].value_counts().sort_index().items()},
    )


def _check_complete(tracks: pd.DataFrame, tracks_meta: pd.DataFrame, tracks_path: Path, meta_path: Path) -> None:
    """Every track that has rows in the tracks file has them from its ``initialFrame`` to its
    ``finalFrame``: a file cut off in the middle of a track is refused, not replayed with a vehicle
    that vanishes. (A track without any row is listed by the mapping as not mapped.)"""
    span = tracks.groupby("trackId")["frame"].agg(["min", "max"])
    span = span.reindex(tracks_meta["trackId"].to_numpy())
    present = span["min"].notna().to_numpy()
    short = present & (
        (span["min"].to_numpy() > tracks_meta["initialFrame"].to_numpy())
        | (span["max"].to_numpy() < tracks_meta["finalFrame"].to_numpy())
    )
    if short.any():
        k = int(np.flatnonzero(short)[0])
        track = int(tracks_meta["trackId"].iloc[k])
        first, last = int(tracks_meta["initialFrame"].iloc[k]), int(tracks_meta["finalFrame"].iloc[k])
        found = f"frames {int(span['min'].iloc[k])}-{int(span['max'].iloc[k])}"
        raise IndDataError(
            f"{tracks_path}: track {track} has {found}, {meta_path.name} says frames {first}-{last} "
            "(a truncated or mismatched tracks file?)"
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
