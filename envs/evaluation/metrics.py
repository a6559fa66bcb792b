"""Traffic metrics of a run: flow rate, stop ratios, collision rate, delay and travel time.

A run's vehicles are collected into a *vehicle log* (one row per vehicle, :data:`VEHICLE_COLUMNS`)
from the scenes the planner saw (what each vehicle is: route, priority, maneuver, where it started),
the environment's step records (what happened to it: :class:`envs.simulation.step_record.StepRecord`) and the
scenario's schedule.

Which vehicles count: **every scheduled vehicle**, the same set for every planner. A vehicle of
the scenario whose scheduled appearance time falls within the run is in the log even if it never
entered the scene (its lane was jammed back to the spawn point; ``spawned`` is False): it counts
in every denominator, as stopped, with the delay it has accumulated (below). So a planner cannot
look better by keeping vehicles out of the scene.

- **stop ratio** and **collision rate**: over all scheduled vehicles (including those still
  approaching, or still waiting to appear, when the run ends);
- **flow rate** (the paper's): vehicles of that set that crossed the intersection (their centre
  left its area, ``StepRecord.crossed``) during the run, divided by the simulated duration.
  ``offered_flow`` is the flow a perfect planner could reach on the same scenario: the scheduled
  vehicles that would cross before the end of the run in free flow, per simulated second;
- **delay**: from the *scheduled* appearance time (not the first appearance), against the
  free-flow time of :mod:`envs.simulation.free_flow` (lane speed limits along the route, the environment's
  acceleration bounds, from the scheduled initial speed at the spawn point). For a vehicle that
  crossed: ``crossed - scheduled - free_flow``. A vehicle that had not crossed when its record
  ended (end of the run, or removal after a collision: ``censored``) gets the delay it has
  accumulated so far, ``censored - scheduled - free_flow_covered``, where ``free_flow_covered``
  is the free-flow time of the distance it did cover (0 for a vehicle that never appeared, whose
  delay is then the time from its scheduled appearance to the end of the run). That is a lower
  bound of the delay it will have when it crosses, so saturated planners are, if anything,
  flattered; never rewarded for a queue.
- **travel time**: vehicles that crossed, from the scheduled appearance to the crossing.
- **mixed traffic**: ``human`` marks a human-driven vehicle (``Scene.human``; the
  schedule's flag for one that never appeared). :func:`run_metrics` repeats the flow rate, mean
  delay, stop ratio and collided vehicles for automated and for human vehicles
  (``flow_rate_automated``, ``delay_mean_human`` ...). ``collisions_human`` counts the vehicles of
  collisions with a human driver in them (``collided_with_human``; a human ignores the planner's
  gaps), ``collisions_automated`` those of collisions between automated vehicles only (the
  planner's and the shield's own).
- **speed-limit violations**: vehicle-steps (scenes the planner answered) in which a vehicle
  drove faster than its lane's limit by more than :data:`SPEED_TOLERANCE`.
- **slow ratio**, **hard brakes per vehicle** and **energy per vehicle** (:func:`motion_metrics`), from the
  executed motion that the step records carry (every simulation sub-step, after the governor and the
  shield; definitions and the energy model in :mod:`envs.simulation.motion`):

  - ``slow_ratio``: scheduled vehicles whose lowest speed (``min_speed``) was below
    :data:`~envs.simulation.motion.SLOW_SPEED` (2 m/s), over all scheduled vehicles; a vehicle that never
    appeared stands (``min_speed`` 0). Every stopped vehicle is slow, so ``slow_ratio >= stop_ratio_all``;
  - ``hard_brakes_per_vehicle``: hard-braking events (maximal runs of consecutive sub-steps whose
    acceleration was below :data:`~envs.simulation.motion.HARD_BRAKE_ACCELERATION`, -3 m/s^2, by more than
    :data:`~envs.simulation.motion.HARD_BRAKE_MARGIN`) over all scheduled vehicles;
  - ``energy_kj_per_vehicle``: mean traction energy [kJ] of the vehicles that crossed, from their appearance
    to the end of the policy step in which they crossed (``traction_energy_j``): the same stretch of road for
    every planner. Vehicles that did not cross are left out (their energy so far would flatter a jam), as
    from ``travel_time_mean``.

The environment appears vehicles and reports crossings at policy steps (0.2 s by default), so a
delay includes up to one step of appearance and one of crossing quantization, the same for
every planner. Logs without a schedule or a layout (hand-built scenes, recorded drivers) fall
back to the first appearance and to ``path_length / speed_limit`` for the free-flow time, and
have delays for crossed vehicles only.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from envs.simulation.free_flow import free_flow_table, time_at
from envs.simulation.motion import SLOW_SPEED, event_starts, hard_braking, traction_energy
from envs.simulation.scene import MANEUVERS, PRIORITY_NAMES, STOP_SPEED, Scene
from envs.simulation.step_record import StepRecord, step_record

if TYPE_CHECKING:
    from envs.simulation.layouts import Layout
    from envs.simulation.traffic import Scenario

VEHICLE_COLUMNS = (
    "vehicle_id",
    "route",
    "priority",
    "maneuver",
    "scheduled",
    "spawned",
    "first_seen",
    "path_length",
    "speed_limit",
    "crossed",
    "removed",
    "censored",
    "free_flow",
    "free_flow_covered",
    "stopped",
    "collided",
    "speed_violations",
    "steps",
    "governed_steps",
    "min_speed",
    "hard_brakes",
    "traction_energy_j",
    "human",
    "collided_with_human",
)
# Mixed traffic: the main figures again for each kind of driver (``<figure>_<kind>``).
DRIVER_KINDS = ("automated", "human")
PRIORITIES = ("major", "minor")
STOP_GROUPS = ("all",) + PRIORITIES + tuple(MANEUVERS)
# A vehicle faster than its lane's limit by more than this [m/s] violates it.
SPEED_TOLERANCE = 0.1
# The liveness watchdog: a run is *stuck* when for this long no vehicle crossed the intersection while
# some vehicle waited to (appeared, or was due to appear, and had neither crossed nor left) [s].
STANDSTILL_LIMIT = 30.0
_FLOAT_COLUMNS = (
    "scheduled", "first_seen", "path_length", "speed_limit", "crossed", "removed", "censored",
    "free_flow", "free_flow_covered", "min_speed", "hard_brakes", "traction_energy_j",
)  # fmt: skip


class VehicleLog:
    """Collects one run's per-vehicle facts, step by step.

    Call :meth:`observe` with every scene the planner sees, :meth:`record` with the record of every
    environment step (``reset`` included) and :meth:`finish` with the last scene; :meth:`frame`
    returns the vehicle log. A vehicle's static facts come from the first scene it is in, its events
    from the records: each fact has one source.

    :param layout: the intersection (needed for free-flow times and unspawned vehicles; without
        it the log falls back as described in the module docstring)
    """

    def __init__(self, layout: Layout | None = None) -> None:
        self.layout = layout
        self._rows: dict[int, dict[str, Any]] = {}
        self._seen = np.zeros(0, np.int64)  # ids already registered from a scene
        # Per scene: ids, centre arc lengths, speeding flags (reduced in frame(), not per vehicle).
        self._trace: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._stopped: list[np.ndarray] = []
        self._counted: list[np.ndarray] = []  # ids of each scene the planner answered
        self._governed: list[np.ndarray] = []  # ids the speed governor held back, per step
        # The executed motion, per scene or step (reduced in frame()): (ids, lowest speeds) of every scene and
        # step, (ids repeated per sub-step, hard-braking flags) and (ids, traction energy, record time) per step.
        self._lowest: list[tuple[np.ndarray, np.ndarray]] = []
        self._braking: list[tuple[np.ndarray, np.ndarray]] = []
        self._energy: list[tuple[np.ndarray, np.ndarray, float]] = []
        self._bounds = (5.0, 5.0)  # acceleration, deceleration of the free-flow reference

    def _row(self, vid: int) -> dict[str, Any]:
        row = self._rows.get(vid)
        if row is None:
            row = dict.fromkeys(VEHICLE_COLUMNS, np.nan)
            row.update(
                vehicle_id=vid, route="", priority="", maneuver="", spawned=True, stopped=False, collided=False,
                speed_violations=0, steps=0, governed_steps=0, route_index=-1, start_arc=np.nan, start_speed=np.nan,
                human=False, collided_with_human=False,
            )  # fmt: skip
            self._rows[vid] = row
        return row

    def observe(self, scene: Scene, count: bool = True) -> None:
        """Register the vehicles of a scene (their static facts, the only source of route, priority and
        maneuver, are taken the first time).

        :param scene: the vehicles now
        :param count: count stops and speed-limit violations in this scene (a scene the planner answers)
        """
        ids = scene.vehicle_id
        if not self._trace:
            self._bounds = (float(scene.a_max), float(-scene.a_min))
        arc = scene.arc if scene.arc is not None else np.full(len(ids), np.nan)
        new = np.flatnonzero(~np.isin(ids, self._seen))
        self._seen = np.concatenate([self._seen, ids[new]])
        human = scene.humans
        for k in new.tolist():  # once per vehicle, not per step
            row = self._row(int(ids[k]))
            row.update(
                route=scene.route_names[int(scene.route[k])],
                priority=PRIORITY_NAMES[int(scene.priority[k])],
                maneuver=MANEUVERS[int(scene.maneuver[k])],
                first_seen=float(scene.time),
                # the centre crosses the exit (StepRecord.crossed); dist_to_exit is from the rear
                path_length=float(max(scene.dist_to_exit[k] - 0.5 * scene.length[k], 0.0)),
                speed_limit=float(scene.speed_limit[k]),
                route_index=int(scene.route[k]),
                start_arc=float(arc[k]),
                start_speed=float(scene.speed[k]),
                human=bool(human[k]),
            )
        speeding = np.zeros(len(ids), bool)
        self._lowest.append((ids.copy(), np.asarray(scene.speed, float).copy()))
        if count and len(ids):
            self._stopped.append(ids[scene.speed < STOP_SPEED])
            self._counted.append(ids.copy())
            speeding = scene.speed > scene.speed_limit + SPEED_TOLERANCE
        self._trace.append((ids.copy(), np.asarray(arc, float).copy(), speeding))

    def finish(self, scene: Scene) -> None:
        """Register the last scene of the run: positions and new vehicles, no stops or violations.

        :param scene: the vehicles at the end of the run
        """
        self.observe(scene, count=False)

    def record(self, record: StepRecord | Mapping[str, Any]) -> None:
        """Register the events of one environment step.

        :param record: the step's record, or the step ``info`` that carries it (``info["record"]``)
        """
        if not isinstance(record, StepRecord):
            record = step_record(record)
        time = float(record.time)
        for vid in record.crossed.tolist():
            row = self._row(vid)
            if np.isnan(row["crossed"]):
                row["crossed"] = time
        for vid in record.removed.tolist():
            self._row(vid)["removed"] = time
        for vid in record.stopped.tolist():
            self._row(vid)["stopped"] = True
        self._governed.append(record.governed)
        for vid in record.collisions.reshape(-1).tolist():
            self._row(vid)["collided"] = True
        for a, b in record.collisions.reshape(-1, 2).tolist():  # once per collision
            if self._row(a)["human"] or self._row(b)["human"]:
                self._row(a)["collided_with_human"] = self._row(b)["collided_with_human"] = True
        if record.has_motion:
            self._record_motion(record)

    def _record_motion(self, record: StepRecord) -> None:
        """Keep what the metrics need of a step's executed sub-step speeds (vectorized over its vehicles)."""
        ids, speeds, h = record.moved, record.speeds, float(record.substep)
        self._lowest.append((ids, speeds.min(axis=0)))
        hard = hard_braking(np.diff(speeds, axis=0) / h).T.ravel()  # vehicle-major, in time order
        self._braking.append((np.repeat(ids, speeds.shape[0] - 1), hard))
        self._energy.append((ids, traction_energy(speeds[:-1], speeds[1:], h).sum(axis=0), float(record.time)))

    def frame(self, schedule: Scenario | None = None, end: float | None = None) -> pd.DataFrame:
        """The vehicle log: one row per vehicle, columns :data:`VEHICLE_COLUMNS`.

        :param schedule: the scenario the run replayed: adds the scheduled times, and a row for
            every vehicle scheduled up to ``end`` that never appeared
        :param end: simulated time at which the run ended [s] (censors the vehicles that did not cross)
        :return: the vehicle log
        """
        rows = pd.DataFrame(list(self._rows.values()))
        if rows.empty:
            rows = pd.DataFrame(columns=[*VEHICLE_COLUMNS, "route_index", "start_arc", "start_speed"])
        rows = rows.astype({"route_index": np.int64, "start_arc": float, "start_speed": float})
        ids = rows["vehicle_id"].to_numpy(np.int64)
        rows["end_arc"] = np.nan
        if self._trace:
            seen = np.concatenate([t[0] for t in self._trace])
            arcs = np.concatenate([t[1] for t in self._trace])
            speeding = np.concatenate([t[2] for t in self._trace])
            stopped = np.concatenate(self._stopped) if self._stopped else np.zeros(0, np.int64)
            rows["stopped"] = rows["stopped"].astype(bool) | np.isin(ids, stopped)
            fast, counts = np.unique(seen[speeding], return_counts=True)
            rows["speed_violations"] = pd.Series(counts, index=fast).reindex(ids, fill_value=0).to_numpy()
            for column, parts in (("steps", self._counted), ("governed_steps", self._governed)):
                found, counts = np.unique(np.concatenate(parts) if parts else np.zeros(0, np.int64), return_counts=True)
                rows[column] = pd.Series(counts, index=found).reindex(ids, fill_value=0).to_numpy()
            last, where = np.unique(seen[::-1], return_index=True)  # the last scene of each vehicle
            rows["end_arc"] = pd.Series(arcs[::-1][where], index=last).reindex(ids).to_numpy()
        self._motion_columns(rows)
        if schedule is not None and end is not None and self.layout is not None:
            rows = self._add_schedule(rows, schedule, float(end))
        return self._reference(rows, end)

    def _motion_columns(self, rows: pd.DataFrame) -> None:
        """Add ``min_speed``, ``hard_brakes`` and ``traction_energy_j`` (in place; NaN where unknown: the
        two motion columns of a log whose records carry no sub-step speeds)."""
        ids = rows["vehicle_id"].to_numpy(np.int64)
        rows["min_speed"] = np.nan
        rows["hard_brakes"] = np.nan
        rows["traction_energy_j"] = np.nan
        if self._lowest:
            seen = np.concatenate([x[0] for x in self._lowest])
            lowest = pd.Series(np.concatenate([x[1] for x in self._lowest])).groupby(seen).min()
            rows["min_speed"] = lowest.reindex(ids).to_numpy()
        if not self._energy:
            return
        vehicle = np.concatenate([x[0] for x in self._braking])
        order = np.argsort(vehicle, kind="stable")  # each vehicle's sub-steps together, in time order
        starts = event_starts(np.concatenate([x[1] for x in self._braking])[order], vehicle[order])
        found, counts = np.unique(vehicle[order][starts], return_counts=True)
        rows["hard_brakes"] = pd.Series(counts, index=found).reindex(ids, fill_value=0).to_numpy(float)
        moved = np.concatenate([x[0] for x in self._energy])
        energy = np.concatenate([x[1] for x in self._energy])
        time = np.concatenate([np.full(len(x[0]), x[2]) for x in self._energy])
        crossed = pd.Series(rows["crossed"].to_numpy(float), index=ids)
        before = time <= crossed.reindex(moved).to_numpy()  # up to the step of the crossing (NaN: never)
        to_exit = pd.Series(energy[before]).groupby(moved[before]).sum()
        rows["traction_energy_j"] = np.where(rows["crossed"].notna(), to_exit.reindex(ids, fill_value=0.0), np.nan)

    def _add_schedule(self, rows: pd.DataFrame, schedule: Scenario, end: float) -> pd.DataFrame:
        """Scheduled times for every row, and rows for the vehicles due by ``end`` that never appeared."""
        lay = self.layout
        times = pd.Series(schedule.time, index=schedule.vehicle_id)
        rows["scheduled"] = rows["vehicle_id"].map(times).astype(float)
        missing = (schedule.time <= end + 1e-9) & ~np.isin(schedule.vehicle_id, rows["vehicle_id"].to_numpy())
        if not missing.any():
            return rows
        names, inverse = np.unique(np.asarray(schedule.route)[missing], return_inverse=True)
        route = np.array([lay.route_id(n) for n in names], np.int64)[inverse]  # a loop over route names
        start = schedule.length[missing] / 2  # where the simulation places a new vehicle's centre
        waiting = pd.DataFrame(
            {
                "vehicle_id": schedule.vehicle_id[missing],
                "route": np.asarray(lay.route_names, dtype=object)[route],
                "priority": np.asarray(PRIORITY_NAMES, dtype=object)[lay.priority[route]],
                "maneuver": np.asarray(MANEUVERS, dtype=object)[lay.maneuver[route]],
                "scheduled": schedule.time[missing],
                "spawned": False,
                "stopped": True,  # it stands at (behind) the spawn point
                "collided": False,
                "speed_violations": 0,
                "steps": 0,
                "governed_steps": 0,
                "min_speed": 0.0,  # it stands
                "hard_brakes": 0.0 if self._energy else np.nan,
                "traction_energy_j": np.nan,
                "human": schedule.human[missing],
                "collided_with_human": False,
                "route_index": route,
                "start_arc": start,
                "start_speed": schedule.speed[missing],
                "end_arc": start,
            }
        )
        return pd.concat([rows, waiting], ignore_index=True)

    def _reference(self, rows: pd.DataFrame, end: float | None) -> pd.DataFrame:
        """Add ``censored``, ``free_flow`` and ``free_flow_covered``; return the vehicle log."""
        not_crossed = rows["crossed"].isna()
        if end is not None:
            rows["censored"] = np.where(not_crossed, rows["removed"].fillna(float(end)), np.nan)
        known = (rows["route_index"] >= 0) & rows["start_arc"].notna() & rows["start_speed"].notna()
        if self.layout is not None and known.any():
            lay, sub = self.layout, rows[known]
            route = sub["route_index"].to_numpy(np.int64)
            start = sub["start_arc"].to_numpy(float)
            table = free_flow_table(lay, route, start, sub["start_speed"].to_numpy(float), *self._bounds)
            to_exit = time_at(table, lay.exit_arc[route] - start, lay.ds)
            covered = time_at(table, sub["end_arc"].to_numpy(float) - start, lay.ds)
            rows.loc[known, "free_flow"] = to_exit
            rows.loc[known, "free_flow_covered"] = np.where(sub["crossed"].notna(), to_exit, covered)
        return vehicle_frame(rows.to_dict("records"))


