"""The inD file format, as published by ika (RWTH Aachen) with the dataset.

Every recording ``XX`` (two digits) is three CSV files in one folder::

    XX_tracks.csv         one row per (track, frame)
    XX_tracksMeta.csv     one row per track
    XX_recordingMeta.csv  one row: the recording

Coordinates are metres in a local, right-handed frame (x east, y north; ``xUtmOrigin`` /
``yUtmOrigin`` shift it to UTM), ``heading`` is in degrees counter-clockwise from +x, and the
frame rate is ``frameRate`` (25 Hz in the published data). Column names follow the dataset's
format description and the reference reader ``src/tracks_import.py`` of
ika-rwth-aachen/drone-dataset-tools.
"""

from __future__ import annotations

from pathlib import Path

# All columns of each file, in the published order.
TRACKS_COLUMNS: tuple[str, ...] = (
    "recordingId",
    "trackId",
    "frame",
    "trackLifetime",
    "xCenter",
    "yCenter",
    "heading",
    "width",
    "length",
    "xVelocity",
    "yVelocity",
    "xAcceleration",
    "yAcceleration",
    "lonVelocity",
    "latVelocity",
    "lonAcceleration",
    "latAcceleration",
)
TRACKS_META_COLUMNS: tuple[str, ...] = (
    "recordingId",
    "trackId",
    "initialFrame",
    "finalFrame",
    "numFrames",
    "width",
    "length",
    "class",
)
RECORDING_META_COLUMNS: tuple[str, ...] = (
    "recordingId",
    "locationId",
    "frameRate",
    "speedLimit",
    "weekday",
    "startTime",
    "duration",
    "numTracks",
    "numVehicles",
    "numVRUs",
    "latLocation",
    "lonLocation",
    "xUtmOrigin",
    "yUtmOrigin",
    "orthoPxToMeter",
)

# The columns this package reads; a file lacking one of them is an error naming file and column.
# The others are optional so that a trimmed copy of the data still loads.
REQUIRED_TRACKS_COLUMNS: tuple[str, ...] = (
    "recordingId",
    "trackId",
    "frame",
    "xCenter",
    "yCenter",
    "heading",
    "xVelocity",
    "yVelocity",
)
OPTIONAL_TRACKS_COLUMNS: tuple[str, ...] = ("lonVelocity",)
REQUIRED_TRACKS_META_COLUMNS: tuple[str, ...] = (
    "recordingId",
    "trackId",
    "initialFrame",
    "finalFrame",
    "class",
)
REQUIRED_RECORDING_META_COLUMNS: tuple[str, ...] = ("recordingId", "locationId", "frameRate", "duration")

# Object classes of inD ("class" of tracksMeta). Later levelXdata exports split ``truck_bus``
# into ``truck`` and ``bus``: both are vehicles too.
VEHICLE_CLASSES: tuple[str, ...] = ("car", "truck_bus", "truck", "bus", "van")
VRU_CLASSES: tuple[str, ...] = ("pedestrian", "bicycle", "motorcycle")

# inD recording sites. The two four-way intersections are Bendplatz and Frankenburg.
LOCATIONS: dict[int, str] = {1: "Bendplatz", 2: "Frankenburg", 3: "Heckstrasse", 4: "Neukoellner Strasse"}
FOUR_WAY_RECORDINGS: dict[int, tuple[int, ...]] = {1: tuple(range(7, 18)), 2: tuple(range(18, 30))}

FILE_KINDS: tuple[str, ...] = ("tracks", "tracksMeta", "recordingMeta")
# Highest recording number accepted on the command line (inD has 33; "0-99999999999" must not
# build a list of 10^11 numbers).
MAX_RECORDING = 999


class IndDataError(ValueError):
    """An inD recording that does not match the published format or the requested site."""


def recording_file(data_dir: str | Path, recording_id: int, kind: str) -> Path:
    """Path of one file of a recording.

    :param data_dir: folder holding the CSV files (inD's ``data/`` folder)
    :param recording_id: recording number, e.g. ``7`` for ``07_tracks.csv``
    :param kind: one of ``"tracks"``, ``"tracksMeta"``, ``"recordingMeta"``
    :return: ``data_dir / f"{recording_id:02d}_{kind}.csv"``
    """
    if kind not in FILE_KINDS:
        raise ValueError(f"kind must be one of {FILE_KINDS}, got {kind!r}")
    return Path(data_dir) / f"{int(recording_id):02d}_{kind}.csv"


def parse_recordings(text: str) -> list[int]:
    """Recording numbers from a command-line list such as ``"07-17"`` or ``"7,9,18-20"``.

    :param text: comma-separated numbers and inclusive ranges ``a-b``
    :return: sorted, distinct recording numbers
    """
    ids: set[int] = set()
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        bounds = part.split("-")
        try:
            numbers = [int(b) for b in bounds]
        except ValueError:
            raise ValueError(f"recordings: {part!r} is not a number or a range like 07-17") from None
        if any(n > MAX_RECORDING for n in numbers):
            raise ValueError(f"recordings: {part!r} goes beyond recording {MAX_RECORDING}")
        if len(numbers) == 1:
            ids.add(numbers[0])
        elif len(numbers) == 2 and numbers[0] <= numbers[1]:
            ids.update(range(numbers[0], numbers[1] + 1))
        else:
            raise ValueError(f"recordings: {part!r} is not a number or an increasing range like 07-17")
    if not ids or min(ids) < 0:
        raise ValueError(f"recordings: expected non-negative numbers such as 07-17, got {text!r}")
    return sorted(ids)


def location_of_recordings(recording_ids: list[int]) -> int | None:
    """The four-way site whose published recording numbers contain all of ``recording_ids``.

    :param recording_ids: recording numbers
    :return: the ``locationId`` (1 Bendplatz, 2 Frankenburg), or ``None`` if no single four-way site
    """
    for location, ids in FOUR_WAY_RECORDINGS.items():
        if set(recording_ids) <= set(ids):
            return location
    return None
