"""Small made-up recordings in the exact inD file format: a test fixture generator.

No inD data may ship with the project (its licence forbids it), so tests and examples build
their own recordings here: a four-way intersection at an arbitrary centre and rotation, vehicles
on known routes (entry arm, exit arm) with known appearance times, speeds and stops, plus a
pedestrian, a bicycle and tracks that cannot be mapped (parked, a U-turn, one that starts inside
the intersection). The files have every published column (:mod:`envs.ind.format`), so the
loader reads them exactly as it reads the real data.

Arms are named by compass direction *before* rotation, counter-clockwise:
``east`` (0 deg), ``north`` (90), ``west`` (180), ``south`` (270); traffic keeps right.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from envs.ind.format import (
    RECORDING_META_COLUMNS,
    TRACKS_COLUMNS,
    TRACKS_META_COLUMNS,
    VEHICLE_CLASSES,
    recording_file,
)

ARMS: tuple[str, ...] = ("east", "north", "west", "south")
_TURN_BY_STEP = {0: "u-turn", 1: "right", 2: "straight", 3: "left"}


def maneuver_of(entry: str, exit: str) -> str:
    """The maneuver of a route between two arms of the synthetic four-way (right-hand traffic).

    :param entry: arm the vehicle comes from
    :param exit: arm the vehicle leaves by
    :return: ``"left"``, ``"straight"``, ``"right"`` or ``"u-turn"``
    """
    return _TURN_BY_STEP[(ARMS.index(exit) - ARMS.index(entry)) % 4]


@dataclass(frozen=True)
class SyntheticSite:
    """Geometry of the made-up four-way intersection.

    :param centre: intersection centre in the recording's local frame [m]
    :param rotation_deg: counter-clockwise rotation of the whole site [deg]
    :param arm_length: distance from the centre where tracks begin and end [m]
    :param arm_lengths: per arm (east, north, west, south) instead of ``arm_length``, e.g. a
        minor road seen only a short way, as at the real site
    :param box: distance from the centre to the stop lines [m]
    :param lane_offset: distance of a lane centre line from the arm's axis [m]
    :param location_id: ``locationId`` written to the recording meta
    :param frame_rate: frames per second
    """

    centre: tuple[float, float] = (63.2, -41.7)
    rotation_deg: float = 23.0
    arm_length: float = 45.0
    arm_lengths: tuple[float, float, float, float] | None = None
    box: float = 9.0
    lane_offset: float = 1.75
    location_id: int = 1
    frame_rate: float = 25.0

    def length_of(self, arm: str) -> float:
        """Distance from the centre where tracks on ``arm`` begin or end [m]."""
        return self.arm_length if self.arm_lengths is None else float(self.arm_lengths[ARMS.index(arm)])

    def outward(self, arm: str) -> np.ndarray:
        """Unit vector from the centre out along ``arm``."""
        angle = np.deg2rad(self.rotation_deg + 90.0 * ARMS.index(arm))
        return np.array([np.cos(angle), np.sin(angle)])

    def path(self, entry: str, exit: str, step: float = 0.25) -> np.ndarray:
        """Polyline of the route ``entry -> exit``: in on the right-hand lane, a curve, out on the right.

        :param entry: arm the vehicle comes from
        :param exit: arm the vehicle leaves by
        :param step: spacing of the points [m]
        :return: ``(n, 2)`` points in the local frame
        """
        c = np.asarray(self.centre, dtype=float)
        u_in, u_out = self.outward(entry), self.outward(exit)
        left = lambda u: np.array([-u[1], u[0]])  # noqa: E731
        # Keep right: the incoming lane is left of the arm's outward axis, the outgoing lane right of it.
        start = c + self.length_of(entry) * u_in + self.lane_offset * left(u_in)
        p_in = c + self.box * u_in + self.lane_offset * left(u_in)
        p_out = c + self.box * u_out - self.lane_offset * left(u_out)
        end = c + self.length_of(exit) * u_out - self.lane_offset * left(u_out)
        d_in, d_out = -u_in, u_out
        cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
        if abs(cross) > 1e-6:  # a turn: control point where the two lane lines meet
            t = ((p_out - p_in)[0] * d_out[1] - (p_out - p_in)[1] * d_out[0]) / cross
            control = p_in + t * d_in
        elif entry == exit:  # U-turn: swing around the centre
            control = c - self.box * u_in
        else:
            control = 0.5 * (p_in + p_out)
        tt = np.linspace(0.0, 1.0, 64)[:, None]
        curve = (1 - tt) ** 2 * p_in + 2 * (1 - tt) * tt * control + tt**2 * p_out
        rough = np.vstack([start, curve, end])
        seg = np.hypot(*np.diff(rough, axis=0).T)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        fine = np.arange(0.0, s[-1], step)
        return np.column_stack([np.interp(fine, s, rough[:, 0]), np.interp(fine, s, rough[:, 1])])


@dataclass(frozen=True)
class SyntheticVehicle:
    """One made-up road user on a route.

    :param entry: arm it comes from (:data:`ARMS`)
    :param exit: arm it leaves by
    :param time: appearance time [s]
    :param speed: cruising speed [m/s]
    :param stop: seconds it stands at the stop line (0: it never stops)
    :param cls: inD class, e.g. ``"car"``, ``"truck_bus"``, ``"bicycle"``
    """

    entry: str
    exit: str
    time: float
    speed: float
    stop: float = 0.0
    cls: str = "car"


@dataclass
class SyntheticRecording:
    """The three inD tables of a made-up recording and what the mapping should find.

    :param tracks: ``XX_tracks.csv`` rows
    :param tracks_meta: ``XX_tracksMeta.csv`` rows
    :param recording_meta: ``XX_recordingMeta.csv`` row
    :param expected: per trackId: ``class``, ``entry``, ``exit``, ``maneuver``, ``time``, ``speed``,
        ``stopped`` and ``reason`` (why it cannot be mapped, ``""`` if it can)
    """

    tracks: pd.DataFrame
    tracks_meta: pd.DataFrame
    recording_meta: pd.DataFrame
    expected: pd.DataFrame = field(repr=False)


def _motion(
    site: SyntheticSite, points: np.ndarray, v0: float, stop: float, stop_at: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, speeds and tangents along ``points`` sampled at the frame rate.

    A stopping vehicle brakes at 2.5 m/s^2 to stand still ``stop_at`` metres along the path, waits
    ``stop`` seconds and pulls away at 2 m/s^2.
    """
    dt = 1.0 / site.frame_rate
    seg = np.hypot(*np.diff(points, axis=0).T)
    s_path = np.concatenate([[0.0], np.cumsum(seg)])
    if stop > 0 and v0 > 0:
        brake, pull = 2.5, 2.0
        t1 = max(stop_at - v0**2 / (2 * brake), 0.0) / v0
        t2 = t1 + v0 / brake
        t3 = t2 + stop
        t4 = t3 + v0 / pull
        t_knots, v_knots = [0.0, t1, t2, t3, t4, t4 + 1e4], [v0, v0, 0.0, 0.0, v0, v0]
    else:
        t_knots, v_knots = [0.0, 1e4], [v0, v0]
    t = np.arange(0.0, 1e4, dt)
    v = np.interp(t, t_knots, v_knots)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    keep = s <= s_path[-1]
    s, v = s[keep], v[keep]
    xy = np.column_stack([np.interp(s, s_path, points[:, 0]), np.interp(s, s_path, points[:, 1])])
    tangent = np.diff(points, axis=0) / np.maximum(seg, 1e-9)[:, None]
    idx = np.clip(np.searchsorted(s_path, s, side="right") - 1, 0, len(tangent) - 1)
    return xy, v, tangent[idx]


