"""Intersection layouts: highway-env road networks plus the per-route arrays the simulation reads.

Every layout is a highway-env :class:`~highway_env.road.road.RoadNetwork` of
:class:`~highway_env.road.lane.StraightLane` and :class:`~highway_env.road.lane.CircularLane`
objects with right-hand traffic, lane priorities and speed limits. A *route* (``"<entry arm>-><exit
arm>"``) is the sequence of lanes from an arm's outer end through the intersection to another arm's
outer end. At build time every route is sampled into a polyline at a fixed spacing ``ds`` so that
positions and headings of all vehicles come from one vectorized gather plus interpolation
(:meth:`Layout.pose`), with no call into highway-env in the hot path.

Coordinate frame: highway-env's, ``x`` east and ``y`` *south* (the viewer draws ``+y`` downwards).
Arm ``"north"`` therefore lies towards ``-y``. :attr:`Layout.arm_angle` gives each arm's outward
direction as ``atan2(y, x)`` in this frame (north ``-pi/2``, east ``0``, south ``pi/2``, west ``pi``).
Data recorded in a right-handed frame with ``y`` north (inD) maps onto it by ``y -> -y`` and
``heading -> -heading``.

The intersection area of a route runs from the stop line (the end of its last incoming lane) to the
start of its exit lane; :attr:`Layout.entry_arc` and :attr:`Layout.exit_arc` give both as arc lengths
along the route.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field, fields
from functools import cache

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork

from envs.simulation.scene import LEFT, MAJOR, MINOR, RIGHT, STRAIGHT

LAYOUT_NAMES = ("4way", "3way", "inD")
ARM_ANGLES = {"east": 0.0, "south": np.pi / 2, "west": np.pi, "north": -np.pi / 2}

LANE_WIDTH = AbstractLane.DEFAULT_WIDTH  # 4 m
# The road's speed limit [m/s] (urban); on curved lanes the limit is lower, from the curvature:
# ``v_max = sqrt(a_lat_max / kappa)`` with the largest lateral acceleration below.
APPROACH_SPEED_LIMIT = 10.0
# Largest lateral acceleration on curved lanes [m/s^2]: a comfortable value for urban turns
# (drivers keep below about 3-4 m/s^2). On the default radii: right turn (9 m) 5.2 m/s, left turn
# (13 m) 6.2 m/s.
DEFAULT_LATERAL_ACCELERATION = 3.0
# Two routes conflict when their intersection parts come closer than this [m] (paths cross), or
# when they share the exit lane (paths merge). A vehicle is 2 m wide: parallel lanes 4 m apart
# stay apart, crossing paths reach 0.
CONFLICT_DISTANCE = 2.5
# Padding of every conflict zone on both ends [m]: the shield's default, which the observation's
# zone features use too (envs.simulation.graph).
ZONE_MARGIN = 1.5


@dataclass(frozen=True)
class ArmSpec:
    """One arm of an intersection (build-time description).

    :param name: ``"north"``, ``"east"``, ``"south"`` or ``"west"``
    :param priority: ``MAJOR`` or ``MINOR``
    :param stop_distance: distance of the stop line from the intersection centre [m]
    :param access_length: length of the incoming and the exit road outside the intersection [m]
    :param left_pocket: the left turn branches into its own lane before the stop line
    """

    name: str
    priority: int
    stop_distance: float
    access_length: float
    left_pocket: bool = False


@dataclass(eq=False)
class Layout:
    """An intersection: its road network and the sampled geometry of every route.

    Arrays indexed ``[route, sample]`` are padded by repeating each route's last sample.

    :param name: layout name (one of :data:`LAYOUT_NAMES`)
    :param network: the highway-env road network (used for rendering only)
    :param route_names: ``(R,)`` names ``"<entry arm>-><exit arm>"``
    :param route_lanes: lane indices ``(from, to, id)`` of each route, in driving order
    :param maneuver: ``(R,)`` ``LEFT``, ``STRAIGHT`` or ``RIGHT``
    :param priority: ``(R,)`` ``MAJOR``/``MINOR`` of the route's incoming road
    :param entry_arc: ``(R,)`` arc length where the route enters the intersection area [m]
    :param exit_arc: ``(R,)`` arc length where the route leaves the intersection area [m]
    :param length: ``(R,)`` total route length [m]
    :param conflicts: ``(R, R)`` bool, paths cross or merge inside the intersection
    :param arm_angle: arm name -> outward direction [rad] in the layout frame
    :param entry_arm: ``(R,)`` name of each route's entry arm
    :param exit_arm: ``(R,)`` name of each route's exit arm
    :param spawn_lanes: lane index of each spawn lane (the first lane of one or more routes)
    :param route_spawn_lane: ``(R,)`` index into ``spawn_lanes`` of each route's first lane
    :param spawn_priority: ``(S,)`` priority of each spawn lane
    :param ds: sample spacing [m]
    :param xy: ``(R, M, 2)`` sampled centre line
    :param heading: ``(R, M)`` unwrapped heading along the centre line [rad]
    :param speed_limit: ``(R, M)`` lane speed limit at each sample [m/s]
    :param lanes: every lane index of the network, position = global lane id
    :param route_lane_ids: ``(R, K)`` global lane ids along each route, padded with -1
    :param route_lane_starts: ``(R, K)`` arc length where each of them starts, padded with ``inf``
    :param lane_start: ``(R, Lg)`` arc length where global lane ``g`` starts on route ``r``;
        ``nan`` where the lane is not on the route
    :param touch_arc: ``(R,)`` arc length where the route leaves its spawn lane; before it, only
        vehicles on the same lane can touch (collision checks use this)
    :param zone_start: ``(R, R)`` arc length on route ``r`` (row) where its conflict zone with
        route ``q`` (column) starts [m]; ``nan`` where they do not conflict. A vehicle's body
        ``[arc - length / 2, arc + length / 2]`` occupies the zone while it overlaps
        ``[zone_start, zone_end]``
    :param zone_end: ``(R, R)`` where that zone ends [m]
    :param lateral_acceleration: largest lateral acceleration that set the curved lanes' limits [m/s^2]
    """

    name: str
    network: RoadNetwork
    route_names: tuple[str, ...]
    route_lanes: tuple[tuple[tuple[str, str, int], ...], ...]
    maneuver: np.ndarray
    priority: np.ndarray
    entry_arc: np.ndarray
    exit_arc: np.ndarray
    length: np.ndarray
    conflicts: np.ndarray
    arm_angle: dict[str, float]
    entry_arm: tuple[str, ...]
    exit_arm: tuple[str, ...]
    spawn_lanes: tuple[tuple[str, str, int], ...]
    route_spawn_lane: np.ndarray
    spawn_priority: np.ndarray
    ds: float
    xy: np.ndarray
    heading: np.ndarray
    speed_limit: np.ndarray
    lanes: tuple[tuple[str, str, int], ...]
    route_lane_ids: np.ndarray
    route_lane_starts: np.ndarray
    lane_start: np.ndarray
    touch_arc: np.ndarray
    zone_start: np.ndarray
    zone_end: np.ndarray
    lateral_acceleration: float = DEFAULT_LATERAL_ACCELERATION
    route_index: dict[str, int] = field(default_factory=dict)
    _envelopes: dict[float, np.ndarray] = field(default_factory=dict, repr=False)
    _envelopes_squared: dict[float, np.ndarray] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.route_index = {name: i for i, name in enumerate(self.route_names)}
        # One layout serves every simulation, shield and planner of the process (build_layout's
        # cache): its arrays are read-only down to their buffers, so no planner changes the physics.
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                setattr(self, f.name, read_only(value))
        self._sealed = True

    def __setattr__(self, name: str, value) -> None:
        if getattr(self, "_sealed", False):
            raise AttributeError(f"Layout is read-only (one layout serves the whole process): cannot set {name!r}")
        object.__setattr__(self, name, value)

    def speed_envelope(self, deceleration: float) -> np.ndarray:
        """``(R, M)`` highest speed at each sample from which every lower limit ahead can still be
        met braking at ``deceleration``: ``min_{k' >= k} sqrt(limit[k']^2 + 2 b (k' - k) ds)``.

        Computed once per deceleration (a backward pass over the samples, vectorized over routes).

        :param deceleration: braking deceleration ``b`` [m/s^2], positive
        :return: the envelope [m/s] (never above the limit itself)
        """
        key = float(deceleration)
        if key not in self._envelopes:
            env = self.speed_limit.copy()
            step = 2.0 * key * self.ds
            for k in range(env.shape[1] - 2, -1, -1):
                env[:, k] = np.minimum(env[:, k], np.sqrt(env[:, k + 1] ** 2 + step))
            self._envelopes[key] = read_only(env)
        return self._envelopes[key]

    def envelope_at(self, route: np.ndarray, arc: np.ndarray, deceleration: float) -> np.ndarray:
        """:meth:`speed_envelope` at points on routes [m/s], never above :meth:`limit_at` there.

        The squared speed is interpolated linearly between samples: on a braking stretch it falls
        at exactly ``2 b`` per metre, so following the envelope takes deceleration ``b``.
        """
        key = float(deceleration)
        squared = self._envelopes_squared.get(key)
        if squared is None:  # the speed governor calls this every sub-step: square the table once
            squared = self._envelopes_squared[key] = read_only(self.speed_envelope(key) ** 2)
        last = squared.shape[1] - 1
        u = np.minimum(np.maximum(arc / self.ds, 0.0), last)
        k = u.astype(np.int64)  # the sample of limit_at: clipping before truncating gives the same index
        i0 = np.minimum(k, last - 1)
        sq0 = squared[route, i0]
        return np.minimum(np.sqrt(sq0 + (squared[route, i0 + 1] - sq0) * (u - i0)), self.speed_limit[route, k])

    @property
    def num_routes(self) -> int:
        return len(self.route_names)

    @property
    def arms(self) -> tuple[str, ...]:
        return tuple(self.arm_angle)

    def route_id(self, name: str) -> int:
        """Index of a route by name.

        :param name: ``"<entry arm>-><exit arm>"``
        :raises ValueError: for a route this layout does not have
        """
        if name not in self.route_index:
            raise ValueError(f"layout {self.name!r} has no route {name!r}; routes: {list(self.route_names)}")
        return self.route_index[name]

    def spawn_routes(self, spawn: int) -> np.ndarray:
        """Routes that start on spawn lane ``spawn``."""
        return np.flatnonzero(self.route_spawn_lane == spawn)

    # ------------------------------------------------------------------ vectorized lookups
    def pose(self, route: np.ndarray, arc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and headings of points on routes (linear interpolation of the samples).

        :param route: ``(n,)`` route indices (or any shape that broadcasts against ``arc``)
        :param arc: ``(n,)`` arc lengths along the routes [m] (or any shape, e.g. ``(times, n)``)
        :return: ``(n, 2)`` positions and ``(n,)`` headings wrapped to ``(-pi, pi]`` (in general:
            ``arc``'s shape plus 2, and ``arc``'s shape)
        """
        last = self.xy.shape[1] - 1
        u = np.minimum(np.maximum(arc / self.ds, 0.0), last)
        i0 = np.minimum(u.astype(np.int64), last - 1)
        f = u - i0
        p0, p1 = self.xy[route, i0], self.xy[route, i0 + 1]
        xy = p0 + (p1 - p0) * f[..., None]
        h0 = self.heading[route, i0]
        h = h0 + (self.heading[route, i0 + 1] - h0) * f
        return xy, (h + np.pi) % (2 * np.pi) - np.pi

    def limit_at(self, route: np.ndarray, arc: np.ndarray) -> np.ndarray:
        """Lane speed limit at points on routes [m/s]."""
        return self.speed_limit[route, self._sample(arc)]

    def highest_limit(self, route: np.ndarray, arc: np.ndarray, until: np.ndarray) -> np.ndarray:
        """The highest lane speed limit on each route from ``arc`` to ``until`` (the samples that
        :meth:`limit_at` reads there and between; ``until <= arc``: the limit at ``arc``) [m/s]."""
        first = self._sample(np.asarray(arc, float))
        last = np.maximum(self._sample(np.asarray(until, float)), first)
        k = np.arange(self.speed_limit.shape[1])
        between = (k >= first[:, None]) & (k <= last[:, None])
        return np.where(between, self.speed_limit[route], -np.inf).max(axis=1)

    def _sample(self, arc: np.ndarray) -> np.ndarray:
        """Index of the limit-table sample that holds each arc (clipped to the table)."""
        return np.minimum(np.maximum((arc / self.ds).astype(np.int64), 0), self.speed_limit.shape[1] - 1)

    def lane_at(self, route: np.ndarray, arc: np.ndarray) -> np.ndarray:
        """Global lane id of points on routes (exact: compares with the lanes' start arcs).

        :param route: ``(n,)`` route indices
        :param arc: ``(n,)`` arc lengths, or ``(p, n)``: ``p`` points on each route (one comparison)
        :return: lane ids of the shape of ``arc``
        """
        k = (self.route_lane_starts[route] <= arc[..., None]).sum(axis=-1) - 1
        return self.route_lane_ids[route, np.maximum(k, 0)]


_PARTING: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def parting_arcs(layout: Layout) -> np.ndarray:
    """``(R, R)`` arc on route ``r`` (row) from which its centre line stays at least the layout's
    conflict distance from route ``q``'s (column), for two routes that leave the same spawn lane;
    ``-inf`` for every other pair (their vehicles meet in conflict zones or on one lane). Where two
    such paths split, a vehicle whose rear is still before this arc of its route overlaps the other
    path: the simulation keeps it the leader of the other branch's vehicles, and the shield predicts
    the pair as a follow pair until then. Cached per layout."""
    if layout not in _PARTING:
        num_r, ds = layout.num_routes, layout.ds
        out = np.full((num_r, num_r), -np.inf)
        spawn = layout.route_spawn_lane
        for a, b in zip(*np.nonzero((spawn[:, None] == spawn[None, :]) & ~np.eye(num_r, dtype=bool))):
            n = int(layout.length[a] / ds) + 1
            near = np.linalg.norm(layout.xy[a, :n, None] - layout.xy[b, None], axis=-1).min(axis=1) < CONFLICT_DISTANCE
            out[a, b] = (np.flatnonzero(near).max() + 1) * ds
        _PARTING[layout] = out
    return _PARTING[layout]


_HULLS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def zone_hull(layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    """``(R,)`` arcs where each route's first conflict zone starts and its last one ends (``inf``,
    ``-inf`` for a route without any); cached per layout (the shield and the observation read them
    at every step).

    :param layout: the intersection
    """
    if layout not in _HULLS:
        zs, ze = layout.zone_start, layout.zone_end
        with np.errstate(invalid="ignore"):
            first = np.where(np.isnan(zs), np.inf, zs).min(axis=1)
            last = np.where(np.isnan(ze), -np.inf, ze).max(axis=1)
        _HULLS[layout] = read_only(first), read_only(last)
    return _HULLS[layout]


def body_hull(
    layout: Layout, route: np.ndarray, length: np.ndarray, margin: float = ZONE_MARGIN
) -> tuple[np.ndarray, np.ndarray]:
    """``(n,)`` centre arcs from which each body may touch its route's first conflict zone, and past
    which it has left the last one, each zone padded by ``margin`` (``inf`` and ``-inf`` for a route
    without any): where the shield's rules and the observation's zone features start and end.

    :param layout: the intersection
    :param route: ``(n,)`` route of each vehicle
    :param length: ``(n,)`` vehicle lengths [m]
    :param margin: padding of every zone on both ends [m]
    """
    first, last = zone_hull(layout)
    return first[route] - margin - length / 2, last[route] + margin + length / 2


def read_only(array: np.ndarray) -> np.ndarray:
    """A read-only copy of an array whose buffer is an immutable ``bytes`` object, so that neither
    ``setflags(write=True)`` on it nor on its base can make it writable again.

    :param array: any array of a fixed-size dtype
    :return: the copy (same dtype and shape)
    """
    array = np.ascontiguousarray(array)
    return np.frombuffer(array.tobytes(), dtype=array.dtype).reshape(array.shape)


# ---------------------------------------------------------------------- geometry helpers
def _rot(angle: float) -> np.ndarray:
    return np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])


