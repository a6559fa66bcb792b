"""One junction of any SUMO network (``.net.xml``, e.g. one that ``netconvert`` made from OpenStreetMap) as a
:class:`~envs.simulation.layouts.Layout`.

The network must hold exactly one junction with connections (the far ends of its roads are dead ends). Every
connection of that junction from an incoming lane to an outgoing lane (U-turns left out) is a route: the
incoming lane's shape, the junction's internal lane(s) of the connection, and the outgoing lane's shape, read
with ``sumolib``. The stop line is the end of the incoming lane, the exit the start of the outgoing one; speed
limits are the lanes' (lowered on curves as in our layouts), and the conflict zones are computed from the
sampled routes as in our layouts (:func:`envs.simulation.layouts.layout_from_routes`).

Arms are named by the compass direction they leave the junction in (``x`` east, ``y`` north in SUMO; at most one
arm per direction); a route is ``"<entry arm>-><exit arm>"``, with ``"@<lane>"`` after the entry arm where the
same two arms are joined from several incoming lanes. The roads of the incoming edges with the highest SUMO
priority are the major road, the others minor. Coordinates are shifted so that the junction lies at the origin,
and flipped into the layout frame (``y`` south).

A file that is not a SUMO network, or that holds no junction or more than one, is a :class:`NetFileError`: one
line naming the file and what is wrong.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
from highway_env.road.lane import LineType, PolyLaneFixedWidth
from highway_env.road.road import RoadNetwork

from envs.simulation.layouts import (
    ARM_ANGLES,
    DEFAULT_LATERAL_ACCELERATION,
    LAYOUT_NAMES,
    Layout,
    _maneuver,
    build_layout,
    layout_from_routes,
)
from envs.simulation.scene import LEFT, MAJOR, MINOR, RIGHT, STRAIGHT

# A layout name that reads a SUMO network: "net:<path of the .net.xml>" (the environment's ``layout`` config key,
# a scenario file's ``layout`` field).
NET_PREFIX = "net:"
LAYOUT_HELP = f"one of {LAYOUT_NAMES}, or '{NET_PREFIX}FILE' (the one junction of a SUMO .net.xml)"
# SUMO's connection directions -> our maneuvers (partial ones as the full ones; "t" is a U-turn: left out)
_DIRECTIONS = {"s": STRAIGHT, "l": LEFT, "L": LEFT, "r": RIGHT, "R": RIGHT}
# A junction's internal lane is resampled at this spacing [m] and averaged over this window [m] (_smoothed).
INTERNAL_SPACING = 0.25
SMOOTHING_WINDOW = 1.0


class NetFileError(ValueError):
    """A SUMO network that cannot be read as one junction (the message is one line naming the file)."""


class _Polyline(PolyLaneFixedWidth):
    """A lane along a polyline: its position exact on every segment, its heading continuous (highway-env's
    polyline lane looks both up every metre)."""

    def __init__(self, points: np.ndarray, width: float, speed_limit: float, priority: int) -> None:
        none = LineType.NONE
        super().__init__(
            [tuple(p) for p in points], width=width, line_types=(none, none), speed_limit=speed_limit,
            priority=priority,
        )  # fmt: skip
        self._points = np.asarray(points, float)
        step = np.diff(self._points, axis=0)
        self._starts = np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])
        self._headings = np.arctan2(step[:, 1], step[:, 0])
        self.length = float(self._starts[-1])

    @property
    def points(self) -> np.ndarray:
        """``(k, 2)`` the polyline (the SUMO network written from a layout gives edges this shape)."""
        return self._points

    def _segment(self, longitudinal: float) -> int:
        return int(np.clip(np.searchsorted(self._starts, longitudinal, side="right") - 1, 0, len(self._headings) - 1))

    def position(self, longitudinal: float, lateral: float) -> np.ndarray:
        k = self._segment(longitudinal)
        h = self._headings[k]
        along = np.array([np.cos(h), np.sin(h)])
        return self._points[k] + (longitudinal - self._starts[k]) * along + lateral * np.array([-along[1], along[0]])

    def heading_at(self, longitudinal: float) -> float:
        # continuous: interpolated between the segments' middles, so that a sampled curve reads its curvature
        middles = (self._starts[:-1] + self._starts[1:]) / 2
        return float(np.interp(longitudinal, middles, np.unwrap(self._headings)))


def _smoothed(before: np.ndarray, inside: np.ndarray, after: np.ndarray) -> np.ndarray:
    """An internal lane's shape resampled every :data:`INTERNAL_SPACING` m and averaged over
    :data:`SMOOTHING_WINDOW` m, with the lanes before and after it as context, its two ends kept where they are.

    SUMO writes shapes to 0.01 m and netconvert samples a turn with a few points: read as they are, both would
    show as kinks, whose speed limits (:func:`envs.simulation.layouts._kink_limits`) lie below what the curve's
    radius allows.
    """
    path = np.vstack([before, inside[1:], after[1:]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    a0 = float(np.sum(np.linalg.norm(np.diff(before, axis=0), axis=1)))
    a1 = a0 + float(np.sum(np.linalg.norm(np.diff(inside, axis=0), axis=1)))
    s = np.arange(max(0.0, a0 - SMOOTHING_WINDOW), min(arc[-1], a1 + SMOOTHING_WINDOW), INTERNAL_SPACING)
    xy = np.stack([np.interp(s, arc, path[:, 0]), np.interp(s, arc, path[:, 1])], axis=1)
    k = max(1, int(round(SMOOTHING_WINDOW / INTERNAL_SPACING / 2)))
    kernel = np.ones(2 * k + 1) / (2 * k + 1)
    mean = np.stack([np.convolve(xy[:, j], kernel, mode="same") for j in range(2)], axis=1)
    full = (np.arange(len(s)) >= k) & (np.arange(len(s)) < len(s) - k)  # a whole window of context
    # the average moves a curve inwards a little: phase it in over the first and last metre, so that the ends stay
    # where they are without a step
    weight = np.clip(np.minimum(s - a0, a1 - s), 0.0, 1.0) * full
    xy = xy + weight[:, None] * (mean - xy)
    middle = (s > a0 + INTERNAL_SPACING / 2) & (s < a1 - INTERNAL_SPACING / 2)
    return np.vstack([inside[:1], xy[middle], inside[-1:]])


def _read(path: Path):
    """The network, read with sumolib (internal lanes included)."""
    import sumolib  # the sumo extra

    if not path.is_file():
        raise NetFileError(f"{path}: no such file")
    try:
        return sumolib.net.readNet(str(path), withInternal=True)
    except Exception as error:  # a file from a user: whatever sumolib's parser says, in one line
        text = " ".join(str(error).split()) or type(error).__name__
        text = f"missing attribute {text}" if isinstance(error, KeyError) else text
        raise NetFileError(f"{path}: not a SUMO network ({text})") from None


def _the_junction(path: Path, net) -> object:
    """The one node with connections between normal edges."""
    junctions = [
        node for node in net.getNodes()
        if any(c.getFrom().getFunction() != "internal" for c in node.getConnections())
    ]  # fmt: skip
    if len(junctions) != 1:
        ids = ", ".join(node.getID() for node in junctions[:5]) + (", ..." if len(junctions) > 5 else "")
        raise NetFileError(
            f"{path}: {len(junctions)} junctions with connections ({ids or 'none'}); expected exactly one (cut the "
            "network to one junction, e.g. with netconvert --keep-edges.explicit)"
        )
    return junctions[0]


def _arm_names(path: Path, junction, to_layout) -> dict[str, str]:
    """Edge id -> the compass name of the arm it lies on (its far end's direction from the junction)."""
    names: dict[str, str] = {}
    compass = np.array(list(ARM_ANGLES.values()))
    for edges, far_end, kind in ((junction.getIncoming(), 0, "incoming"), (junction.getOutgoing(), -1, "outgoing")):
        taken: dict[str, str] = {}
        for edge in edges:
            if edge.getFunction() == "internal":
                continue
            far = to_layout(np.array(edge.getLane(0).getShape()[far_end]))
            angle = np.arctan2(far[1], far[0])
            name = list(ARM_ANGLES)[int(np.argmin(np.abs(np.angle(np.exp(1j * (compass - angle))))))]
            if name in taken:
                raise NetFileError(
                    f"{path}: the {kind} edges {taken[name]!r} and {edge.getID()!r} both leave the junction to the "
                    f"{name}; a readable junction has at most one arm per compass direction"
                )
            taken[name] = edge.getID()
            names[edge.getID()] = name
    return names


def _route_lanes(net, connection) -> list:
    """The SUMO lanes of a connection in driving order: incoming lane, internal lane(s), outgoing lane."""
    lanes = [connection.getFromLane()]
    via = connection.getViaLaneID()
    while via:
        lane = net.getLane(via)
        lanes.append(lane)
        onward = [c for c in lane.getOutgoing() if c.getToLane() is not None]
        if not onward:
            break
        via = onward[0].getViaLaneID()
        if not via:
            lanes.append(onward[0].getToLane())
    if lanes[-1].getEdge().getFunction() == "internal":
        lanes.append(connection.getToLane())
    return lanes


def read_junction(
    path: str | Path, ds: float = 0.5, lateral_acceleration: float = DEFAULT_LATERAL_ACCELERATION
) -> Layout:
    """The one junction of a SUMO network as a layout (see the module docstring).

    :param path: the ``.net.xml`` file
    :param ds: sample spacing of the route polylines [m]
    :param lateral_acceleration: largest lateral acceleration on curves [m/s^2] (their speed limits)
    :return: the layout, named ``"net:<the file's absolute path>"``
    :raises NetFileError: in one line naming the file and what is wrong
    :raises ImportError: without the sumo extra (sumolib)
    """
    path = Path(path)
    net = _read(path)
    junction = _the_junction(path, net)
    centre = np.array(junction.getCoord()[:2], float)

    def to_layout(points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, float)[..., :2] - centre) * (1.0, -1.0)

    arms = _arm_names(path, junction, to_layout)
    connections = [
        c for c in junction.getConnections()
        if c.getFrom().getFunction() != "internal" and c.getDirection() not in ("t", "T")
    ]  # fmt: skip
    if not connections:
        raise NetFileError(f"{path}: junction {junction.getID()!r} has no connection between two arms")
    top = max(c.getFrom().getPriority() for c in connections)
    road = RoadNetwork()
    keys: dict[str, tuple[str, str, int]] = {}
    routes = []
    for c in connections:
        lanes = _route_lanes(net, c)
        route_keys = [
            _add_lane(road, keys, lane, to_layout, lanes[max(k - 1, 0)], lanes[min(k + 1, len(lanes) - 1)])
            for k, lane in enumerate(lanes)
        ]
        shape_in, shape_out = to_layout(lanes[0].getShape()), to_layout(lanes[-1].getShape())
        h_in, h_out = shape_in[-1] - shape_in[-2], shape_out[1] - shape_out[0]
        maneuver = _DIRECTIONS.get(
            c.getDirection(), _maneuver(h_in / np.linalg.norm(h_in), h_out / np.linalg.norm(h_out))
        )
        entry, exit_ = arms[c.getFrom().getID()], arms[c.getTo().getID()]
        priority = MAJOR if c.getFrom().getPriority() == top else MINOR
        routes.append(
            [f"{entry}->{exit_}", route_keys, maneuver, priority, entry, exit_, 1, c.getFromLane().getIndex()]
        )
    names = [r[0] for r in routes]
    for r in routes:  # several incoming lanes join the same two arms: name the lane
        if names.count(r[0]) > 1:
            r[0] = f"{r[4]}@{r[7]}->{r[5]}"
    used = sorted({a for r in routes for a in (r[4], r[5])}, key=list(ARM_ANGLES).index)
    return layout_from_routes(
        NET_PREFIX + str(path.resolve()), road, [tuple(r[:7]) for r in routes],
        {a: float(ARM_ANGLES[a]) for a in used}, float(ds), float(lateral_acceleration),
    )  # fmt: skip