def _track_rows(
    track_id: int,
    first_frame: int,
    xy: np.ndarray,
    v: np.ndarray,
    tangent: np.ndarray,
    width: float,
    length: float,
    frame_rate: float,
) -> pd.DataFrame:
    n = len(v)
    vel = v[:, None] * tangent
    if n > 1:
        acc = np.gradient(vel, 1.0 / frame_rate, axis=0)
        lon_acc = np.gradient(v, 1.0 / frame_rate)
    else:
        acc, lon_acc = np.zeros((n, 2)), np.zeros(n)
    heading = np.rad2deg(np.arctan2(tangent[:, 1], tangent[:, 0])) % 360.0
    lat_acc = acc[:, 1] * tangent[:, 0] - acc[:, 0] * tangent[:, 1]
    return pd.DataFrame(
        {
            "trackId": track_id,
            "frame": first_frame + np.arange(n),
            "trackLifetime": np.arange(n),
            "xCenter": xy[:, 0],
            "yCenter": xy[:, 1],
            "heading": heading,
            "width": width,
            "length": length,
            "xVelocity": vel[:, 0],
            "yVelocity": vel[:, 1],
            "xAcceleration": acc[:, 0],
            "yAcceleration": acc[:, 1],
            "lonVelocity": v,
            "latVelocity": 0.0,
            "lonAcceleration": lon_acc,
            "latAcceleration": lat_acc,
        }
    )