def _right_of(direction: np.ndarray) -> np.ndarray:
    # y points down on screen: rotating by +90 deg turns a heading to its right-hand side.
    return _rot(np.pi / 2) @ direction


def _connector(
    start: np.ndarray, h_in: np.ndarray, end: np.ndarray, h_out: np.ndarray, speed_limit: float, priority: int
) -> list[AbstractLane]:
    """Lanes from ``start`` (heading ``h_in``) to ``end`` (heading ``h_out``).

    Parallel headings: one straight lane (diagonal when the lateral offsets differ). Perpendicular
    headings: a fillet, i.e. the largest circular arc tangent to both lines, with straight pieces
    where one leg is longer than the other.
    """
    n = LineType.NONE
    cross = h_in[0] * h_out[1] - h_in[1] * h_out[0]
    if abs(cross) < 1e-6:
        return [StraightLane(start, end, line_types=(n, n), priority=priority, speed_limit=speed_limit)]
    # Corner: where the incoming line meets the outgoing line.
    t, u = np.linalg.solve(np.stack([h_in, h_out], axis=1), end - start)
    corner = start + t * h_in
    radius = min(t, u)
    p_arc0, p_arc1 = corner - radius * h_in, corner + radius * h_out
    turn_right = cross > 0  # y down: positive cross product = clockwise on screen = right turn
    normal = _right_of(h_in) if turn_right else -_right_of(h_in)
    centre = p_arc0 + radius * normal
    phi0 = float(np.arctan2(*(p_arc0 - centre)[::-1]))
    phi1 = float(np.arctan2(*(p_arc1 - centre)[::-1]))
    # highway-env CircularLane: clockwise=True means increasing angle (in the y-down frame).
    dphi = (phi1 - phi0 + np.pi) % (2 * np.pi) - np.pi
    lanes: list[AbstractLane] = []
    if t - radius > 1e-6:
        lanes.append(StraightLane(start, p_arc0, line_types=(n, n), priority=priority, speed_limit=speed_limit))
    lanes.append(
        CircularLane(
            centre,
            radius,
            phi0,
            phi0 + dphi,
            clockwise=dphi > 0,
            line_types=(n, n),
            priority=priority,
            speed_limit=speed_limit,
        )
    )
    if u - radius > 1e-6:
        lanes.append(StraightLane(p_arc1, end, line_types=(n, n), priority=priority, speed_limit=speed_limit))
    return lanes


