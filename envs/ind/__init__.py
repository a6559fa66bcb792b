"""Real-world traffic from the inD dataset: load recordings, map tracks, measure recorded drivers.

No inD data ships with the project (its licence forbids it): point the ``sb3-graph ind`` command
at a licensed copy (see ``docs/ind.md``). :mod:`envs.ind.synthetic` writes small made-up
recordings in the same file format for tests and examples.

>>> from envs.ind import load_recordings, map_recordings, stop_table
>>> recordings = load_recordings("/path/to/inD/data", range(7, 18), location_id=1)  # doctest: +SKIP
>>> mapped = map_recordings(recordings)  # doctest: +SKIP
>>> stop_table(mapped)  # doctest: +SKIP
"""

from envs.ind.dataset_metrics import dataset_summary, per_recording, stop_table
from envs.ind.format import IndDataError, parse_recordings
from envs.ind.loader import Recording, class_table, load_recording, load_recordings
from envs.ind.mapping import (
    LayoutArms,
    MappedTracks,
    MappingOptions,
    align_arms,
    layout_arms,
    map_recordings,
    scenario_records,
)

__all__ = [
    "IndDataError",
    "LayoutArms",
    "MappedTracks",
    "MappingOptions",
    "Recording",
    "align_arms",
    "class_table",
    "dataset_summary",
    "layout_arms",
    "load_recording",
    "load_recordings",
    "map_recordings",
    "parse_recordings",
    "per_recording",
    "scenario_records",
    "stop_table",
]