def default_vehicles(seed: int = 0, num: int = 36) -> list[SyntheticVehicle]:
    """A mix of every route of the four-way, more traffic on the east-west (major) road.

    Left turns stop more often than the rest, as at the real site; every route appears at least
    once, so the mapping sees all four arms as entries and exits.

    :param seed: random seed
    :param num: number of vehicles (at least 12, one per route)
    :return: vehicles sorted by appearance time
    """
    rng = np.random.default_rng(seed)
    routes = [(a, b) for a in ARMS for b in ARMS if a != b]
    weights = np.array(
        [3.0 if a in ("east", "west") else 1.0 for a, _ in routes]
    )  # east-west is the busy road
    extra = rng.choice(len(routes), max(num - len(routes), 0), p=weights / weights.sum())
    picks = list(range(len(routes))) + [int(k) for k in extra]
    times = np.sort(rng.uniform(0.0, 6.0 * num, size=len(picks)))
    vehicles = []
    for i, (k, t) in enumerate(zip(picks, times)):
        entry, exit = routes[k]
        p_stop = 0.7 if maneuver_of(entry, exit) == "left" else 0.2
        stop = float(rng.uniform(1.0, 4.0)) if rng.random() < p_stop else 0.0
        cls = "truck_bus" if i % 9 == 4 else "car"
        vehicles.append(
            SyntheticVehicle(entry, exit, float(round(t, 2)), float(rng.uniform(6.0, 12.0)), stop, cls)
        )
    return vehicles


def make_recording(
    recording_id: int,
    vehicles: Sequence[SyntheticVehicle],
    site: SyntheticSite | None = None,
    extras: bool = True,
) -> SyntheticRecording:
    """Build the three inD tables of one recording.

    :param recording_id: the recording number written into every table
    :param vehicles: the road users on routes, in trackId order
    :param site: the intersection geometry (default: :class:`SyntheticSite`)
    :param extras: after the vehicles, add a pedestrian, a bicycle, a parked car, a U-turn, a car
        whose track starts inside the intersection, one whose track ends there and one coming out
        of a driveway between two arms. Their ``expected`` reasons are the labels
        ``"not modelled"``, ``"parked"``, ``"u-turn"``, ``"starts inside"``, ``"ends inside"``, ``"off arm"``
    :return: the tables and the expected mapping
    """
    site = site or SyntheticSite()
    tracks = _TrackTables(site)
    for vehicle in vehicles:
        _add_route_vehicle(tracks, site, vehicle)
    if extras:
        _add_extras(tracks, site)
    return tracks.recording(int(recording_id))


