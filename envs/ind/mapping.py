"""Map recorded vehicle tracks onto the simulated intersection, from the tracks alone.

The real site's map is not used: everything is derived from where vehicles enter and leave.

1. Per track (one pandas ``groupby`` over all frames): first and last position, direction of
   travel there, first speed, lowest speed, path length.
2. Intersection centre: the point closest, in least squares, to the lines along which vehicles
   enter and leave (every arm points at the centre), or given by the caller.
3. Arms: the directions (angles around the centre) of the track ends outside ``inner_radius``
   pile up in one bump per arm; the ``num_arms`` largest bumps of a smoothed circular
   histogram are the arms, each refined to the circular mean of its ends.
4. Each track gets an entry arm, an exit arm, and a maneuver from the signed turn angle between
   the entry direction (inwards) and the exit direction (outwards): counter-clockwise is a left
   turn in the inD frame (x east, y north), traffic keeps right.
5. Major road: by default the pair of opposite arms carrying the most mapped tracks.
6. Alignment: recorded arms are matched to a simulated layout's arms keeping the cyclic order
   (so left stays left) and sending the major road to the layout's major road; each track gets
   the layout route name ``"<entry arm>-><exit arm>"``.
7. Arrival timing (``MappingOptions.arrival_timing``, on by default): the recorded tracks begin
   at the edge of the drone's view, a different distance from the centre on every arm, while
   simulated vehicles appear at the start of the layout's approach lane. Each simulated
   appearance is therefore timed so that the vehicle, driving at its recorded initial speed
   (clipped to the lane's limit), reaches the stop line when the recorded vehicle entered the
   intersection area (first frame within the stop-line distance of the centre; if the track never
   comes that close, its closest approach to the centre minus the layout's travel from the stop
   line to that point), never before time 0.

A track that cannot be mapped keeps its row, with ``mapped = False`` and the reason.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from envs.ind.loader import Recording
from envs.simulation.layouts import build_layout
from envs.simulation.motion import event_starts, hard_braking, traction_energy
from envs.simulation.scene import MAJOR, MANEUVERS, STOP_SPEED

COMPASS: tuple[str, ...] = ("east", "north", "west", "south")  # counter-clockwise from +x

# Reasons a track is not mapped (the ``reason`` column).
REASON_NOT_MODELLED = "not modelled: "  # followed by the class
REASON_NO_FRAMES = "no frames in the tracks file"
REASON_PARKED = "parked (travels less than min_travel)"
REASON_STARTS_INSIDE = "starts inside the intersection"
REASON_ENDS_INSIDE = "ends inside the intersection"
REASON_ENTRY_OFF_ARM = "enters away from every arm"
REASON_EXIT_OFF_ARM = "leaves away from every arm"
REASON_U_TURN = "u-turn (enters and leaves by the same arm)"
REASON_LAYOUT = "maneuver changes in the layout"

# Size of a simulated vehicle where tracksMeta gives none [m] (the scenario defaults).
DEFAULT_VEHICLE_LENGTH = 5.0
DEFAULT_VEHICLE_WIDTH = 2.0


@dataclass(frozen=True)
class MappingOptions:
    """How tracks are mapped.

    :param centre: intersection centre in the recordings' local frame [m]; ``None`` estimates it
    :param num_arms: number of approach arms (4 for inD's four-way sites)
    :param inner_radius: a track end closer than this to the centre is inside the intersection [m]
    :param min_travel: a track travelling less than this in total is parked [m]
    :param arm_tolerance_deg: a track end farther than this (angle around the centre) from every
        arm belongs to no arm [deg]
    :param major_arms: names of the two recorded arms of the major road (compass names, see
        :attr:`MappedTracks.arms`); ``None``: the opposite pair carrying the most traffic
    :param turn_threshold_deg: turns whose signed angle exceeds this are left (positive) or
        right (negative) turns, the others straight [deg]
    :param min_arm_separation_deg: smallest angle between two arms [deg]
    :param arrival_timing: time each simulated appearance so that the vehicle reaches the stop
        line when the recorded one entered the intersection area (see the module docstring);
        ``False``: appear at the recorded appearance time (``initialFrame / frameRate``)
    :param entry_radius: a recorded vehicle enters the intersection area when its centre first
        comes this close to the centre [m]; ``None``: the simulated layout's distance from its
        centre to the stop line of the vehicle's route
    :param min_timing_speed: recorded initial speeds below this count as this for the timing
        [m/s]: a vehicle recorded standing at the edge of the view is not assumed to crawl the
        whole approach
    """

    centre: tuple[float, float] | None = None
    num_arms: int = 4
    inner_radius: float = 10.0
    min_travel: float = 5.0
    arm_tolerance_deg: float = 30.0
    major_arms: tuple[str, str] | None = None
    turn_threshold_deg: float = 45.0
    min_arm_separation_deg: float = 45.0
    arrival_timing: bool = True
    entry_radius: float | None = None
    min_timing_speed: float = 3.0

    def __post_init__(self) -> None:
        if self.num_arms < 3:
            raise ValueError(f"num_arms must be at least 3, got {self.num_arms}")
        for name in (
            "inner_radius",
            "min_travel",
            "arm_tolerance_deg",
            "turn_threshold_deg",
            "min_arm_separation_deg",
            "min_timing_speed",
        ):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if self.centre is not None and (len(self.centre) != 2 or not np.all(np.isfinite(self.centre))):
            raise ValueError(f"centre must be two finite numbers (x, y), got {self.centre!r}")
        if self.major_arms is not None and len(set(self.major_arms)) != 2:
            raise ValueError(f"major_arms must name two different arms, got {self.major_arms!r}")
        if self.entry_radius is not None and not (np.isfinite(self.entry_radius) and self.entry_radius > 0):
            raise ValueError(f"entry_radius must be a positive number or None, got {self.entry_radius!r}")
        if not isinstance(self.arrival_timing, (bool, np.bool_)):
            raise ValueError(f"arrival_timing must be True or False, got {self.arrival_timing!r}")


@dataclass(frozen=True)
class LayoutArms:
    """What the alignment needs to know about a simulated layout.

    :param angles: arm name -> outward direction of the arm [rad], counter-clockwise from +x
    :param major: the two arms of the layout's major (priority) road
    :param routes: route geometry for the arrival timing, indexed by route name
        (``"<entry arm>-><exit arm>"``): ``entry_arc`` (arc length from the route's start to its
        stop line [m]), ``speed_limit`` (at the route's start [m/s]), ``entry_radius`` (distance
        of the stop line's lane centre from the layout's centre [m]) and ``inside`` (arc length
        from the stop line to the route's closest approach to the centre [m]); ``None`` when
        unknown (then ``arrival_timing`` cannot be used)
    """

    angles: Mapping[str, float]
    major: tuple[str, str]
    routes: pd.DataFrame | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if not set(self.major) <= set(self.angles) or len(set(self.major)) != 2:
            raise ValueError(f"major must be two of the arms {sorted(self.angles)}, got {self.major!r}")


# The simulated four-way when envs.simulation.layouts cannot say: compass arms, east-west priority road.
DEFAULT_LAYOUT = LayoutArms(angles={n: k * np.pi / 2 for k, n in enumerate(COMPASS)}, major=("east", "west"))


def layout_arms(layout: Any) -> LayoutArms:
    """The alignment interface of a simulated layout (an :class:`envs.simulation.layouts.Layout`).

    The layouts use highway-env's frame (``y`` south, arm angles ``atan2(y, x)`` there), inD a
    right-handed frame with ``y`` north: the angles change sign, which keeps left turns left.

    :param layout: an :class:`envs.simulation.layouts.Layout` (centred on the origin); the arms need
        ``arm_angle`` (arm -> outward angle [rad], ``y`` south), ``entry_arm`` and ``priority``
        (per route); the route geometry of the arrival timing is read when the layout has
        ``route_names``, ``entry_arc``, ``exit_arc``, ``xy``, ``ds`` and ``speed_limit``
    :return: arms in the inD frame, the entry arms of the major-road routes and the route geometry
    """
    angles = {str(name): -float(angle) for name, angle in layout.arm_angle.items()}
    major = sorted(
        {str(arm) for arm, p in zip(layout.entry_arm, np.asarray(layout.priority)) if int(p) == MAJOR}
    )
    if len(major) != 2:
        raise ValueError(
            f"layout {getattr(layout, 'name', '?')!r}: expected a major road of two arms, got {major}"
        )
    routes = None
    if all(hasattr(layout, a) for a in ("route_names", "entry_arc", "exit_arc", "xy", "ds", "speed_limit")):
        routes = _route_geometry(layout)
    return LayoutArms(angles=angles, major=(major[0], major[1]), routes=routes)


def _route_geometry(layout: Any) -> pd.DataFrame:
    """The per-route table of :attr:`LayoutArms.routes` from a layout's sampled centre lines."""
    entry, exit_ = np.asarray(layout.entry_arc, float), np.asarray(layout.exit_arc, float)
    xy = np.asarray(layout.xy, float)  # (R, M, 2), the layout's centre at the origin
    arc = np.arange(xy.shape[1]) * float(layout.ds)
    radius = np.hypot(xy[..., 0], xy[..., 1])
    within = (arc[None, :] >= entry[:, None]) & (arc[None, :] <= exit_[:, None])
    closest = np.where(within, radius, np.inf).argmin(axis=1)
    rows = np.arange(len(entry))
    at_entry = np.minimum(np.round(entry / layout.ds).astype(np.int64), xy.shape[1] - 1)
    return pd.DataFrame(
        {
            "entry_arc": entry,
            "speed_limit": np.asarray(layout.speed_limit, float)[:, 0],
            "entry_radius": radius[rows, at_entry],
            "inside": np.maximum(arc[closest] - entry, 0.0),
        },
        index=pd.Index(list(layout.route_names), name="route"),
    )


@dataclass
class MappedTracks:
    """The mapping of every track of one or more recordings of one site.

    :param tracks: one row per track (every class), columns ``recording``, ``track_id``, ``class``,
        ``length`` and ``width`` (tracksMeta, [m]),
        ``time`` (appearance time [s]: initialFrame / frameRate), ``speed`` (first speed [m/s]),
        ``min_speed``, ``stopped`` (speed below ``STOP_SPEED`` in some frame), ``t_centre`` (time
        of the frame closest to the centre [s]), ``t_last`` (last frame [s]), ``min_distance``
        (closest approach to the centre [m]), ``hard_brakes`` (hard-braking events over the track) and
        ``energy_to_centre_j`` (traction energy from the first frame to the one closest to the centre [J]:
        :func:`track_motion`), ``t_entry`` (when it entered the intersection
        area [s], NaN without arrival timing), ``spawn_time`` (when it appears in simulation [s]:
        timed by the arrival timing, else ``time``), ``entry_arm``,
        ``exit_arm``, ``turn_deg`` (signed turn angle, left positive), ``maneuver``,
        ``priority`` (``"major"``/``"minor"`` road of the entry arm), ``route`` (layout route name),
        ``mapped`` (bool) and ``reason`` (why not, ``""`` when mapped)
    :param arms: one row per recorded arm, indexed by its compass name: ``angle_deg`` (outward
        direction), ``entries``, ``exits``, ``major`` (bool), ``layout_arm``
    :param centre: the intersection centre used [m]
    :param centre_estimated: whether the centre was estimated from the tracks
    :param options: the options the mapping used
    """

    tracks: pd.DataFrame
    arms: pd.DataFrame
    centre: np.ndarray
    centre_estimated: bool = True
    options: MappingOptions = field(default_factory=MappingOptions)

    @property
    def mapped(self) -> pd.DataFrame:
        """The rows of the tracks that are mapped."""
        return self.tracks[self.tracks["mapped"]]

    @property
    def unmapped(self) -> pd.DataFrame:
        """The rows of the tracks that are not mapped, with their reasons."""
        return self.tracks[~self.tracks["mapped"]]

    def reasons(self) -> pd.Series:
        """Number of unmapped tracks per reason."""
        return self.unmapped["reason"].value_counts().rename("tracks")


def _wrap_deg(angle: np.ndarray | float) -> np.ndarray:
    """Angles in degrees wrapped to ``(-180, 180]``."""
    return 180.0 - np.mod(180.0 - np.asarray(angle, dtype=float), 360.0)


def track_summary(tracks: pd.DataFrame) -> pd.DataFrame:
    """First and last state, lowest speed and path length of each vehicle track.

    :param tracks: per-frame rows (``recordingId``, ``trackId``, ``frame``, ``xCenter``,
        ``yCenter``, ``heading``, ``xVelocity``, ``yVelocity``, ``speed``), sorted by track and frame
    :return: one row per ``(recordingId, trackId)``: ``x0, y0, dx0, dy0`` (position and unit
        direction of travel at the first frame), ``x1, y1, dx1, dy1`` (last frame), ``speed0``,
        ``min_speed``, ``travel`` [m], ``last_frame``
    """
    keys = ["recordingId", "trackId"]
    # Direction of travel: the velocity where the vehicle moves, else its heading.
    speed = tracks["speed"].to_numpy()
    moving = speed > 0.5
    heading = np.deg2rad(tracks["heading"].to_numpy())
    norm = np.maximum(speed, 1e-9)
    dx = np.where(moving, tracks["xVelocity"].to_numpy() / norm, np.cos(heading))
    dy = np.where(moving, tracks["yVelocity"].to_numpy() / norm, np.sin(heading))
    same_track = tracks[keys].eq(tracks[keys].shift()).all(axis=1).to_numpy()
    step = np.where(same_track, np.hypot(tracks["xCenter"].diff(), tracks["yCenter"].diff()), 0.0)
    frame = tracks[keys].assign(
        frame=tracks["frame"], x=tracks["xCenter"], y=tracks["yCenter"], dx=dx, dy=dy, speed=speed, step=step
    )
    grouped = frame.groupby(keys, sort=True)
    first, last = grouped.first(), grouped.last()
    return pd.DataFrame(
        {
            "x0": first["x"],
            "y0": first["y"],
            "dx0": first["dx"],
            "dy0": first["dy"],
            "x1": last["x"],
            "y1": last["y"],
            "dx1": last["dx"],
            "dy1": last["dy"],
            "speed0": first["speed"],
            "min_speed": grouped["speed"].min(),
            "travel": grouped["step"].sum(),
            "last_frame": last["frame"],
        }
    )


def track_motion(tracks: pd.DataFrame, frame_rate: float) -> tuple[np.ndarray, np.ndarray]:
    """What each recorded vehicle's motion costs, frame by frame, with the simulation's measures
    (:mod:`envs.simulation.motion`): between two frames of a track the speed changes linearly.

    :param tracks: per-frame rows of one recording (``trackId``, ``frame``, ``speed``), sorted by track and frame
    :param frame_rate: the recording's frames per second
    :return: ``(m,)`` bool: a hard-braking event begins between the previous frame and this one, and
        ``(m,)`` the traction energy from the track's first frame to this one [J]
    """
    track = tracks["trackId"].to_numpy()
    speed = tracks["speed"].to_numpy(float)
    frame = tracks["frame"].to_numpy(float)
    same = np.zeros(len(track), bool)
    same[1:] = (track[1:] == track[:-1]) & (frame[1:] > frame[:-1])
    before = np.concatenate([speed[:1], speed[:-1]])  # the previous frame's speed
    dt = np.where(same, np.diff(frame, prepend=frame[:1]) / frame_rate, 1.0)
    group = np.cumsum(~same)  # one group per track (and per gap in its frames)
    starts = event_starts(same & hard_braking((speed - before) / dt), group)
    energy = np.where(same, traction_energy(before, speed, dt), 0.0)
    return starts, pd.Series(energy).groupby(group).cumsum().to_numpy()


def estimate_centre(points: np.ndarray, directions: np.ndarray, iterations: int = 5) -> np.ndarray:
    """The point closest to a set of lines, in iteratively reweighted least squares.

    Line ``i`` passes through ``points[i]`` along ``directions[i]``; the point ``c`` minimises
    ``sum_i w_i |(I - d_i d_i^T)(c - p_i)|^2`` with ``w_i = 1 / max(dist_i, 1 m)`` after the first
    pass, so that the few lines that miss the centre (lane offsets, odd tracks) weigh little.

    :param points: ``(n, 2)`` a point of each line [m]
    :param directions: ``(n, 2)`` unit direction of each line
    :param iterations: reweighting passes
    :return: ``(2,)`` the centre
    :raises ValueError: the lines are (nearly) parallel, so no single crossing point exists
    """
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    projector = np.eye(2)[None] - d[:, :, None] * d[:, None, :]  # (n, 2, 2) removes the along-line part
    weights = np.ones(len(points))
    centre = np.zeros(2)
    for _ in range(iterations):
        a = np.einsum("n,nij->ij", weights, projector)
        b = np.einsum("n,nij,nj->i", weights, projector, points)
        if len(points) < 2 or np.linalg.cond(a) > 1e6:
            raise ValueError(
                "cannot estimate the intersection centre: the tracks run (nearly) parallel; "
                "give it with centre=(x, y)"
            )
        centre = np.linalg.solve(a, b)
        residual = np.linalg.norm(np.einsum("nij,nj->ni", projector, centre - points), axis=1)
        weights = 1.0 / np.maximum(residual, 1.0)
    return centre


def find_arms(angles_deg: np.ndarray, num_arms: int, min_separation_deg: float = 45.0) -> np.ndarray:
    """Directions of the approach arms from the angles (around the centre) of track ends.

    A circular histogram with 1 degree bins is smoothed over +-10 degrees; the ``num_arms``
    highest peaks at least ``min_separation_deg`` apart are the arms, each refined to the
    circular mean of the angles nearest to it (and within ``min_separation_deg``). The separation
    keeps the two lanes of one arm (entering and leaving, far apart in angle where the recorded
    arm is short) from being taken for two arms.

    :param angles_deg: ``(n,)`` angles of the track ends [deg]
    :param num_arms: how many arms to find
    :param min_separation_deg: smallest angle between two arms [deg]
    :return: ``(num_arms,)`` arm directions in ``[0, 360)``, counter-clockwise order
    :raises ValueError: fewer distinct arms than ``num_arms``
    """
    angles = np.mod(np.asarray(angles_deg, dtype=float), 360.0)
    histogram = np.bincount(np.floor(angles).astype(int) % 360, minlength=360).astype(float)
    kernel = np.exp(-0.5 * (np.arange(-10, 11) / 4.0) ** 2)
    padded = np.concatenate([histogram[-10:], histogram, histogram[:10]])
    density = np.convolve(padded, kernel, mode="valid")  # circular smoothing
    bins = np.arange(360)
    peaks = []
    for _ in range(num_arms):
        k = int(np.argmax(density))
        if density[k] <= 0:
            raise ValueError(
                f"found only {len(peaks)} approach arms in the tracks, expected {num_arms}; "
                "check inner_radius and centre"
            )
        peaks.append(k + 0.5)
        density[np.abs(_wrap_deg(bins + 0.5 - peaks[-1])) < min_separation_deg] = 0.0
    peaks = np.array(peaks)
    off = np.abs(_wrap_deg(angles[:, None] - peaks[None, :]))  # (n, arms)
    near = (off == off.min(axis=1, keepdims=True)) & (off < min_separation_deg)  # nearest peak only
    rad = np.deg2rad(angles)[:, None]
    refined = np.rad2deg(np.arctan2((near * np.sin(rad)).sum(0), (near * np.cos(rad)).sum(0)))
    return np.sort(np.mod(refined, 360.0))


def compass_names(arm_angles_deg: np.ndarray) -> list[str]:
    """Name arms after the compass direction they point to (x east, y north), keeping their order.

    Four arms get east, north, west, south rotated as a whole to fit best; other numbers of arms
    get the nearest compass or half-compass name, made unique with a suffix.

    :param arm_angles_deg: ``(k,)`` arm directions in counter-clockwise order [deg]
    :return: a name per arm
    """
    angles = np.asarray(arm_angles_deg, dtype=float)
    if len(angles) == 4:
        cost = [np.abs(_wrap_deg(angles - 90.0 * ((np.arange(4) + r) % 4))).sum() for r in range(4)]
        r = int(np.argmin(cost))
        return [COMPASS[(k + r) % 4] for k in range(4)]
    eight = ("east", "northeast", "north", "northwest", "west", "southwest", "south", "southeast")
    names = [eight[int(np.round(a / 45.0)) % 8] for a in angles]
    return [n if names.count(n) == 1 else f"{n}{names[:i].count(n) + 1}" for i, n in enumerate(names)]


def align_arms(
    recorded: Mapping[str, float], recorded_major: Sequence[str], layout: LayoutArms
) -> dict[str, str]:
    """Match recorded arms to layout arms, keeping the rotation sense and the major road.

    Both sets of arms are put in counter-clockwise order; the candidates are the cyclic shifts
    (never a mirror image, which would turn left turns into right turns) that send the recorded
    major road onto the layout's major road. Of those, the one that rotates the arms least wins.

    :param recorded: recorded arm name -> outward direction [deg]
    :param recorded_major: the two recorded arms of the major road
    :param layout: the layout's arms and major road
    :return: recorded arm name -> layout arm name
    :raises ValueError: different numbers of arms, or no shift matches the major roads
    """
    if len(recorded) != len(layout.angles):
        raise ValueError(
            f"the recording has {len(recorded)} arms but the layout has {len(layout.angles)}: "
            f"{sorted(layout.angles)}"
        )
    rec_names = sorted(recorded, key=lambda n: np.mod(recorded[n], 360.0))
    lay_names = sorted(layout.angles, key=lambda n: np.mod(np.rad2deg(layout.angles[n]), 360.0))
    rec_angles = np.array([recorded[n] for n in rec_names])
    lay_angles = np.rad2deg(np.array([layout.angles[n] for n in lay_names]))
    n = len(rec_names)
    best, best_cost = None, np.inf
    for shift in range(n):
        pairing = {rec_names[k]: lay_names[(k + shift) % n] for k in range(n)}
        if {pairing[a] for a in recorded_major} != set(layout.major):
            continue
        rotation = _wrap_deg(lay_angles[(np.arange(n) + shift) % n] - rec_angles)
        cost = float(np.abs(rotation).sum())
        if cost < best_cost - 1e-9:
            best, best_cost = pairing, cost
    if best is None:
        raise ValueError(
            f"no rotation sends the recorded major road {tuple(recorded_major)} onto the layout's "
            f"major road {layout.major}: the arms do not correspond"
        )
    return best


def _maneuver(turn_deg: np.ndarray, threshold: float) -> np.ndarray:
    return np.where(
        turn_deg > threshold, MANEUVERS[0], np.where(turn_deg < -threshold, MANEUVERS[2], MANEUVERS[1])
    )


def map_recordings(
    recordings: Sequence[Recording],
    options: MappingOptions | None = None,
    layout: LayoutArms | None = None,
) -> MappedTracks:
    """Map the tracks of recordings of one site to the simulated layout.

    :param recordings: loaded recordings, all of one site (they share the local frame)
    :param options: mapping options
    :param layout: the simulated layout's arms and route geometry (default: those of the
        ``"inD"`` layout of :mod:`envs.simulation.layouts`, the one the replay runs on)
    :return: the mapping of every track
    :raises ValueError: recordings of several sites, nothing to map, or ``arrival_timing`` with a
        layout that has no route geometry
    """
    options = options or MappingOptions()
    if layout is None:
        layout = layout_arms(build_layout("inD"))
    _check_mapping_inputs(recordings, options, layout)
    table = _track_table(recordings)
    vehicle = table["is_vehicle"].to_numpy() & table["x0"].notna().to_numpy()
    moving = vehicle & (table["travel"].to_numpy() >= options.min_travel)
    if moving.sum() < 2:
        raise ValueError(
            f"only {int(moving.sum())} vehicle track(s) move at least min_travel={options.min_travel} m: "
            "nothing to map"
        )
    centre = _centre(table, moving, options)
    r0, a0 = _polar(table["x0"], table["y0"], centre)
    r1, a1 = _polar(table["x1"], table["y1"], centre)
    table = _with_passages(table, recordings, centre)
    start_out = moving & (r0 >= options.inner_radius)
    end_out = moving & (r1 >= options.inner_radius)
    arm_angles = find_arms(
        np.concatenate([a0[start_out], a1[end_out]]), options.num_arms, options.min_arm_separation_deg
    )
    names = np.array(compass_names(arm_angles))
    k0, on0 = _nearest_arm(a0, arm_angles, options.arm_tolerance_deg)
    k1, on1 = _nearest_arm(a1, arm_angles, options.arm_tolerance_deg)
    checks = [
        (~table["is_vehicle"].to_numpy(), None),
        (~vehicle, REASON_NO_FRAMES),
        (vehicle & ~moving, REASON_PARKED),
        (moving & ~start_out, REASON_STARTS_INSIDE),
        (moving & ~end_out, REASON_ENDS_INSIDE),
        (moving & ~on0, REASON_ENTRY_OFF_ARM),
        (moving & ~on1, REASON_EXIT_OFF_ARM),
        (moving & (k0 == k1), REASON_U_TURN),
    ]
    reason = _first_reasons(table, checks)
    ok = reason == ""

    entry = np.where(ok, names[k0], "")
    exit_ = np.where(ok, names[k1], "")
    turn = np.where(ok, _wrap_deg(arm_angles[k1] - (arm_angles[k0] + 180.0)), np.nan)
    maneuver = np.where(ok, _maneuver(turn, options.turn_threshold_deg), "")
    entries = pd.Series(entry[ok]).value_counts().reindex(names, fill_value=0)
    exits = pd.Series(exit_[ok]).value_counts().reindex(names, fill_value=0)
    major = _major_road(entries, exits, names, options)

    pairing = align_arms(dict(zip(names, arm_angles)), major, layout)
    route, changed = _layout_routes(pairing, names, k0, k1, ok, maneuver, layout, options)
    reason[changed] = REASON_LAYOUT
    ok = ok & ~changed

    route = np.where(ok, route, "")
    table["t_entry"], table["spawn_time"] = _arrival_times(table, recordings, centre, route, ok, layout, options)
    table = table.assign(
        entry_arm=np.where(ok, entry, ""),
        exit_arm=np.where(ok, exit_, ""),
        turn_deg=np.where(ok, turn, np.nan),
        maneuver=np.where(ok, maneuver, ""),
        priority=np.where(ok, np.where(np.isin(entry, major), "major", "minor"), ""),
        route=np.where(ok, route, ""),
        mapped=ok,
        reason=reason,
    )
    arms = _arm_table(arm_angles, names, entries, exits, major, pairing)
    return MappedTracks(table[list(MAPPED_COLUMNS)], arms, centre, options.centre is None, options)


def _arm_table(
    arm_angles: np.ndarray,
    names: np.ndarray,
    entries: pd.Series,
    exits: pd.Series,
    major: tuple[str, ...],
    pairing: Mapping[str, str],
) -> pd.DataFrame:
    """:attr:`MappedTracks.arms`: one row per recorded arm."""
    return pd.DataFrame(
        {
            "angle_deg": arm_angles,
            "entries": entries.to_numpy(),
            "exits": exits.to_numpy(),
            "major": np.isin(names, major),
            "layout_arm": [pairing[n] for n in names],
        },
        index=pd.Index(names, name="arm"),
    )


def _polar(x: pd.Series, y: pd.Series, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from ``centre`` [m] and angle [deg] of points."""
    radius = np.hypot(x - centre[0], y - centre[1]).to_numpy()
    angle = np.rad2deg(np.arctan2(y - centre[1], x - centre[0])).to_numpy()
    return radius, angle


def _layout_routes(
    pairing: Mapping[str, str],
    names: np.ndarray,
    k0: np.ndarray,
    k1: np.ndarray,
    ok: np.ndarray,
    maneuver: np.ndarray,
    layout: LayoutArms,
    options: MappingOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Each mapped track's route on the layout (``"<entry>-><exit>"`` of the layout's arms), and where
    the layout's own turn angles give another maneuver (they do not unless its arms are skewed)."""
    layout_name = np.array([pairing[n] for n in names], dtype=object)  # per recorded arm
    layout_deg = np.array([np.rad2deg(layout.angles[pairing[n]]) for n in names])
    route = np.where(ok, pd.Series(layout_name[k0]).str.cat(layout_name[k1], sep="->").to_numpy(), "")
    layout_turn = _wrap_deg(layout_deg[k1] - layout_deg[k0] - 180.0)
    return route, ok & (_maneuver(layout_turn, options.turn_threshold_deg) != maneuver)


# Columns of MappedTracks.tracks, in order.
MAPPED_COLUMNS = (
    "recording",
    "track_id",
    "class",
    "length",
    "width",
    "time",
    "speed",
    "min_speed",
    "stopped",
    "t_centre",
    "t_last",
    "min_distance",
    "hard_brakes",
    "energy_to_centre_j",
    "t_entry",
    "spawn_time",
    "entry_arm",
    "exit_arm",
    "turn_deg",
    "maneuver",
    "priority",
    "route",
    "mapped",
    "reason",
)


def _check_mapping_inputs(recordings: Sequence[Recording], options: MappingOptions, layout: LayoutArms) -> None:
    """Refuse what :func:`map_recordings` cannot map: no recordings, several sites, or ``arrival_timing``
    without the layout's route geometry."""
    if options.arrival_timing and layout.routes is None:
        raise ValueError(
            "arrival_timing needs the layout's route geometry (LayoutArms.routes, e.g. from "
            "layout_arms(build_layout('inD'))); pass such a layout or set arrival_timing=False"
        )
    if not recordings:
        raise ValueError("recordings: expected at least one recording")
    if len({r.location_id for r in recordings}) > 1:
        raise ValueError(
            f"recordings of several sites cannot be mapped together: locationId "
            f"{sorted({r.location_id for r in recordings})}"
        )


def _track_table(recordings: Sequence[Recording]) -> pd.DataFrame:
    """One row per track of every class: when it appears, what it is, and its :func:`track_summary`."""
    meta = pd.concat(
        [
            r.tracks_meta.assign(recording=r.recording_id, time=r.tracks_meta["initialFrame"] / r.frame_rate)
            for r in recordings
        ],
        ignore_index=True,
    )
    table = pd.DataFrame(
        {
            "recording": meta["recording"].astype(int),
            "track_id": meta["trackId"].astype(int),
            "class": meta["class"],
            "time": meta["time"].astype(float),
            "is_vehicle": meta["is_vehicle"],
            "length": meta["length"].astype(float) if "length" in meta else np.nan,
            "width": meta["width"].astype(float) if "width" in meta else np.nan,
        }
    )
    # Per recording, so that the frames of all recordings are never copied into one table.
    summary = pd.concat([track_summary(r.tracks.assign(recordingId=r.recording_id)) for r in recordings])
    summary = summary.rename_axis(["recording", "track_id"]).reset_index()
    table = table.merge(summary, on=["recording", "track_id"], how="left")
    table["speed"] = table.pop("speed0")
    table["stopped"] = table["min_speed"] < STOP_SPEED
    return table


def _centre(table: pd.DataFrame, moving: np.ndarray, options: MappingOptions) -> np.ndarray:
    """The intersection centre: ``options.centre``, or where the lines along which moving vehicles
    enter and leave meet (:func:`estimate_centre`)."""
    if options.centre is not None:
        return np.asarray(options.centre, dtype=float)
    pts = np.vstack([table.loc[moving, ["x0", "y0"]].to_numpy(), table.loc[moving, ["x1", "y1"]].to_numpy()])
    dirs = np.vstack([table.loc[moving, ["dx0", "dy0"]].to_numpy(), table.loc[moving, ["dx1", "dy1"]].to_numpy()])
    return estimate_centre(pts, dirs)


def _with_passages(table: pd.DataFrame, recordings: Sequence[Recording], centre: np.ndarray) -> pd.DataFrame:
    """``table`` with when and how close each vehicle passes the centre (one groupby over the frames
    of a recording), its hard brakes and its traction energy up to there."""
    passages = []
    for r in recordings:
        x, y = r.tracks["xCenter"].to_numpy(), r.tracks["yCenter"].to_numpy()
        dist = pd.Series(np.hypot(x - centre[0], y - centre[1]))
        closest = dist.groupby(r.tracks["trackId"].to_numpy()).idxmin().to_numpy()
        starts, energy = track_motion(r.tracks, r.frame_rate)
        brakes = pd.Series(starts).groupby(r.tracks["trackId"].to_numpy()).sum()
        passages.append(
            pd.DataFrame(
                {
                    "recording": r.recording_id,
                    "track_id": r.tracks["trackId"].to_numpy()[closest],
                    "centre_frame": r.tracks["frame"].to_numpy()[closest],
                    "min_distance": dist.to_numpy()[closest],
                    "hard_brakes": brakes.reindex(r.tracks["trackId"].to_numpy()[closest]).to_numpy(float),
                    "energy_to_centre_j": energy[closest],
                }
            )
        )
    passage = pd.concat(passages, ignore_index=True)
    table = table.merge(passage, on=["recording", "track_id"], how="left")
    frame_rate = table["recording"].map({r.recording_id: r.frame_rate for r in recordings})
    table["t_centre"] = table.pop("centre_frame") / frame_rate
    table["t_last"] = table["last_frame"] / frame_rate
    return table


def _nearest_arm(angle: np.ndarray, arm_angles: np.ndarray, tolerance_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the arm nearest to each angle, and whether it is within ``tolerance_deg``."""
    off = np.abs(_wrap_deg(angle[:, None] - arm_angles[None, :]))
    off = np.nan_to_num(off, nan=np.inf)
    k = off.argmin(axis=1)
    return k, off[np.arange(len(k)), k] <= tolerance_deg


def _first_reasons(table: pd.DataFrame, checks: Sequence[tuple[np.ndarray, str | None]]) -> np.ndarray:
    """Why each track is not mapped, the first check that applies winning (``""``: mapped; a ``None``
    reason: not modelled, with the track's class)."""
    reason = np.full(len(table), "", dtype=object)
    for mask, text in checks:
        fill = mask & (reason == "")
        if text is None:
            reason[fill] = ("not modelled: " + table["class"].astype(str)).to_numpy()[fill]
        else:
            reason[fill] = text
    return reason


def _major_road(entries: pd.Series, exits: pd.Series, names: np.ndarray, options: MappingOptions) -> tuple[str, ...]:
    """The major road: ``options.major_arms``, or the opposite pair of arms with the most mapped
    entries and exits."""
    if options.major_arms is not None:
        unknown = set(options.major_arms) - set(names)
        if unknown:
            raise ValueError(f"major_arms: {sorted(unknown)} are not arms of this site; its arms are {list(names)}")
        return tuple(options.major_arms)
    if options.num_arms % 2:
        raise ValueError(f"major_arms must be given for a site with {options.num_arms} arms")
    half = options.num_arms // 2
    traffic = (entries + exits).to_numpy()
    pair = int(np.argmax([traffic[k] + traffic[k + half] for k in range(half)]))
    return (str(names[pair]), str(names[pair + half]))


def _arrival_times(
    table: pd.DataFrame,
    recordings: Sequence[Recording],
    centre: np.ndarray,
    route: np.ndarray,
    ok: np.ndarray,
    layout: LayoutArms,
    options: MappingOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """``(t_entry, spawn_time)`` of every track: when each simulated vehicle must appear (vectorized
    over tracks; NaN where not mapped). Without ``arrival_timing``: no entry time, and it appears when
    the track does."""
    if not options.arrival_timing:
        return np.nan, np.where(ok, table["time"].to_numpy(float), np.nan)
    geometry = layout.routes.reindex(route)  # NaN rows where not mapped
    missing = sorted(set(route[ok & geometry["entry_arc"].isna().to_numpy()]))
    if missing:
        raise ValueError(f"arrival_timing: the layout's route geometry has no routes {missing}")
    if options.entry_radius is None:
        radius = geometry["entry_radius"].to_numpy()
    else:
        radius = np.where(ok, options.entry_radius, np.nan)
    entered = _entry_times(recordings, table, centre, radius)
    # Recorded initial speed, clipped to the lane's limit; slow starts count as the floor.
    limit = geometry["speed_limit"].to_numpy()
    speed = np.maximum(np.minimum(table["speed"].to_numpy(float), limit), options.min_timing_speed)
    # Never that close to the centre: closest approach minus the layout's travel to it.
    fallback = table["t_centre"].to_numpy(float) - geometry["inside"].to_numpy() / speed
    t_entry = np.where(ok, np.where(np.isnan(entered), fallback, entered), np.nan)
    length = table["length"].to_numpy(float)
    length = np.where(length > 0, length, DEFAULT_VEHICLE_LENGTH)  # NaN > 0 is False
    # The simulated centre starts half a length into the route and drives to the stop line.
    travel = geometry["entry_arc"].to_numpy() - length / 2
    return t_entry, np.where(ok, np.maximum(t_entry - travel / speed, 0.0), np.nan)


def _entry_times(
    recordings: Sequence[Recording], table: pd.DataFrame, centre: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """When each track's centre first came within ``radius`` of the centre [s], NaN if never.

    :param recordings: the recordings (their per-frame tables)
    :param table: one row per track with ``recording`` and ``track_id``
    :param centre: ``(2,)`` intersection centre [m]
    :param radius: per row of ``table``, NaN to skip the track [m]
    :return: per row of ``table``
    """
    found = []
    for r in recordings:  # one vectorized pass over the frames of each recording
        rows = (table["recording"] == r.recording_id).to_numpy()
        per_track = pd.Series(radius[rows], index=table["track_id"].to_numpy()[rows])
        track = r.tracks["trackId"].to_numpy()
        limit = per_track.reindex(track).to_numpy()
        x, y = r.tracks["xCenter"].to_numpy(), r.tracks["yCenter"].to_numpy()
        near = np.hypot(x - centre[0], y - centre[1]) < limit  # False where the limit is NaN
        first = pd.Series(r.tracks["frame"].to_numpy()[near]).groupby(track[near]).min()
        found.append(
            pd.DataFrame({"recording": r.recording_id, "track_id": first.index, "t": first.to_numpy() / r.frame_rate})
        )
    times = pd.concat(found, ignore_index=True)
    return table[["recording", "track_id"]].merge(times, on=["recording", "track_id"], how="left")["t"].to_numpy()


def scenario_records(mapped: MappedTracks, recording: int | None = None) -> pd.DataFrame:
    """The mapped vehicles as scenario rows for the simulated layout.

    :param mapped: the mapping
    :param recording: keep only this recording (``None``: all, times per recording)
    :return: columns ``time`` (appearance in simulation [s]: ``spawn_time``, see
        :class:`MappingOptions` ``arrival_timing``), ``route`` (layout route name), ``speed`` (initial
        speed [m/s]), ``vehicle_id`` (the trackId), ``recording``, ``maneuver``, ``length`` and
        ``width`` [m] (NaN where the recording does not give them), sorted by recording and time
    """
    rows = mapped.mapped
    if recording is not None:
        rows = rows[rows["recording"] == recording]
    out = pd.DataFrame(
        {
            "time": rows["spawn_time"].to_numpy(float),
            "route": rows["route"].to_numpy(str),
            "speed": rows["speed"].to_numpy(float),
            "vehicle_id": rows["track_id"].to_numpy(np.int64),
            "recording": rows["recording"].to_numpy(np.int64),
            "maneuver": rows["maneuver"].to_numpy(str),
            "length": rows["length"].to_numpy(float),
            "width": rows["width"].to_numpy(float),
        }
    )
    return out.sort_values(["recording", "time", "vehicle_id"], kind="stable").reset_index(drop=True)