def vehicle_frame(rows: Iterable[Mapping[str, Any]]) -> pd.DataFrame:
    """Build a vehicle log from row dictionaries (missing columns become NaN/False).

    :param rows: one mapping per vehicle with keys from :data:`VEHICLE_COLUMNS`
    :return: the vehicle log with proper dtypes
    """
    frame = pd.DataFrame(list(rows), columns=list(VEHICLE_COLUMNS))
    for column in _FLOAT_COLUMNS:
        frame[column] = frame[column].astype(float)
    for column in ("stopped", "collided", "human", "collided_with_human"):
        frame[column] = frame[column].fillna(False).astype(bool)
    frame["spawned"] = frame["spawned"].fillna(True).astype(bool)
    for column in ("speed_violations", "steps", "governed_steps"):
        frame[column] = frame[column].fillna(0).astype(np.int64)
    frame["vehicle_id"] = frame["vehicle_id"].astype(np.int64)
    return frame


def _column(vehicles: pd.DataFrame, name: str, default: Any = np.nan) -> pd.Series:
    """A column of a vehicle log, or ``default`` for logs written before it existed."""
    if name in vehicles:
        return vehicles[name]
    return pd.Series(default, index=vehicles.index)


def add_travel_times(vehicles: pd.DataFrame) -> pd.DataFrame:
    """Add ``travel_time`` (crossed vehicles) and ``delay`` (every vehicle with a reference) [s].

    :param vehicles: a vehicle log
    :return: a copy with the two columns (definitions in the module docstring)
    """
    out = vehicles.copy()
    start = _column(out, "scheduled").astype(float).fillna(out["first_seen"])
    crossed = out["crossed"].notna()
    fallback = out["path_length"] / out["speed_limit"].where(out["speed_limit"] > 0)
    free = _column(out, "free_flow").astype(float).fillna(fallback)
    covered = np.where(crossed, free, _column(out, "free_flow_covered").astype(float))
    finish = out["crossed"].fillna(_column(out, "censored").astype(float))
    out["travel_time"] = np.where(crossed, out["crossed"] - start, np.nan)
    out["delay"] = finish - start - covered
    return out