class _TrackTables:
    """The rows of a made-up recording as its tracks are added: frames, track metadata and what the
    mapping should find for each track."""

    def __init__(self, site: SyntheticSite) -> None:
        self.site = site
        self.fr = site.frame_rate
        self.frames: list[pd.DataFrame] = []
        self.metas: list[dict[str, Any]] = []
        self.expected: list[dict[str, Any]] = []

    def add(self, cls: str, first_frame: int, xy, v, tangent, entry="", exit="", reason="", maneuver="") -> None:
        """Add one track (the next trackId) of class ``cls``, and its expected mapping."""
        fr = self.fr
        track_id = len(self.metas)
        is_vehicle = cls in VEHICLE_CLASSES
        width, length = ((2.5, 10.0) if cls == "truck_bus" else (1.8, 4.5)) if is_vehicle else (0.0, 0.0)
        self.frames.append(_track_rows(track_id, first_frame, xy, v, tangent, width, length, fr))
        self.metas.append(
            {
                "trackId": track_id,
                "initialFrame": first_frame,
                "finalFrame": first_frame + len(v) - 1,
                "numFrames": len(v),
                "width": width,
                "length": length,
                "class": cls,
            }
        )
        self.expected.append(
            {
                "trackId": track_id,
                "class": cls,
                "entry": entry,
                "exit": exit,
                "maneuver": maneuver,
                "time": first_frame / fr,
                "speed": float(v[0]),
                "stopped": bool((v < 0.3).any()),
                "reason": reason,
            }
        )

    def end_time(self) -> float:
        """Time of the last frame so far [s] (0 without tracks)."""
        return max((m["finalFrame"] for m in self.metas), default=0) / self.fr

    def recording(self, recording_id: int) -> SyntheticRecording:
        """The three inD tables of the tracks added, and the expected mapping."""
        fr, site = self.fr, self.site
        tracks = pd.concat(self.frames, ignore_index=True)
        tracks.insert(0, "recordingId", recording_id)
        tracks = tracks[list(TRACKS_COLUMNS)]
        tracks_meta = pd.DataFrame(self.metas)
        tracks_meta.insert(0, "recordingId", recording_id)
        tracks_meta = tracks_meta[list(TRACKS_META_COLUMNS)]
        num_vehicles = int(tracks_meta["class"].isin(VEHICLE_CLASSES).sum())
        duration = (int(tracks["frame"].max()) + 1) / fr
        recording_meta = pd.DataFrame(
            [
                {
                    "recordingId": recording_id,
                    "locationId": site.location_id,
                    "frameRate": fr,
                    "speedLimit": 13.8889,
                    "weekday": "tuesday",
                    "startTime": 8,
                    "duration": duration,
                    "numTracks": len(tracks_meta),
                    "numVehicles": num_vehicles,
                    "numVRUs": len(tracks_meta) - num_vehicles,
                    "latLocation": 50.78,
                    "lonLocation": 6.07,
                    "xUtmOrigin": 293487.1,
                    "yUtmOrigin": 5629712.0,
                    "orthoPxToMeter": 0.0126999352667008,
                }
            ]
        )[list(RECORDING_META_COLUMNS)]
        expected = pd.DataFrame(self.expected).set_index("trackId")
        return SyntheticRecording(tracks, tracks_meta, recording_meta, expected)


def _add_route_vehicle(tracks: _TrackTables, site: SyntheticSite, vehicle: SyntheticVehicle) -> None:
    """Add a road user driving its route (a U-turn is expected as ``"u-turn"``)."""
    points = site.path(vehicle.entry, vehicle.exit)
    xy, v, tangent = _motion(site, points, vehicle.speed, vehicle.stop, site.length_of(vehicle.entry) - site.box - 1.0)
    maneuver = maneuver_of(vehicle.entry, vehicle.exit)
    reason = "u-turn" if maneuver == "u-turn" else ""  # labels: see make_recording
    first = int(round(vehicle.time * site.frame_rate))
    tracks.add(vehicle.cls, first, xy, v, tangent, vehicle.entry, vehicle.exit, reason, "" if reason else maneuver)


