"""The scene on the wire, and its one mapping to and from the in-process :class:`envs.simulation.scene.Scene`.

A scene crosses the wire in physical units, as the vehicles themselves know it:

- ``layout``: the intersection by name (``"4way"``, ``"3way"``, ``"inD"``);
- ``time``: simulated time [s];
- ``captured``: when the scene was captured, on the wall clock [s since the Unix epoch, UTC]: the server measures
  the scene's age against it (a scene from the future is refused; one older than the shield's declared latency
  bound too, :mod:`envs.serve.app`);
- ``vehicles``: one object per vehicle, ``id`` (integer, unique in the scene, stable while the vehicle
  is in it), ``route`` (its route by name, ``"<entry arm>-><exit arm>"``), ``arc`` (centre position
  along the route from the route's start [m]), ``speed`` [m/s], ``length`` and ``width`` [m].

Everything else a planner reads (pose, path coordinate ``s``, lane limits, distances to the
intersection, leaders and gaps, priority, maneuver, conflicts) is derived on the server by the
simulation's own code (:meth:`envs.simulation.engine.Simulation.scene`), so a planner behind the server sees
the scene that it would see in process, to the bit. Row ``i`` of the scene is ``vehicles[i]``, and
the answer's acceleration ``i`` is that vehicle's.

This module needs numpy (and numba, which the package depends on, for one of the server's checks): the
client (:mod:`envs.serve.client`) and the server (:mod:`envs.serve.app`, with the pydantic schema of
:mod:`envs.serve.schema`) both use it.
"""

from __future__ import annotations

import hashlib
import time as _clock
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from envs.simulation.engine import Simulation
from envs.simulation.scene import Scene
from envs.simulation.sumo_junction import named_layout

# Version of the wire schema; a change that old clients cannot read increments it (2: steps carry `seq`; 3: scenes
# carry `captured`).
SCHEMA_VERSION = 3
VEHICLE_FIELDS = ("id", "route", "arc", "speed", "length", "width")
# Largest number of vehicles the schema takes in one scene (the server's own limit is its
# environment's max_vehicles, usually far lower: its OpenAPI schema states that one).
MAX_VEHICLES = 1024
# Longest layout name a scene may carry: one of ours, or "net:FILE", the path of a SUMO network the server loaded.
MAX_LAYOUT_NAME = 256
# Physical bounds of a vehicle's size [m]: from a small car to a road train, from a narrow car to a wide load.
LENGTH_RANGE = (1.5, 30.0)
WIDTH_RANGE = (0.8, 5.0)


class WireError(ValueError):
    """A scene that the schema accepts but the intersection does not (an unknown route, a duplicate id...).

    :param field: the offending field, e.g. ``"vehicles[3].route"``
    :param message: what is wrong with it
    """

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def scene_to_wire(scene: Scene, captured: float | None = None) -> dict[str, Any]:
    """The wire form of an in-process scene (what the client sends).

    :param scene: a scene made by the simulation (it needs ``layout`` and ``arc``)
    :param captured: when it was captured [s since the Unix epoch] (default: now)
    :return: a JSON-ready dictionary (plain Python floats: ``json`` writes them so that they read back exactly)
    :raises ValueError: a hand-built scene without ``layout`` or ``arc``
    """
    if scene.layout is None or scene.arc is None:
        raise ValueError("a remote planner needs scenes with layout and arc (scenes made by the simulation)")
    n = scene.num_vehicles
    width = scene.width if scene.width is not None else np.full(n, 2.0)
    names = scene.route_names
    columns = zip(
        scene.vehicle_id.tolist(),
        [names[r] for r in scene.route.tolist()],
        scene.arc.tolist(),
        scene.speed.tolist(),
        scene.length.tolist(),
        np.asarray(width, float).tolist(),
    )
    vehicles = [dict(zip(VEHICLE_FIELDS, row)) for row in columns]
    captured = _clock.time() if captured is None else float(captured)
    return {"layout": scene.layout.name, "time": float(scene.time), "captured": captured, "vehicles": vehicles}


@dataclass(frozen=True)
class WireLimits:
    """What the server's environment allows in a scene.

    :param max_vehicles: most vehicles in one scene (the environment's ``max_vehicles``)
    :param max_speed: speed cap [m/s]
    """

    max_vehicles: int
    max_speed: float