def _add_lane(
    road: RoadNetwork, keys: dict[str, tuple[str, str, int]], lane, to_layout, before, after
) -> tuple[str, str, int]:
    """The key of a SUMO lane in ``road``, added on first use (an internal lane smoothed with the route's lanes
    ``before`` and ``after`` it as context)."""
    lane_id = lane.getID()
    if lane_id not in keys:
        edge = lane.getEdge()
        points = to_layout(lane.getShape())
        if edge.getFunction() == "internal":
            points = _smoothed(to_layout(before.getShape()), points, to_layout(after.getShape()))
        start, end = f"{edge.getID()}-from", f"{edge.getID()}-to"
        priority = int(edge.getPriority()) if edge.getFunction() != "internal" else 0
        road.add_lane(start, end, _Polyline(points, float(lane.getWidth()), float(lane.getSpeed()), priority))
        keys[lane_id] = (start, end, len(road.graph[start][end]) - 1)
    return keys[lane_id]


def is_layout_name(name: object) -> bool:
    """``name`` names a layout: one of ours, or ``"net:FILE"`` (whether the file reads is checked when it is read)."""
    return isinstance(name, str) and (name in LAYOUT_NAMES or (name.startswith(NET_PREFIX) and len(name) > 4))


def named_layout(name: str, ds: float = 0.5, lateral_acceleration: float = DEFAULT_LATERAL_ACCELERATION) -> Layout:
    """The layout of a name: one of ours (:func:`envs.simulation.layouts.build_layout`), or ``"net:FILE"``, the
    junction of a SUMO network (:func:`read_junction`, once per file version and process).

    :raises ValueError: an unknown name (:class:`NetFileError`: a file that does not read, in one line)
    """
    if isinstance(name, str) and name.startswith(NET_PREFIX):
        path = Path(name[len(NET_PREFIX) :]).resolve()
        version = path.stat().st_mtime_ns if path.is_file() else 0
        return _junction_of(str(path), version, float(ds), float(lateral_acceleration))
    return build_layout(name, ds, lateral_acceleration)


@cache
def _junction_of(path: str, version: int, ds: float, lateral_acceleration: float) -> Layout:
    del version  # part of the key only: an edited file is read again
    return read_junction(path, ds, lateral_acceleration)
