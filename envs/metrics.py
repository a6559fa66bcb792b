"""Traffic metrics of a run: flow rate, stop ratios, collision rate, delay and travel time.

A run's vehicles are collected into a *vehicle log* (one row per vehicle, :data:`VEHICLE_COLUMNS`)
from the environment's step ``info`` (see :mod:`envs.scene`) and the scenes the planner saw.

Which vehicles count (the same rule for every planner):

- **stop ratio** and **collision rate**: every vehicle that was in the scene at some point of
  the run, including those still approaching when the run ends (a queue that never cleared is
  exactly what the stop ratio must show);
- **flow rate**: vehicles that crossed the intersection (left its area, ``info["crossed"]``)
  during the run, divided by the simulated duration of the run;
- **travel time** and **delay**: vehicles that crossed during the run. Travel time runs from the
  first scene the vehicle appears in to the step in which its centre left the intersection
  area; its free-flow time is the distance its centre drove in that interval at the speed limit
  of the lane it was first seen on. Delay = travel time - free-flow time.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import pandas as pd

from envs.scene import MANEUVERS, PRIORITY_NAMES, Scene

VEHICLE_COLUMNS = (
    "vehicle_id",
    "route",
    "priority",
    "maneuver",
    "first_seen",
    "path_length",
    "speed_limit",
    "crossed",
    "removed",
    "stopped",
    "collided",
)
PRIORITIES = ("major", "minor")
STOP_GROUPS = ("all",) + PRIORITIES + tuple(MANEUVERS)


class VehicleLog:
    """Collects one run's per-vehicle facts, step by step.

    Call :meth:`observe` with every scene the planner sees and :meth:`record` with every step
    ``info``; :meth:`frame` returns the vehicle log.
    """

    def __init__(self) -> None:
        self._rows: dict[int, dict[str, Any]] = {}

    def _row(self, vid: int) -> dict[str, Any]:
        row = self._rows.get(vid)
        if row is None:
            row = dict.fromkeys(VEHICLE_COLUMNS, np.nan)
            row.update(vehicle_id=vid, route="", priority="", maneuver="", stopped=False, collided=False)
            self._rows[vid] = row
        return row

    def observe(self, scene: Scene) -> None:
        """Register the vehicles of a scene (their static facts are taken the first time).

        :param scene: the vehicles now
        """
        ids = scene.vehicle_id
        new = [
            k
            for k, vid in enumerate(ids.tolist())
            if vid not in self._rows
            or self._rows[vid]["route"] == ""
            or np.isnan(self._rows[vid]["first_seen"])
        ]
        for k in new:  # once per vehicle, not per step
            row = self._row(int(ids[k]))
            row.update(
                route=scene.route_names[int(scene.route[k])],
                priority=PRIORITY_NAMES[int(scene.priority[k])],
                maneuver=MANEUVERS[int(scene.maneuver[k])],
                first_seen=float(scene.time),
                # the centre crosses the exit (info "crossed"); dist_to_exit is from the rear
                path_length=float(max(scene.dist_to_exit[k] - 0.5 * scene.length[k], 0.0)),
                speed_limit=float(scene.speed_limit[k]),
            )
        if len(ids):
            stopped_now = scene.speed < _stop_speed()
            for vid in ids[stopped_now].tolist():
                self._rows[int(vid)]["stopped"] = True

    def record(self, info: Mapping[str, Any]) -> None:
        """Register the events of one environment step.

        :param info: the step ``info`` (keys documented in :mod:`envs.scene`)
        """
        time = float(info.get("time", np.nan))
        meta = info.get("vehicles", {}) or {}
        for vid in info.get("entered", ()):
            row = self._row(int(vid))
            facts = meta.get(vid, meta.get(int(vid), {}))
            if facts and not row["route"]:
                row["route"] = str(facts.get("route", ""))
                priority = facts.get("priority", "")
                row["priority"] = PRIORITY_NAMES[int(priority)] if not isinstance(priority, str) else priority
                row["maneuver"] = str(facts.get("maneuver", ""))
        for vid in info.get("crossed", ()):
            row = self._row(int(vid))
            if np.isnan(row["crossed"]):
                row["crossed"] = time
        for vid in info.get("removed", ()):
            self._row(int(vid))["removed"] = time
        for vid in info.get("stopped", ()):
            self._row(int(vid))["stopped"] = True
        collisions = np.asarray(info.get("collisions", np.zeros((0, 2))), dtype=np.int64).reshape(-1)
        for vid in collisions.tolist():
            self._row(int(vid))["collided"] = True

    def frame(self) -> pd.DataFrame:
        """The vehicle log: one row per vehicle, columns :data:`VEHICLE_COLUMNS`."""
        return vehicle_frame(self._rows.values())


def _stop_speed() -> float:
    from envs.scene import STOP_SPEED

    return STOP_SPEED


def vehicle_frame(rows: Iterable[Mapping[str, Any]]) -> pd.DataFrame:
    """Build a vehicle log from row dictionaries (missing columns become NaN/False).

    :param rows: one mapping per vehicle with keys from :data:`VEHICLE_COLUMNS`
    :return: the vehicle log with proper dtypes
    """
    frame = pd.DataFrame(list(rows), columns=list(VEHICLE_COLUMNS))
    for column in ("first_seen", "path_length", "speed_limit", "crossed", "removed"):
        frame[column] = frame[column].astype(float)
    for column in ("stopped", "collided"):
        frame[column] = frame[column].fillna(False).astype(bool)
    frame["vehicle_id"] = frame["vehicle_id"].astype(np.int64)
    return frame


def add_travel_times(vehicles: pd.DataFrame) -> pd.DataFrame:
    """Add ``travel_time`` and ``delay`` columns [s] (NaN for vehicles that did not cross).

    :param vehicles: a vehicle log
    :return: a copy with the two columns
    """
    out = vehicles.copy()
    crossed = out["crossed"].notna() & out["first_seen"].notna()
    travel = np.where(crossed, out["crossed"] - out["first_seen"], np.nan)
    free = out["path_length"] / out["speed_limit"].where(out["speed_limit"] > 0)
    out["travel_time"] = travel
    out["delay"] = np.where(crossed, travel - free, np.nan)
    return out


def stop_counts(vehicles: pd.DataFrame) -> dict[str, tuple[int, int]]:
    """Vehicles and stopped vehicles per group (``all``, ``major``, ``minor``, maneuvers).

    :param vehicles: a vehicle log
    :return: ``group -> (vehicles, stopped)``
    """
    counts = {"all": (len(vehicles), int(vehicles["stopped"].sum()))}
    for column, groups in (("priority", PRIORITIES), ("maneuver", MANEUVERS)):
        for group in groups:
            sub = vehicles[vehicles[column] == group]
            counts[group] = (len(sub), int(sub["stopped"].sum()))
    return counts


def _ratio(stopped: int, total: int) -> float:
    return float(stopped / total) if total else float("nan")


def run_metrics(vehicles: pd.DataFrame, duration: float) -> dict[str, float | int]:
    """Metrics of one run (one row of ``metrics.csv``).

    :param vehicles: the run's vehicle log
    :param duration: simulated duration of the run [s]
    :return: ``duration_s, vehicles, crossed, flow_rate`` [veh/s], ``stop_ratio_<group>`` and
        ``vehicles_<group>`` for every group of :data:`STOP_GROUPS`, ``collided``,
        ``collision_rate``, ``delay_mean``, ``delay_median``, ``travel_time_mean`` [s]
    """
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    timed = add_travel_times(vehicles)
    crossed = int(vehicles["crossed"].notna().sum())
    row: dict[str, float | int] = {
        "duration_s": float(duration),
        "vehicles": len(vehicles),
        "crossed": crossed,
        "flow_rate": crossed / duration,
    }
    for group, (total, stopped) in stop_counts(vehicles).items():
        row[f"vehicles_{group}"] = total
        row[f"stopped_{group}"] = stopped
        row[f"stop_ratio_{group}"] = _ratio(stopped, total)
    collided = int(vehicles["collided"].sum())
    row["collided"] = collided
    row["collision_rate"] = _ratio(collided, len(vehicles)) if len(vehicles) else 0.0
    delays = timed["delay"].dropna()
    row["delay_mean"] = float(delays.mean()) if len(delays) else float("nan")
    row["delay_median"] = float(delays.median()) if len(delays) else float("nan")
    travel = timed["travel_time"].dropna()
    row["travel_time_mean"] = float(travel.mean()) if len(travel) else float("nan")
    return row


def summarize(runs: pd.DataFrame, vehicles: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """Aggregate over runs, per planner (the ``summary.json`` schema).

    Flow-rate statistics are over runs; stop ratios, collision rate and delay are pooled over
    all vehicles of the planner's runs.

    :param runs: ``metrics.csv`` rows with a ``planner`` column
    :param vehicles: all vehicle logs with a ``planner`` column
    :return: ``planner -> {"runs", "vehicles", "flow_rate": {median, q1, q3, mean},
        "stop_ratio": {all, major, minor, left, straight, right}, "collision_rate",
        "delay_s": {median, mean}}``
    """
    summary: dict[str, dict[str, Any]] = {}
    for planner in pd.unique(runs["planner"]):
        r = runs[runs["planner"] == planner]
        v = add_travel_times(vehicles[vehicles["planner"] == planner])
        flow = r["flow_rate"].astype(float)
        counts = stop_counts(v)
        delays = v["delay"].dropna()
        summary[str(planner)] = {
            "runs": len(r),
            "vehicles": len(v),
            "flow_rate": {
                "median": _finite(flow.median()),
                "q1": _finite(flow.quantile(0.25)),
                "q3": _finite(flow.quantile(0.75)),
                "mean": _finite(flow.mean()),
            },
            "stop_ratio": {group: _finite(_ratio(s, t)) for group, (t, s) in counts.items()},
            "collision_rate": _finite(_ratio(int(v["collided"].sum()), len(v))) if len(v) else 0.0,
            "delay_s": {
                "median": _finite(delays.median()) if len(delays) else None,
                "mean": _finite(delays.mean()) if len(delays) else None,
            },
        }
    return summary


def _finite(value: float) -> float | None:
    """JSON has no NaN: undefined values (empty groups) become ``None``."""
    value = float(value)
    return value if np.isfinite(value) else None