def _maneuver(h_in: np.ndarray, h_out: np.ndarray) -> int:
    cross = h_in[0] * h_out[1] - h_in[1] * h_out[0]
    dot = float(h_in @ h_out)
    if dot > np.cos(np.radians(45)):
        return STRAIGHT
    return RIGHT if cross > 0 else LEFT


# ---------------------------------------------------------------------- building
# A lane of the road network: (from node, to node, index).
_LaneKey = tuple[str, str, int]
# A route while the layout is built: (name, lanes, maneuver, priority, entry arm, exit arm, upstream lanes).
_Route = tuple[str, list[_LaneKey], int, int, str, str, int]


def _build(name: str, arms: list[ArmSpec], ds: float, lateral_acceleration: float) -> Layout:
    """The layout of ``arms``: its road network, its routes from every arm to every other one, their
    sampled geometry and speed limits, its spawn lanes and its conflict zones."""
    net = RoadNetwork()
    stops, exits = _add_arms(net, arms)
    routes = _add_routes(net, arms, stops, exits)
    arm_angle = {arm.name: float(ARM_ANGLES[arm.name]) for arm in arms}
    return layout_from_routes(name, net, routes, arm_angle, ds, lateral_acceleration)


def layout_from_routes(
    name: str,
    net: RoadNetwork,
    routes: list[_Route],
    arm_angle: dict[str, float],
    ds: float,
    lateral_acceleration: float,
) -> Layout:
    """The layout of a road network whose routes are known: their sampled geometry and speed limits, the spawn
    lanes and the conflict zones (our layouts, and a junction read from a SUMO network).

    :param name: the layout's name
    :param net: the road network that holds every lane of the routes
    :param routes: ``(name, lanes, maneuver, priority, entry arm, exit arm, upstream lanes)`` per route: its lane
        keys in driving order, and how many of them lie before the stop line
    :param arm_angle: arm name -> outward direction [rad] in the layout frame
    :param ds: sample spacing [m]
    :param lateral_acceleration: largest lateral acceleration that sets the limits of curves [m/s^2]
    """
    tables = _route_tables(net, routes, ds, lateral_acceleration)
    spawn_lanes, route_spawn, priority, spawn_priority = _spawn_lanes(routes)
    conflicts, zone_start, zone_end = _conflicts(routes, tables["xy"], tables["entry_arc"], tables["exit_arc"], ds)
    return Layout(
        name=name,
        network=net,
        route_names=tuple(r[0] for r in routes),
        route_lanes=tuple(tuple(r[1]) for r in routes),
        maneuver=np.array([r[2] for r in routes], np.int64),
        priority=priority,
        entry_arc=tables["entry_arc"],
        exit_arc=tables["exit_arc"],
        length=tables["length"],
        conflicts=conflicts,
        arm_angle=dict(arm_angle),
        entry_arm=tuple(r[4] for r in routes),
        exit_arm=tuple(r[5] for r in routes),
        spawn_lanes=tuple(spawn_lanes),
        route_spawn_lane=route_spawn,
        spawn_priority=spawn_priority,
        ds=ds,
        xy=tables["xy"],
        heading=tables["heading"],
        speed_limit=tables["speed_limit"],
        lanes=tables["lanes"],
        route_lane_ids=tables["route_lane_ids"],
        route_lane_starts=tables["route_lane_starts"],
        lane_start=tables["lane_start"],
        touch_arc=tables["route_lane_starts"][:, 1].copy(),
        zone_start=zone_start,
        zone_end=zone_end,
        lateral_acceleration=lateral_acceleration,
    )