def schedule_counts(vehicles: pd.DataFrame) -> dict[str, int]:
    """``vehicles_scheduled`` (rows with a scheduled time) and ``not_spawned`` (rows that never appeared).

    :param vehicles: a vehicle log
    """
    return {
        "vehicles_scheduled": int(_column(vehicles, "scheduled").notna().sum()),
        "not_spawned": int((~_column(vehicles, "spawned", True).astype(bool)).sum()),
    }


def violations(vehicles: pd.DataFrame) -> int:
    """Speed-limit violations of a vehicle log [vehicle-steps]."""
    return int(_column(vehicles, "speed_violations", 0).sum())


def governor_share(vehicles: pd.DataFrame) -> float:
    """Share of the vehicle-steps in which the speed governor held a vehicle below its command
    (NaN without counted steps): how much a planner leans on the physics to keep the limits."""
    steps = int(_column(vehicles, "steps", 0).sum())
    return float(_column(vehicles, "governed_steps", 0).sum() / steps) if steps else float("nan")


def motion_metrics(vehicles: pd.DataFrame) -> dict[str, float]:
    """Crawling, hard braking and energy of a vehicle log (NaN where its vehicles' motion is unknown).

    :param vehicles: a vehicle log (one run, or pooled runs)
    :return: ``slow_ratio`` (share of the vehicles with a known lowest speed whose speed fell below
        :data:`~envs.simulation.motion.SLOW_SPEED`), ``hard_brakes_per_vehicle`` (hard-braking events per
        vehicle with known motion) and ``energy_kj_per_vehicle`` (mean traction energy of the vehicles that
        crossed [kJ]); definitions in the module docstring
    """
    lowest = _column(vehicles, "min_speed").astype(float).dropna()
    brakes = _column(vehicles, "hard_brakes").astype(float).dropna()
    energy = _column(vehicles, "traction_energy_j").astype(float).dropna()
    return {
        "slow_ratio": float((lowest < SLOW_SPEED).mean()) if len(lowest) else float("nan"),
        "hard_brakes_per_vehicle": float(brakes.mean()) if len(brakes) else float("nan"),
        "energy_kj_per_vehicle": float(energy.mean()) / 1000.0 if len(energy) else float("nan"),
    }