class SceneBuilder:
    """Turns wire scenes into :class:`Scene` objects with the environment's own simulation code.

    :param config: the environment's resolved configuration (``env.unwrapped.config``)
    """

    def __init__(self, config: dict[str, Any]) -> None:
        self.config = dict(config)
        self.layout = named_layout(config["layout"], lateral_acceleration=float(config["lateral_acceleration"]))
        # The environment's own construction (its reset calls the same): the derived quantities use these settings.
        self._sim = Simulation.from_config(self.layout, config)
        self.limits = WireLimits(int(config["max_vehicles"]), float(config["max_speed"]))

    @property
    def dt(self) -> float:
        """Policy period of the environment [s]."""
        return self._sim.dt

    def scene(self, layout: str, time: float, vehicles: Sequence[Any]) -> Scene:
        """The in-process scene of a wire scene (its types and ranges already checked by the schema).

        :param layout: the scene's layout name
        :param time: simulated time [s]
        :param vehicles: objects with the attributes of :data:`VEHICLE_FIELDS`, in row order
        :return: the scene, row ``i`` = ``vehicles[i]``
        :raises WireError: another layout, too many vehicles, an unknown route, a duplicate id, an
            ``arc`` beyond the route's end, a ``speed`` above the cap or two vehicles in one place
            (:func:`_check_overlaps`), naming the field
        """
        return self.build(time, *self.columns(layout, vehicles))

    def columns(self, layout: str, vehicles: Sequence[Any]) -> tuple[np.ndarray, ...]:
        """The columns of a wire scene's vehicles: ids, route indices, arcs, speeds, lengths, widths.

        :raises WireError: another layout, too many vehicles, an unknown route
        """
        n = self._check_size(layout, len(vehicles))
        index = self.layout.route_index
        try:
            route = np.fromiter((index[v.route] for v in vehicles), np.int64, n)
        except KeyError:
            i = next(i for i, v in enumerate(vehicles) if v.route not in index)
            raise WireError(f"vehicles[{i}].route", f"layout {layout!r} has no route {vehicles[i].route!r}") from None
        ids = np.fromiter((v.id for v in vehicles), np.int64, n)
        arc = np.fromiter((v.arc for v in vehicles), float, n)
        speed = np.fromiter((v.speed for v in vehicles), float, n)
        length = np.fromiter((v.length for v in vehicles), float, n)
        width = np.fromiter((v.width for v in vehicles), float, n)
        return ids, route, arc, speed, length, width

    def table_columns(self, layout: str, routes: Sequence[str], ids: np.ndarray, route: np.ndarray, *rest: np.ndarray
                      ) -> tuple[np.ndarray, ...]:  # fmt: skip
        """The columns of a fast-path frame (:mod:`envs.serve.frames`), its route indices into the frame's names
        turned into this layout's.

        :raises WireError: another layout, too many vehicles, an unknown route name
        """
        self._check_size(layout, len(ids))
        index = self.layout.route_index
        table = np.fromiter((index.get(name, -1) for name in routes), np.int64, len(routes))
        mine = table[route]
        unknown = np.flatnonzero(mine < 0)
        if unknown.size:
            i = int(unknown[0])
            raise WireError(f"vehicles[{i}].route", f"layout {layout!r} has no route {routes[int(route[i])]!r}")
        return (ids, mine, *rest)

    def _check_size(self, layout: str, n: int) -> int:
        if layout != self.layout.name:
            raise WireError("layout", f"this server plans for layout {self.layout.name!r}, got {layout!r}")
        if n > self.limits.max_vehicles:
            raise WireError("vehicles", f"{n} vehicles, this server takes at most {self.limits.max_vehicles}")
        return n

    def build(self, time: float, ids: np.ndarray, route: np.ndarray, arc: np.ndarray, speed: np.ndarray,
              length: np.ndarray, width: np.ndarray) -> Scene:  # fmt: skip
        """The scene of checked columns, by the simulation's own code (its state set in place: no copies, no
        concatenation; the arrays are this request's own).

        :raises WireError: a duplicate id, an ``arc`` beyond the route's end, a ``speed`` above the cap or two
            vehicles in one place, naming the field
        """
        _check_rows(ids, route, arc, speed, self.layout.length, self.limits.max_speed)
        sim = self._sim
        sim.set_state(time, route, ids, arc, np.clip(speed, 0.0, sim.max_speed), length, width)
        scene = sim.scene()
        _check_overlaps(scene)
        return scene