def _add_arms(net: RoadNetwork, arms: list[ArmSpec]) -> tuple[dict, dict]:
    """Add every arm's approach and exit lanes to ``net``.

    :return: ``stops``: ``(arm, maneuver) -> (stop node, stop point, inward heading, upstream lanes)``;
        ``exits``: ``arm -> (exit node, exit point, outward heading, exit lane)``
    """
    c, n = LineType.CONTINUOUS, LineType.NONE
    w = LANE_WIDTH
    stops: dict[tuple[str, int], tuple[str, np.ndarray, np.ndarray, list]] = {}
    exits: dict[str, tuple[str, np.ndarray, np.ndarray, _LaneKey]] = {}
    for arm in arms:
        angle = ARM_ANGLES[arm.name]
        out = np.array([np.cos(angle), np.sin(angle)])  # outward
        far = arm.stop_distance + arm.access_length
        prio = 3 if arm.priority == MAJOR else 1
        stops.update(_add_approach(net, arm, out, far, prio))
        a = arm.name
        # Exit lane: right-hand side of the outgoing direction.
        right_out = _right_of(out)
        p_exit = out * arm.stop_distance + right_out * (w / 2)
        p_out = out * far + right_out * (w / 2)
        net.add_lane(
            f"{a}_exit",
            f"{a}_out",
            StraightLane(p_exit, p_out, line_types=(n, c), priority=prio, speed_limit=APPROACH_SPEED_LIMIT),
        )
        exits[a] = (f"{a}_exit", p_exit, out, (f"{a}_exit", f"{a}_out", 0))
    return stops, exits