def offered_count(vehicles: pd.DataFrame, duration: float) -> float:
    """Scheduled vehicles that would cross within ``duration`` in free flow (NaN without references).

    :param vehicles: a vehicle log of one run that started at time 0
    :param duration: simulated duration of the run [s]
    """
    free = _column(vehicles, "free_flow").astype(float)
    if free.isna().all():
        return float("nan")
    start = _column(vehicles, "scheduled").astype(float).fillna(vehicles["first_seen"])
    return float(((start + free) <= duration + 1e-9).sum())


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


def standstill(vehicles: pd.DataFrame, duration: float, start: float = 0.0) -> tuple[float, float]:
    """The liveness watchdog's reading of one run: the longest time without a crossing while some
    vehicle waited, and the time of the last crossing.

    Between two consecutive crossings (and from the start to the first, from the last to the end) the
    standstill is measured from the later of the interval's start and the earliest appearance (the
    scheduled one if earlier, e.g. a vehicle the jam kept from appearing) among the vehicles still
    waiting at its end.

    :param vehicles: the run's vehicle log
    :param duration: simulated duration of the run [s]
    :param start: simulated time at which the run started [s]
    :return: ``(longest standstill [s], last crossing [s], nan if none)``
    """
    end = start + float(duration)
    crossed = _column(vehicles, "crossed").astype(float).to_numpy()
    removed = _column(vehicles, "removed").astype(float).to_numpy()
    appear = np.fmin(_column(vehicles, "first_seen").astype(float).to_numpy(),
                     _column(vehicles, "scheduled").astype(float).to_numpy())  # fmt: skip
    leave = np.where(np.isnan(crossed), np.where(np.isnan(removed), np.inf, removed), crossed)
    times = np.sort(crossed[np.isfinite(crossed)])
    lo = np.concatenate([[start], times])
    hi = np.concatenate([times, [end]])
    # (intervals, vehicles): waiting at the interval's end, since its appearance
    waiting = (appear[None, :] < hi[:, None]) & (leave[None, :] >= hi[:, None])
    first = np.where(waiting, appear[None, :], np.inf).min(axis=1, initial=np.inf)
    length = np.where(np.isfinite(first), hi - np.maximum(lo, first), 0.0)
    last = float(times[-1]) if times.size else float("nan")
    return float(max(length.max(initial=0.0), 0.0)), last