def _check_rows(
    ids: np.ndarray, route: np.ndarray, arc: np.ndarray, speed: np.ndarray, route_length: np.ndarray, max_speed: float
) -> None:
    """Refuse what the simulation could not hold: a duplicate id, an arc past the route, a speed above the cap."""
    rule, i = _first_bad_row(ids, route, arc, speed, route_length, max_speed)
    if rule == 0:
        raise WireError(f"vehicles[{i}].id", f"id {int(ids[i])} appears twice in the scene")
    if rule == 1:
        end = route_length[route[i]]
        raise WireError(f"vehicles[{i}].arc", f"{arc[i]} m is past the end of its route ({end:.2f} m)")
    if rule == 2:
        raise WireError(f"vehicles[{i}].speed", f"{speed[i]} m/s is above the speed cap of {max_speed} m/s")


@numba.njit(cache=True)
def _first_bad_row(ids, route, arc, speed, route_length, max_speed):
    """``(rule, row)`` of :func:`_check_rows`' first refusal, ``(-1, -1)`` if none: rule 0 the first row whose id
    an earlier row has, 1 the first arc past its route's end, 2 the first speed above the cap (checked in that
    order; one compiled pass each: the server checks every scene it rebuilds)."""
    n = ids.shape[0]
    order = np.argsort(ids, kind="mergesort")  # stable: within equal ids, rows in order
    first_twice = n
    for k in range(1, n):
        if ids[order[k]] == ids[order[k - 1]]:
            first_twice = min(first_twice, order[k])
    if first_twice < n:
        return 0, first_twice
    for i in range(n):
        if arc[i] > route_length[route[i]]:
            return 1, i
    for i in range(n):
        if speed[i] > max_speed:
            return 2, i
    return -1, -1


def _check_overlaps(scene: Scene) -> None:
    """Refuse two vehicles in one place: centres closer than half the narrower one's width, or a vehicle that
    overlaps its leader on the same path by more than half the shorter one's length (a scene of the simulation
    overlaps by at most what one sub-step of a collision moves, about 1.3 m at the speed cap). A leader on a route
    that shares only the follower's approach (a left-turner ahead of a vehicle going straight) stays its leader up
    to its own exit, so a negative gap counts only where the centres are also within half the two lengths: past the
    fork the two are metres apart, and the simulation's scenes hold such pairs."""
    n = scene.num_vehicles
    if n < 2:
        return
    position = scene.position
    width = np.asarray(scene.width, float)
    kind, j, i = _first_overlap(position, width, scene.leader, scene.gap, scene.length)
    if kind == 0:
        apart = float(np.sqrt(np.square(position[j, 0] - position[i, 0]) + np.square(position[j, 1] - position[i, 1])))
        raise WireError(f"vehicles[{i}].arc", f"vehicle {int(scene.vehicle_id[i])} is {apart:.2f} m from "
                                              f"vehicle {int(scene.vehicle_id[j])}: two vehicles cannot be in one "
                                              "place")  # fmt: skip
    if kind == 1:
        raise WireError(f"vehicles[{i}].arc", f"vehicle {int(scene.vehicle_id[i])} overlaps vehicle "
                                              f"{int(scene.vehicle_id[j])} by {-float(scene.gap[i]):.2f} m: two "
                                              "vehicles cannot be in one place")  # fmt: skip


@numba.njit(cache=True)
def _first_overlap(position, width, leader, gap, length):
    """``(kind, j, i)``: kind 0 the first pair ``j < i`` (in row order) whose centres are closer than half the
    narrower width; else kind 1, the first vehicle ``i`` that overlaps its leader ``j`` by more than half the
    shorter one's length with their centres within half the two lengths; ``(-1, -1, -1)`` if neither (one pass
    over the pairs: the server checks every scene it rebuilds)."""
    n = position.shape[0]
    for j in range(n):
        for i in range(j + 1, n):
            limit = min(0.5 * width[j], 0.5 * width[i])
            if (position[j, 0] - position[i, 0]) ** 2 + (position[j, 1] - position[i, 1]) ** 2 < limit * limit:
                return 0, j, i
    for i in range(n):
        j = leader[i]
        if j >= 0 and gap[i] < -0.5 * min(length[i], length[j]):
            reach = 0.5 * (length[i] + length[j])
            if (position[j, 0] - position[i, 0]) ** 2 + (position[j, 1] - position[i, 1]) ** 2 < reach * reach:
                return 1, j, i
    return -1, -1, -1


def digest(layout: str, time: float, columns: Sequence[np.ndarray]) -> bytes:
    """A hash of a step's content (layout, time and columns), the same whichever codec carried it: a step
    retried over the other path is recognised as the same step."""
    h = hashlib.blake2b(f"{layout}|{float(time)!r}|{len(columns[0])}".encode(), digest_size=16)
    for column in columns:
        h.update(np.ascontiguousarray(column).tobytes())
    return h.digest()