def _add_approach(net: RoadNetwork, arm: ArmSpec, out: np.ndarray, far: float, prio: int) -> dict:
    """Add one arm's approach lanes to ``net``: one lane to the stop line, or with ``left_pocket`` a
    shared lane that splits into a through lane and an isolated left-turn pocket.

    :return: ``(arm, maneuver) -> (stop node, stop point, inward heading, upstream lanes)``
    """
    c, s, n = LineType.CONTINUOUS, LineType.STRIPED, LineType.NONE
    w = LANE_WIDTH
    h_in = -out
    right_in = _right_of(h_in)
    a = arm.name
    if not arm.left_pocket:
        p_far = out * far + right_in * (w / 2)
        p_stop = out * arm.stop_distance + right_in * (w / 2)
        net.add_lane(
            f"{a}_in",
            f"{a}_stop",
            StraightLane(p_far, p_stop, line_types=(s, c), priority=prio, speed_limit=APPROACH_SPEED_LIMIT),
        )
        return {(a, m): (f"{a}_stop", p_stop, h_in, [(f"{a}_in", f"{a}_stop", 0)]) for m in (LEFT, STRAIGHT, RIGHT)}
    # Shared upstream lane, then the through lane moves one lane to the right while the
    # left-turn pocket continues straight on: the left turn gets an isolated lane.
    split = arm.stop_distance + 30.0
    p_far = out * far + right_in * (w / 2)
    p_split = out * split + right_in * (w / 2)
    net.add_lane(
        f"{a}_in",
        f"{a}_split",
        StraightLane(p_far, p_split, line_types=(s, c), priority=prio, speed_limit=APPROACH_SPEED_LIMIT),
    )
    p_stop = out * arm.stop_distance + right_in * (1.5 * w)
    net.add_lane(
        f"{a}_split",
        f"{a}_stop",
        StraightLane(p_split, p_stop, line_types=(n, c), priority=prio, speed_limit=APPROACH_SPEED_LIMIT),
    )
    p_lstop = out * arm.stop_distance + right_in * (w / 2)
    net.add_lane(
        f"{a}_split",
        f"{a}_lstop",
        StraightLane(p_split, p_lstop, line_types=(s, n), priority=prio, speed_limit=APPROACH_SPEED_LIMIT),
    )
    up = [(f"{a}_in", f"{a}_split", 0)]
    through = (f"{a}_stop", p_stop, h_in, up + [(f"{a}_split", f"{a}_stop", 0)])
    return {
        (a, STRAIGHT): through,
        (a, RIGHT): through,
        (a, LEFT): (f"{a}_lstop", p_lstop, h_in, up + [(f"{a}_split", f"{a}_lstop", 0)]),
    }