def run_metrics(vehicles: pd.DataFrame, duration: float) -> dict[str, float | int]:
    """Metrics of one run (one row of ``metrics.csv``).

    :param vehicles: the run's vehicle log
    :param duration: simulated duration of the run [s]
    :return: ``duration_s, vehicles, vehicles_scheduled, not_spawned, crossed, flow_rate`` [veh/s],
        ``offered_flow`` [veh/s], ``stop_ratio_<group>`` and ``vehicles_<group>`` for every group of
        :data:`STOP_GROUPS`, ``collided``, ``collision_rate``, ``delay_mean``, ``delay_median``,
        ``travel_time_mean`` [s], ``speed_limit_violations`` [vehicle-steps], ``governor_share``,
        ``longest_standstill_s``, ``stuck`` (the watchdog, :func:`standstill` against
        :data:`STANDSTILL_LIMIT`), ``last_crossing_s``, and ``slow_ratio``, ``hard_brakes_per_vehicle``,
        ``energy_kj_per_vehicle`` (:func:`motion_metrics`), and for mixed traffic (:func:`driver_metrics`)
        ``vehicles_<kind>``, ``flow_rate_<kind>``, ``delay_mean_<kind>``, ``stop_ratio_<kind>``,
        ``collided_<kind>`` for each kind of :data:`DRIVER_KINDS`, ``collisions_automated``, ``collisions_human``
    """
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    timed = add_travel_times(vehicles)
    crossed = int(vehicles["crossed"].notna().sum())
    row: dict[str, float | int] = {
        "duration_s": float(duration),
        "vehicles": len(vehicles),
        **schedule_counts(vehicles),
        "crossed": crossed,
        "flow_rate": crossed / duration,
        "offered_flow": offered_count(vehicles, duration) / duration,
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
    row["speed_limit_violations"] = violations(vehicles)
    row["governor_share"] = governor_share(vehicles)
    longest, last = standstill(vehicles, duration)
    row["longest_standstill_s"] = longest
    row["stuck"] = bool(longest >= STANDSTILL_LIMIT)
    row["last_crossing_s"] = last
    row.update(motion_metrics(vehicles))
    row.update(driver_metrics(timed, duration))
    return row


def driver_metrics(timed: pd.DataFrame, duration: float) -> dict[str, float | int]:
    """The main figures per kind of driver, and the collisions with and without a human in them.

    :param timed: a vehicle log with ``delay`` (:func:`add_travel_times`)
    :param duration: simulated duration of the run [s]
    :return: see :func:`run_metrics`
    """
    human = _column(timed, "human", False).fillna(False).astype(bool).to_numpy()
    with_human = _column(timed, "collided_with_human", False).fillna(False).astype(bool).to_numpy()
    collided = timed["collided"].to_numpy(bool)
    row: dict[str, float | int] = {}
    for kind, mask in zip(DRIVER_KINDS, (~human, human)):
        part = timed[mask]
        delays = part["delay"].dropna()
        row[f"vehicles_{kind}"] = int(mask.sum())
        row[f"flow_rate_{kind}"] = float(part["crossed"].notna().sum()) / duration
        row[f"delay_mean_{kind}"] = float(delays.mean()) if len(delays) else float("nan")
        row[f"stop_ratio_{kind}"] = _ratio(int(part["stopped"].sum()), len(part))
        row[f"collided_{kind}"] = int(part["collided"].sum())
    row["collisions_automated"] = int((collided & ~with_human).sum())
    row["collisions_human"] = int((collided & with_human).sum())
    return row


def summarize(runs: pd.DataFrame, vehicles: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """Aggregate over runs, per planner (the ``summary.json`` schema).

    Flow-rate statistics are over runs; stop ratios, collision rate and delay are pooled over
    all vehicles of the planner's runs.

    :param runs: ``metrics.csv`` rows with a ``planner`` column
    :param vehicles: all vehicle logs with a ``planner`` column
    :return: ``planner -> {"runs", "vehicles", "vehicles_scheduled", "not_spawned",
        "flow_rate": {median, q1, q3, mean}, "offered_flow" (mean over runs), "stop_ratio": {all, major,
        minor, left, straight, right}, "collision_rate", "delay_s": {median, mean},
        "speed_limit_violations", "governor_share", "stuck_runs" (runs the watchdog found stuck),
        "last_crossing_s" (per run, in run order; ``None`` for a run without a crossing), "slow_ratio",
        "hard_brakes_per_vehicle", "energy_kj_per_vehicle" (:func:`motion_metrics`, pooled)}``
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
            **schedule_counts(v),
            "flow_rate": {
                "median": _finite(flow.median()),
                "q1": _finite(flow.quantile(0.25)),
                "q3": _finite(flow.quantile(0.75)),
                "mean": _finite(flow.mean()),
            },
            "offered_flow": _finite(_column(r, "offered_flow").astype(float).mean()),
            "stop_ratio": {group: _finite(_ratio(s, t)) for group, (t, s) in counts.items()},
            "collision_rate": _finite(_ratio(int(v["collided"].sum()), len(v))) if len(v) else 0.0,
            "delay_s": {
                "median": _finite(delays.median()) if len(delays) else None,
                "mean": _finite(delays.mean()) if len(delays) else None,
            },
            "speed_limit_violations": violations(v),
            "governor_share": _finite(governor_share(v)),
            "stuck_runs": int(_column(r, "stuck", False).astype(bool).sum()),
            "last_crossing_s": [_finite(t) for t in _column(r, "last_crossing_s").astype(float)],
            **{key: _finite(value) for key, value in motion_metrics(v).items()},
        }
    return summary


def _finite(value: float) -> float | None:
    """JSON has no NaN: undefined values (empty groups) become ``None``."""
    value = float(value)
    return value if np.isfinite(value) else None