def _add_extras(tracks: _TrackTables, site: SyntheticSite) -> None:
    """Add the tracks that the mapping must refuse, each with its reason (see :func:`make_recording`)."""
    fr = site.frame_rate
    t_end = tracks.end_time()
    c = np.asarray(site.centre)
    # A pedestrian crossing the east arm on a crosswalk just outside the stop line.
    u, left = site.outward("east"), site.outward("north")
    a, b = c + (site.box + 3) * u - 6 * left, c + (site.box + 3) * u + 6 * left
    n = int(np.hypot(*(b - a)) / 1.4 * fr)
    xy = a + np.linspace(0, 1, n)[:, None] * (b - a)
    direction = np.tile((b - a) / np.hypot(*(b - a)), (n, 1))
    tracks.add("pedestrian", int(5 * fr), xy, np.full(n, 1.4), direction, reason="not modelled")
    # A bicycle going straight south -> north.
    xy, v, tangent = _motion(site, site.path("south", "north"), 4.5, 0.0, 0.0)
    tracks.add("bicycle", int(12 * fr), xy, v, tangent, reason="not modelled")
    # A car parked next to the intersection for the whole recording.
    n = int(max(t_end, 30.0) * fr)
    diag = (site.outward("north") + site.outward("east")) / np.sqrt(2)
    xy = np.tile(c + 25.0 * diag, (n, 1))
    tracks.add("car", 0, xy, np.zeros(n), np.tile(site.outward("north"), (n, 1)), reason="parked")
    # A U-turn on the west arm.
    xy, v, tangent = _motion(site, site.path("west", "west"), 6.0, 0.0, 0.0)
    tracks.add("car", int(20 * fr), xy, v, tangent, "west", "west", "u-turn")
    # A car first tracked in the middle of the intersection, leaving north.
    points = site.path("south", "north")
    start = np.argmin(np.hypot(*(points - c).T))
    xy, v, tangent = _motion(site, points[start:], 8.0, 0.0, 0.0)
    tracks.add("car", int(30 * fr), xy, v, tangent, "", "north", "starts inside")
    # A car whose track is lost in the middle of the intersection, coming from the east.
    points = site.path("east", "west")
    end = np.argmin(np.hypot(*(points - c).T))
    xy, v, tangent = _motion(site, points[: end + 1], 8.0, 0.0, 0.0)
    tracks.add("car", int(40 * fr), xy, v, tangent, "east", "", "ends inside")
    # A car out of a driveway half-way between the east and north arms, leaving south.
    xy, v, tangent = _motion(site, _driveway_path(site, c, diag), 5.0, 0.0, 0.0)
    tracks.add("car", int(50 * fr), xy, v, tangent, "", "south", "off arm")


def _driveway_path(site: SyntheticSite, c: np.ndarray, diag: np.ndarray) -> np.ndarray:
    """Points every 0.25 m from a driveway between the east and north arms to the south exit lane."""
    u_south = site.outward("south")
    rough = np.vstack(
        [
            c + 30.0 * diag,
            c + 1.75 * diag,
            c + site.length_of("south") * u_south - site.lane_offset * np.array([-u_south[1], u_south[0]]),
        ]
    )
    seg = np.hypot(*np.diff(rough, axis=0).T)
    s_rough = np.concatenate([[0.0], np.cumsum(seg)])
    fine = np.arange(0.0, s_rough[-1], 0.25)
    return np.column_stack([np.interp(fine, s_rough, rough[:, 0]), np.interp(fine, s_rough, rough[:, 1])])


def write_recording(data_dir: str | Path, recording: SyntheticRecording) -> dict[str, Path]:
    """Write a made-up recording as ``XX_tracks.csv``, ``XX_tracksMeta.csv``, ``XX_recordingMeta.csv``.

    :param data_dir: folder to write into (created if needed); existing files are not overwritten
    :param recording: the tables from :func:`make_recording`
    :return: kind -> path of each written file
    """
    recording_id = int(recording.recording_meta["recordingId"].iloc[0])
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    tables = {
        "tracks": recording.tracks,
        "tracksMeta": recording.tracks_meta,
        "recordingMeta": recording.recording_meta,
    }
    paths = {kind: recording_file(data_dir, recording_id, kind) for kind in tables}
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing:
        raise FileExistsError(f"refusing to overwrite existing inD files: {', '.join(existing)}")
    for kind, table in tables.items():
        table.to_csv(paths[kind], index=False, float_format="%.4f")
    return paths