def _add_routes(net: RoadNetwork, arms: list[ArmSpec], stops: dict, exits: dict) -> list[_Route]:
    """Add the connector lanes from every arm to every other one to ``net``; the routes, in the order
    of ``arms`` (entry, then exit)."""
    routes: list[_Route] = []
    for arm_in in arms:
        for arm_out in arms:
            if arm_in.name == arm_out.name:
                continue
            h_in = -np.array([np.cos(ARM_ANGLES[arm_in.name]), np.sin(ARM_ANGLES[arm_in.name])])
            exit_node, p_exit, h_out, exit_lane = exits[arm_out.name]
            m = _maneuver(h_in, h_out)
            stop_node, p_stop, _, up_lanes = stops[(arm_in.name, m)]
            limit = APPROACH_SPEED_LIMIT  # curved pieces: lowered by the curvature (_sample_limits)
            prio = 3 if arm_in.priority == MAJOR else 1
            # Left turns yield to straight traffic: one priority level lower, as in highway-env.
            lane_prio = prio - 1 if m == LEFT else prio
            pieces = _connector(p_stop, h_in, p_exit, h_out, limit, lane_prio)
            nodes = [stop_node] + [f"{arm_in.name}>{arm_out.name}_{k}" for k in range(len(pieces) - 1)] + [exit_node]
            con_lanes = []
            for k, lane in enumerate(pieces):
                net.add_lane(nodes[k], nodes[k + 1], lane)
                con_lanes.append((nodes[k], nodes[k + 1], len(net.graph[nodes[k]][nodes[k + 1]]) - 1))
            lanes = list(up_lanes) + con_lanes + [exit_lane]
            name = f"{arm_in.name}->{arm_out.name}"
            routes.append((name, lanes, m, arm_in.priority, arm_in.name, arm_out.name, len(up_lanes)))
    return routes


