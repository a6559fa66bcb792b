"""What the recorded drivers did: stop ratio per maneuver and road priority, and vehicle counts.

These are the dataset's column of the final comparison (paper, Fig. "ind_turn_stops"): a
recorded vehicle *stopped* when its speed fell below ``STOP_SPEED`` (0.3 m/s) in any frame of its
track. Only mapped vehicles count, so every column of the comparison covers the same vehicles;
the tracks left out are reported with their reasons next to the table.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from envs.ind.loader import Recording
from envs.ind.mapping import MappedTracks
from envs.simulation.scene import MANEUVERS, PRIORITY_NAMES

CATEGORIES: tuple[str, ...] = (
    "all",
    *PRIORITY_NAMES[::-1],
    *MANEUVERS,
)  # all, major, minor, left, straight, right
DATASET_NAME = "inD"


def stop_table(mapped: MappedTracks) -> pd.DataFrame:
    """Vehicles and stops of the recorded drivers, overall, per road priority and per maneuver.

    :param mapped: the mapping of the recordings
    :return: indexed by category (``all``, ``major``, ``minor``, ``left``, ``straight``, ``right``),
        columns ``vehicles``, ``stopped``, ``stop_ratio`` (NaN where there are no vehicles)
    """
    rows = mapped.mapped
    stopped = rows["stopped"].astype(bool)
    by_priority = stopped.groupby(rows["priority"]).agg(["size", "sum"])
    by_maneuver = stopped.groupby(rows["maneuver"]).agg(["size", "sum"])
    table = pd.concat(
        [
            pd.DataFrame({"size": [len(rows)], "sum": [int(stopped.sum())]}, index=["all"]),
            by_priority,
            by_maneuver,
        ]
    )
    table = table.reindex(list(CATEGORIES), fill_value=0).astype(int)
    table.columns = ["vehicles", "stopped"]
    table["stop_ratio"] = table["stopped"] / table["vehicles"].where(table["vehicles"] > 0)
    table.index.name = "category"
    return table


def per_recording(mapped: MappedTracks, recordings: Sequence[Recording]) -> pd.DataFrame:
    """One row per recording, like the evaluation harness's one row per run.

    :param mapped: the mapping of ``recordings``
    :param recordings: the recordings (for their durations)
    :return: columns ``planner`` (``"inD"``), ``run`` (recording number), ``duration_s``,
        ``vehicles``, ``flow_rate`` (mapped vehicles per second of recording), ``collision_rate``
        (NaN: recorded drivers are not judged), ``stop_ratio_<category>`` and ``vehicles_<category>``
    """
    rows = []
    for recording in recordings:
        part = MappedTracks(
            mapped.tracks[mapped.tracks["recording"] == recording.recording_id],
            mapped.arms,
            mapped.centre,
            mapped.centre_estimated,
            mapped.options,
        )
        table = stop_table(part)
        row = {
            "planner": DATASET_NAME,
            "run": recording.recording_id,
            "duration_s": recording.duration,
            "vehicles": int(table.loc["all", "vehicles"]),
            "flow_rate": table.loc["all", "vehicles"] / recording.duration
            if recording.duration > 0
            else np.nan,
            "collision_rate": np.nan,
        }
        row.update({f"stop_ratio_{c}": table.loc[c, "stop_ratio"] for c in CATEGORIES})
        row.update({f"vehicles_{c}": int(table.loc[c, "vehicles"]) for c in CATEGORIES})
        rows.append(row)
    return pd.DataFrame(rows)


def _none_if_nan(value: float) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)


def dataset_summary(mapped: MappedTracks, recordings: Sequence[Recording]) -> dict:
    """The dataset's entry of ``summary.json``, in the evaluation harness's schema plus counts.

    :param mapped: the mapping of ``recordings``
    :param recordings: the recordings
    :return: ``{"runs", "vehicles", "flow_rate": {"median", "q1", "q3", "mean"}, "stop_ratio":
        {category: ratio}, "collision_rate": None, "delay_s": None, "stopped": {category: count},
        "vehicles_by": {category: count}, "unmapped": {reason: count} (vehicle tracks only),
        "not_modelled": {class: count} (pedestrians, bicycles, ...),
        "duration_s": total}``
    """
    table = stop_table(mapped)
    runs = per_recording(mapped, recordings)
    flow = runs["flow_rate"].astype(float)
    not_modelled: dict[str, int] = {}
    for recording in recordings:
        for cls, n in recording.not_modelled.items():
            not_modelled[cls] = not_modelled.get(cls, 0) + n
    return {
        "runs": len(recordings),
        "vehicles": int(table.loc["all", "vehicles"]),
        "flow_rate": {
            "median": _none_if_nan(flow.median()),
            "q1": _none_if_nan(flow.quantile(0.25)),
            "q3": _none_if_nan(flow.quantile(0.75)),
            "mean": _none_if_nan(flow.mean()),
        },
        "stop_ratio": {c: _none_if_nan(table.loc[c, "stop_ratio"]) for c in CATEGORIES},
        "collision_rate": None,
        "delay_s": None,
        "stopped": {c: int(table.loc[c, "stopped"]) for c in CATEGORIES},
        "vehicles_by": {c: int(table.loc[c, "vehicles"]) for c in CATEGORIES},
        "unmapped": {
            str(k): int(v) for k, v in mapped.reasons().items() if not str(k).startswith("not modelled")
        },
        "not_modelled": not_modelled,
        "duration_s": float(sum(r.duration for r in recordings)),
    }