def _route_tables(net: RoadNetwork, routes: list[_Route], ds: float, lateral_acceleration: float) -> dict:
    """The global lane table, every route's lanes and arc lengths, and its geometry sampled every
    ``ds`` metres (positions, headings, speed limits; padded with the last sample to one length)."""
    all_lanes: list[_LaneKey] = []
    for _, lanes, *_ in routes:
        for li in lanes:
            if li not in all_lanes:
                all_lanes.append(li)
    lane_id = {li: g for g, li in enumerate(all_lanes)}
    num_r = len(routes)
    k_max = max(len(r[1]) for r in routes)
    route_lane_ids = -np.ones((num_r, k_max), np.int64)
    route_lane_starts = np.full((num_r, k_max), np.inf)
    lane_start = np.full((num_r, len(all_lanes)), np.nan)
    lengths = np.zeros(num_r)
    entry_arc = np.zeros(num_r)
    exit_arc = np.zeros(num_r)
    samples_xy, samples_h, samples_v = [], [], []
    for r, (_, lanes, _, _, _, _, n_up) in enumerate(routes):
        objs = [net.get_lane(li) for li in lanes]
        starts = np.concatenate([[0.0], np.cumsum([lane.length for lane in objs])])
        lengths[r] = starts[-1]
        entry_arc[r] = starts[n_up]
        exit_arc[r] = starts[-2]
        for k, li in enumerate(lanes):
            route_lane_ids[r, k] = lane_id[li]
            route_lane_starts[r, k] = starts[k]
            lane_start[r, lane_id[li]] = starts[k]
        arcs = np.arange(0.0, lengths[r] + ds, ds)
        arcs[-1] = min(arcs[-1], lengths[r])
        k_of = np.clip(np.searchsorted(starts, arcs, side="right") - 1, 0, len(objs) - 1)
        samples_xy.append(np.array([objs[k].position(a - starts[k], 0.0) for a, k in zip(arcs, k_of)]))
        samples_h.append(np.unwrap(np.array([objs[k].heading_at(a - starts[k]) for a, k in zip(arcs, k_of)])))
        samples_v.append(np.array([_lane_limit(objs[k], lateral_acceleration) for k in k_of]))
    m_max = max(len(x) for x in samples_xy)

    def pad(arrs: list[np.ndarray]) -> np.ndarray:
        return np.stack([np.concatenate([x, np.repeat(x[-1:], m_max - len(x), axis=0)]) for x in arrs])

    xy, heading, speed_limit = pad(samples_xy), pad(samples_h), pad(samples_v)
    speed_limit = np.minimum(speed_limit, _kink_limits(heading, speed_limit, ds, lateral_acceleration))
    return {
        "lanes": tuple(all_lanes),
        "route_lane_ids": route_lane_ids,
        "route_lane_starts": route_lane_starts,
        "lane_start": lane_start,
        "length": lengths,
        "entry_arc": entry_arc,
        "exit_arc": exit_arc,
        "xy": xy,
        "heading": heading,
        "speed_limit": speed_limit,
    }


def _spawn_lanes(routes: list[_Route]) -> tuple[list[_LaneKey], np.ndarray, np.ndarray, np.ndarray]:
    """The spawn lanes (the distinct first lanes of the routes), each route's spawn lane, the routes'
    priorities and each spawn lane's priority."""
    spawn_lanes: list[_LaneKey] = []
    for _, lanes, *_ in routes:
        if lanes[0] not in spawn_lanes:
            spawn_lanes.append(lanes[0])
    route_spawn = np.array([spawn_lanes.index(r[1][0]) for r in routes], np.int64)
    priority = np.array([r[3] for r in routes], np.int64)
    spawn_priority = np.array([priority[route_spawn == k][0] for k in range(len(spawn_lanes))], np.int64)
    return spawn_lanes, route_spawn, priority, spawn_priority


# Half-width of the stretch around a kink over which its limit holds [m]: more than a vehicle moves in one
# simulation sub-step at the speed cap (20 m/s at 15 Hz: 1.33 m), so that the governor, which looks up the
# limit where a sub-step starts and where it would end, never steps over it.
KINK_REACH = 2.0


def _kink_limits(heading: np.ndarray, limit: np.ndarray, ds: float, lateral_acceleration: float) -> np.ndarray:
    """``(R, M)`` speed limits from the true heading change where lanes join at a kink (inD's lane shifts).

    The curvature of sample interval ``i`` is ``|heading[i + 1] - heading[i]| / ds``, and
    ``sqrt(a_lat / kappa)`` the speed at which it takes ``a_lat``. Where that is below the lane limits
    on both sides of the interval (a join the lanes' own limits do not know of; circular lanes are
    already limited), it holds within :data:`KINK_REACH` of the interval; elsewhere ``inf``.
    """
    kappa = np.abs(np.diff(heading, axis=1)) / ds  # (R, M - 1)
    with np.errstate(divide="ignore"):
        curve = np.sqrt(lateral_acceleration / kappa)
    known = np.minimum(limit[:, :-1], limit[:, 1:])
    kink = np.where(curve < 0.95 * known, curve, np.inf)
    kink = np.concatenate([kink, np.full((kink.shape[0], 1), np.inf)], axis=1)  # (R, M): sample i = interval i
    reach = int(np.ceil(KINK_REACH / ds))
    padded = np.pad(kink, ((0, 0), (reach, reach)), constant_values=np.inf)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * reach + 1, axis=1)
    return windows.min(axis=-1)


def _lane_limit(lane: AbstractLane, lateral_acceleration: float) -> float:
    """The road's limit, lowered on a circular lane to ``sqrt(a_lat_max * radius)``."""
    if isinstance(lane, CircularLane):
        return float(min(lane.speed_limit, np.sqrt(lateral_acceleration * lane.radius)))
    return float(lane.speed_limit)


def _conflicts(
    routes: list, xy: np.ndarray, entry_arc: np.ndarray, exit_arc: np.ndarray, ds: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Conflict matrix and conflict zones from the sampled geometry (build time only).

    Two routes conflict when they enter the intersection from different stop lines and either
    leave it on the same exit lane (merge) or their intersection parts come closer than
    :data:`CONFLICT_DISTANCE` (cross). Routes from the same stop line diverge and do not conflict.

    The conflict zone of route ``a`` with route ``b`` is the stretch of ``a``'s centre line, inside
    the intersection, that comes closer than :data:`CONFLICT_DISTANCE` to ``b``'s (for a merge: from
    there to ``a``'s intersection exit, where car following takes over).

    :return: ``(R, R)`` bool conflicts, ``(R, R)`` zone start and ``(R, R)`` zone end arcs on the
        row's route [m] (``nan`` where the routes do not conflict)
    """
    num_r = len(routes)
    stop_lane = [r[1][r[6] - 1] for r in routes]
    exit_lane = [r[1][-1] for r in routes]
    parts, offsets = [], []
    for r in range(num_r):
        i0, i1 = int(np.ceil(entry_arc[r] / ds)), int(np.floor(exit_arc[r] / ds)) + 1
        parts.append(xy[r, i0:i1])
        offsets.append(i0)
    out = np.zeros((num_r, num_r), bool)
    start = np.full((num_r, num_r), np.nan)
    end = np.full((num_r, num_r), np.nan)
    for a in range(num_r):
        for b in range(a + 1, num_r):
            if stop_lane[a] == stop_lane[b]:
                continue
            dist = np.linalg.norm(parts[a][:, None] - parts[b][None], axis=-1)
            merge = exit_lane[a] == exit_lane[b]
            if not (merge or dist.min() < CONFLICT_DISTANCE):
                continue
            out[a, b] = out[b, a] = True
            for r, d in ((a, dist.min(axis=1)), (b, dist.min(axis=0))):
                near = np.flatnonzero(d < CONFLICT_DISTANCE)
                if near.size == 0:  # a merge whose paths only meet on the exit lane
                    near = np.array([d.size - 1])
                start[r, b if r == a else a] = (offsets[r] + near[0]) * ds
                end[r, b if r == a else a] = exit_arc[r] if merge else (offsets[r] + near[-1]) * ds
    return out, start, end


@cache
def build_layout(
    name: str, ds: float = 0.5, lateral_acceleration: float = DEFAULT_LATERAL_ACCELERATION, access_length: float = 80.0
) -> Layout:
    """Build (once per process, then cached) one of the intersection layouts.

    - ``"4way"``: the paper's synthetic four-way intersection; the west-east road is the major
      (priority) road, the north-south road the minor one; one lane per direction.
    - ``"3way"``: a T junction, major road west-east, minor arm to the south.
    - ``"inD"``: an approximation of the inD four-way (Bendplatz / Frankenburg): priority road
      west-east with an isolated left-turn lane on each major arm, minor road north-south.

    The returned object is shared: treat it as read-only.

    :param name: one of :data:`LAYOUT_NAMES`
    :param ds: sample spacing of the route polylines [m]
    :param lateral_acceleration: largest lateral acceleration on curved lanes [m/s^2]; sets their
        speed limits (``sqrt(a_lat * radius)``, at most the road's limit)
    :param access_length: length of every incoming and exit road outside the intersection [m] (80: the layouts
        the environments use; a longer one, written as a SUMO network, holds more vehicles: ``net:FILE``)
    :return: the layout
    """
    if name not in LAYOUT_NAMES:
        raise ValueError(f"layout must be one of {LAYOUT_NAMES}, got {name!r}")
    if not ds > 0:
        raise ValueError(f"ds must be > 0, got {ds}")
    if not lateral_acceleration > 0:
        raise ValueError(f"lateral_acceleration must be > 0, got {lateral_acceleration}")
    if not access_length > 0:
        raise ValueError(f"access_length must be > 0, got {access_length}")
    stop = LANE_WIDTH + 5 + LANE_WIDTH / 2  # as highway-env's intersection: right-turn radius 9 m
    access = float(access_length)
    if name == "4way":
        arms = [
            ArmSpec(a, MAJOR if a in ("east", "west") else MINOR, stop, access)
            for a in ("south", "west", "north", "east")
        ]
    elif name == "3way":
        arms = [ArmSpec(a, MAJOR if a in ("east", "west") else MINOR, stop, access) for a in ("south", "west", "east")]
    else:
        arms = [
            ArmSpec("south", MINOR, 14.0, access),
            ArmSpec("west", MAJOR, 14.0, access, left_pocket=True),
            ArmSpec("north", MINOR, 14.0, access),
            ArmSpec("east", MAJOR, 14.0, access, left_pocket=True),
        ]
    return _build(name, arms, float(ds), float(lateral_acceleration))
