"""Vectorized simulation of every vehicle at the intersection: state in arrays, one row per vehicle.

Vehicle model: the kinematic bicycle model with ideal path tracking. Lateral control is assumed
perfect, so every vehicle stays on its route's lane centre line and its heading is the path
tangent; only the longitudinal motion is simulated. The planner commands one acceleration per
vehicle, clipped to ``[-a_max, a_max]`` and held for the policy period, which is integrated in
``simulation_frequency / policy_frequency`` sub-steps (default 15 Hz and 5 Hz: the paper spawns
with 5 % probability per time step and evaluates at 0.2-0.4 veh/s per lane, which matches a 0.2 s
step). Speed stays in ``[0, max_speed]``: vehicles never drive backwards. A vehicle is removed when
its centre reaches the end of its route.

Physics parity: the same limits hold for every planner, applied after its command. A speed
governor keeps each vehicle at or below the braking envelope of its lane limits (the road's limit
on straight lanes, ``sqrt(a_lat_max / kappa)`` on curved ones), slowing it down for a lower limit
ahead at ``governor_deceleration``; the collision check runs at a resolution fine enough to see
brief corner contacts.

Everything per step is vectorized over vehicles and vehicle pairs: positions come from one gather
into the layout's sampled routes, leaders from an ``(n, n)`` table of positions on each other's
route, collisions from a separating-axis test over candidate pairs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from envs.simulation import _leaders_kernel
from envs.simulation.layouts import Layout, parting_arcs
from envs.simulation.scene import STOP_SPEED, Scene

# Metres behind a vehicle's rear over which diverging paths still overlap a vehicle's width (the inD
# through lane leaves its left-turn pocket at 7.6 deg: 2 m apart after ~15 m); where paths part more
# slowly than that, the layout's parting arcs (`parting_arcs`) keep the leader longer.
SPLIT_CLEARANCE = 15.0
_INT = np.int64


@dataclass
class StepEvents:
    """What happened during one policy step (all ids are vehicle ids).

    :param stopped: ids whose speed was below ``STOP_SPEED`` after any sub-step
    :param crossed: ids whose centre passed the intersection exit (``s`` passed 0)
    :param removed: ids that left the scene: they reached the end of their route, or collided
        in a step run with ``remove_collided``
    :param collisions: ``(k, 2)`` id pairs whose bodies overlapped after any sub-step
    :param kept: ``(n,)`` bool over the rows before the step: the vehicle is still in the scene
    :param governed: ids whose speed the governor lowered below what the planner commanded
    :param moved: ``(n,)`` ids of the rows before the step (removed vehicles included): the columns of ``speeds``
    :param speeds: ``(S + 1, n)`` executed speeds at the sub-step boundaries (row 0: the step's start) [m/s],
        after the acceleration bounds and the governor: the motion the metrics measure
        (:mod:`envs.simulation.motion`)
    :param lost: ids that the plant lost on its own: a vehicle it refused to insert or removed without
        reaching its route's end (SUMO can; our simulation never does). They are in ``removed`` too
    """

    stopped: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))
    crossed: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))
    removed: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))
    collisions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), _INT))
    kept: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    governed: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))
    moved: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))
    speeds: np.ndarray = field(default_factory=lambda: np.zeros((1, 0)))
    lost: np.ndarray = field(default_factory=lambda: np.zeros(0, _INT))


class PlantError(RuntimeError):
    """The plant failed during a run (SUMO: an error of libsumo). The harness counts the run as failed and
    reports this one line; the other runs go on."""

    def line(self, scenario: str | None = None) -> str:
        """The one line that reports the error (naming ``scenario`` when given)."""
        at = f", scenario {scenario}" if scenario else ""
        return f"plant error{at}: {self}"


def table_settings(config: dict[str, Any]) -> dict[str, Any]:
    """The keyword arguments of :class:`VehicleTable` that a validated environment configuration gives (every
    plant's ``from_config`` passes them on)."""
    keys = ("simulation_frequency", "policy_frequency", "max_speed", "max_acceleration", "s_ref", "max_vehicles",
            "governor_deceleration")  # fmt: skip
    return {key: config[key] for key in keys}


class VehicleTable:
    """The vehicles at the intersection as columns, one row per vehicle, and every view of them that a plant
    gives from columns: poses, leaders, the path coordinate and the :class:`~envs.simulation.scene.Scene`
    (the one door through which both plants build a scene). A plant (:mod:`envs.simulation.plant`) moves the
    rows; this class only stores and reads them.

    :param layout: the intersection
    :param simulation_frequency: integration rate [Hz]
    :param policy_frequency: rate of new commands [Hz]; must divide ``simulation_frequency``
    :param max_speed: speed cap [m/s]
    :param max_acceleration: commands are clipped to ``[-max_acceleration, max_acceleration]`` [m/s^2]
    :param s_ref: common reference length of the paths inside the intersection [m]
    :param max_vehicles: capacity; :meth:`add` refuses vehicles beyond it
    :param governor_deceleration: deceleration with which the speed governor slows vehicles down
        for a lower limit ahead [m/s^2]
    """

    # Whether the plant drives the human rows itself (SUMO's drivers); otherwise the environment commands them
    # with our human model (:class:`envs.planners.human.HumanDriver`).
    drives_humans = False
    # The per-vehicle columns: rows are dropped from all of them at once (:meth:`_keep`).
    COLUMNS: tuple[str, ...] = ("route", "arc", "speed", "length", "width", "vehicle_id", "appearance_time", "human")

    def __init__(
        self,
        layout: Layout,
        simulation_frequency: int = 15,
        policy_frequency: int = 5,
        max_speed: float = 20.0,
        max_acceleration: float = 5.0,
        s_ref: float = 25.0,
        max_vehicles: int = 64,
        governor_deceleration: float = 3.0,
    ) -> None:
        if simulation_frequency % policy_frequency:
            raise ValueError(
                f"simulation_frequency ({simulation_frequency}) must be a multiple of "
                f"policy_frequency ({policy_frequency})"
            )
        self.layout = layout
        self.simulation_frequency = int(simulation_frequency)
        self.policy_frequency = int(policy_frequency)
        self.substeps = self.simulation_frequency // self.policy_frequency
        self.max_speed = float(max_speed)
        self.max_acceleration = float(max_acceleration)
        self.s_ref = float(s_ref)
        self.max_vehicles = int(max_vehicles)
        self.governor_deceleration = float(governor_deceleration)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Empty the scene and set the clock to 0."""
        self.time = 0.0
        self.route = np.zeros(0, _INT)
        self.arc = np.zeros(0)  # centre, along the route [m]
        self.speed = np.zeros(0)
        self.length = np.zeros(0)
        self.width = np.zeros(0)
        self.vehicle_id = np.zeros(0, _INT)
        self.appearance_time = np.zeros(0)
        self.human = np.zeros(0, bool)  # human-driven: the environment replaces their commands
        self._cache: dict[str, tuple[tuple[np.ndarray, ...], Any]] = {}
        # Speeds and arcs at the sub-step boundaries of the last step, rows as before it
        # (diagnostics and tests: the trajectory the collision check saw).
        self.last_trajectory: tuple[np.ndarray, np.ndarray] = (np.zeros((1, 0)), np.zeros((1, 0)))

    def set_state(
        self,
        time: float,
        route: np.ndarray,
        vehicle_id: np.ndarray,
        arc: np.ndarray,
        speed: np.ndarray,
        length: np.ndarray,
        width: np.ndarray,
        human: np.ndarray | None = None,
    ) -> None:
        """Replace the whole scene by these vehicles, all appearing now (what :meth:`reset` then :meth:`add`
        would store, without :meth:`add`'s checks and concatenations: the caller has checked the rows). The
        arrays are kept, not copied: the simulation replaces its state arrays and never writes in them.

        :param time: the clock [s]
        :param route: ``(n,)`` route indices
        :param vehicle_id: ``(n,)`` unique ids
        :param arc: ``(n,)`` centre positions along the routes [m]
        :param speed: ``(n,)`` speeds [m/s], within ``[0, max_speed]``
        :param length: ``(n,)`` vehicle lengths [m]
        :param width: ``(n,)`` vehicle widths [m]
        :param human: ``(n,)`` bool: human-driven vehicles (default: none)
        """
        self.reset()
        self.time = float(time)
        n = len(vehicle_id)
        if n:
            self.route, self.vehicle_id, self.arc, self.speed = route, vehicle_id, arc, speed
            self.length, self.width = length, width
            self.appearance_time = np.full(n, self.time)
            self.human = np.zeros(n, bool) if human is None else human

    @property
    def num_vehicles(self) -> int:
        return int(self.route.shape[0])

    def close(self) -> None:
        """Nothing to release: the columns are plain arrays (a plant that holds more overrides this)."""

    @property
    def dt(self) -> float:
        """Policy period [s]."""
        return 1.0 / self.policy_frequency

    def add(
        self,
        route: np.ndarray,
        speed: np.ndarray,
        vehicle_id: np.ndarray,
        length: np.ndarray | float = 5.0,
        width: np.ndarray | float = 2.0,
        arc: np.ndarray | None = None,
        human: np.ndarray | bool | None = None,
    ) -> None:
        """Append vehicles (new rows at the end: existing rows keep their order).

        :param route: ``(k,)`` route indices
        :param speed: ``(k,)`` initial speeds [m/s]
        :param vehicle_id: ``(k,)`` unique ids
        :param length: vehicle lengths [m]
        :param width: vehicle widths [m]
        :param arc: ``(k,)`` centre positions along the route; default: rear at the route's start
        :param human: ``(k,)`` bool: human-driven vehicles (default: none)
        :raises ValueError: when the scene would exceed ``max_vehicles`` or an id is already present
        """
        route = np.atleast_1d(np.asarray(route, _INT))
        k = route.shape[0]
        if self.num_vehicles + k > self.max_vehicles:
            raise ValueError(f"adding {k} vehicles exceeds max_vehicles={self.max_vehicles}")
        vehicle_id = np.atleast_1d(np.asarray(vehicle_id, _INT))
        if np.intersect1d(vehicle_id, self.vehicle_id).size or np.unique(vehicle_id).size != k:
            raise ValueError(f"vehicle ids must be unique, got {vehicle_id.tolist()}")
        length = np.broadcast_to(np.asarray(length, float), (k,))
        width = np.broadcast_to(np.asarray(width, float), (k,))
        arc = length / 2 if arc is None else np.broadcast_to(np.asarray(arc, float), (k,))
        self.route = np.concatenate([self.route, route])
        self.arc = np.concatenate([self.arc, arc])
        self.speed = np.concatenate([self.speed, np.clip(np.asarray(speed, float), 0.0, self.max_speed)])
        self.length = np.concatenate([self.length, length])
        self.width = np.concatenate([self.width, width])
        self.vehicle_id = np.concatenate([self.vehicle_id, vehicle_id])
        self.appearance_time = np.concatenate([self.appearance_time, np.full(k, self.time)])
        human = np.zeros(k, bool) if human is None else np.broadcast_to(np.asarray(human, bool), (k,))
        self.human = np.concatenate([self.human, human])

    def _keep(self, keep: np.ndarray) -> None:
        for name in self.COLUMNS:
            setattr(self, name, getattr(self, name)[keep])

    # ------------------------------------------------------------------ spawning
    def spawn_free(self, spawn_lane: np.ndarray, speed: np.ndarray, length: np.ndarray, min_gap: float) -> np.ndarray:
        """Whether a new vehicle fits at the start of each given spawn lane.

        The bumper gap to the last vehicle that entered by that lane must be at least ``min_gap``
        plus the extra braking distance the newcomer needs to slow to the other's speed at
        ``max_acceleration``, so that a spawn never forces a collision.

        :param spawn_lane: ``(k,)`` indices into ``layout.spawn_lanes``
        :param speed: ``(k,)`` speeds the newcomers would have [m/s]
        :param length: ``(k,)`` their lengths [m]
        :param min_gap: smallest bumper gap [m]
        :return: ``(k,)`` bool
        """
        spawn_lane = np.asarray(spawn_lane, _INT)
        if self.num_vehicles == 0:
            return np.ones(spawn_lane.shape, bool)
        rear = self.arc - self.length / 2
        on_lane = self.layout.route_spawn_lane[self.route][None, :] == spawn_lane[:, None]  # (k, n)
        masked = np.where(on_lane, rear[None, :], np.inf)
        last = masked.argmin(axis=1)
        gap = masked[np.arange(len(spawn_lane)), last] - np.asarray(length, float)
        v_other = self.speed[last]
        brake = np.maximum(np.asarray(speed, float) ** 2 - v_other**2, 0.0) / (2 * self.max_acceleration)
        return gap >= min_gap + brake

    # ------------------------------------------------------------------ geometry
    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """``(n, 2)`` centre positions and ``(n,)`` headings."""
        return self._cached("pose", lambda: self.layout.pose(self.route, self.arc))

    def _cached(self, name: str, compute: Callable[[], Any]) -> Any:
        # The state arrays are replaced, never written in place, by the simulation: their
        # identities tell whether a derived quantity is still valid (the scene of the last step
        # and the start of the next one share pose, lanes and leaders).
        # The cache holds the arrays themselves, so their ids cannot be reused while it lives.
        key = (self.arc, self.route, self.length)
        hit = self._cache.get(name)
        if hit is not None and all(a is b for a, b in zip(hit[0], key)):
            return hit[1]
        value = compute()
        self._cache[name] = (key, value)
        return value

    def collisions(self, position: np.ndarray | None = None, heading: np.ndarray | None = None) -> np.ndarray:
        """Rows of overlapping vehicle pairs (oriented rectangles, separating-axis test).

        :return: ``(k, 2)`` row pairs ``i < j``
        """
        if position is None or heading is None:
            position, heading = self.pose()
        return overlapping_pairs(position, heading, self.length, self.width)

    def leaders(self) -> tuple[np.ndarray, np.ndarray]:
        """Nearest vehicle ahead on the same path and the bumper gap to it.

        Vehicle ``j`` lies on ``i``'s path when ``j``'s current lane is one of the lanes of
        ``i``'s route; its position on that route is the lane's start on ``i``'s route plus
        ``j``'s distance along the lane.

        :return: ``(n,)`` leader rows (-1 if none) and ``(n,)`` gaps [m] (``inf`` if none)
        """
        return self._cached("leaders", self._leaders)

    def _leaders(self) -> tuple[np.ndarray, np.ndarray]:
        n = self.num_vehicles
        if n == 0:
            return np.zeros(0, _INT), np.zeros(0)
        lay = self.layout
        # Where paths split (a turn pocket, a turn at the stop line) a vehicle that has just taken
        # the other branch still overlaps the shared path: it stays the leader until the point
        # SPLIT_CLEARANCE behind its rear has passed the split too; where the paths part more slowly
        # (inD's turn pockets), while its rear is short of the arc where its path leaves the other's.
        # The lanes of both points and the pairs in one compiled call (bitwise the NumPy search).
        return _leaders_kernel.leaders_at(
            np.ascontiguousarray(self.route, _INT), np.ascontiguousarray(self.arc, float),
            np.ascontiguousarray(self.length, float), SPLIT_CLEARANCE, lay.route_lane_starts, lay.route_lane_ids,
            lay.lane_start, parting_arcs(lay),
        )  # fmt: skip

    def path_coordinate(self) -> np.ndarray:
        """The paper's ``s``: 0 at the intersection exit, ``-s_ref`` at its entry, metres outside."""
        lay = self.layout
        entry, exit_ = lay.entry_arc[self.route], lay.exit_arc[self.route]
        inside = -self.s_ref + (self.arc - entry) * (self.s_ref / (exit_ - entry))
        return np.where(
            self.arc < entry,
            -self.s_ref + (self.arc - entry),
            np.where(self.arc < exit_, inside, self.arc - exit_),
        )

    def scene(self) -> Scene:
        """The current snapshot (row ``i`` = vehicle ``i`` = action slot ``i``)."""
        lay = self.layout
        position, heading = self.pose()
        leader, gap = self.leaders()
        return Scene(
            time=float(self.time),
            dt=self.dt,
            vehicle_id=self.vehicle_id.copy(),
            route=self.route.copy(),
            s=self.path_coordinate(),
            position=position.copy(),  # pose and leaders are cached: the scene gets its own arrays
            heading=heading.copy(),
            speed=self.speed.copy(),
            speed_limit=lay.limit_at(self.route, self.arc),
            dist_to_entry=lay.entry_arc[self.route] - (self.arc + self.length / 2),
            dist_to_exit=lay.exit_arc[self.route] - (self.arc - self.length / 2),
            leader=leader.copy(),
            gap=gap.copy(),
            priority=lay.priority[self.route],
            maneuver=lay.maneuver[self.route],
            length=self.length.copy(),
            route_names=lay.route_names,
            conflicts=lay.conflicts,
            a_min=-self.max_acceleration,
            a_max=self.max_acceleration,
            width=self.width.copy(),
            s_ref=self.s_ref,
            arc=self.arc.copy(),
            layout=lay,
            human=self.human.copy(),
            substeps=self.substeps,
        )

    def rollout_scene(self, speed_limit: np.ndarray | None = None) -> Scene:
        """A lean :meth:`scene` for planning ahead in a copy of the world (``lookahead``'s rollouts): the same
        values, but the arrays are the simulation's own (not copied: the planners and the shield given it must
        not write in them) and what no planner behind the shield reads (``position``, ``heading``, ``s``) is NaN.
        :meth:`scene` copied about twenty arrays and computed the poses, a tenth of a rollout step.

        :param speed_limit: ``(n,)`` ``layout.limit_at(route, arc)`` where the caller has it already
        """
        lay = self.layout
        n = self.num_vehicles
        leader, gap = self.leaders()
        return Scene(
            time=float(self.time),
            dt=self.dt,
            vehicle_id=self.vehicle_id,
            route=self.route,
            s=np.full(n, np.nan),
            position=np.full((n, 2), np.nan),
            heading=np.full(n, np.nan),
            speed=self.speed,
            speed_limit=lay.limit_at(self.route, self.arc) if speed_limit is None else speed_limit,
            dist_to_entry=lay.entry_arc[self.route] - (self.arc + self.length / 2),
            dist_to_exit=lay.exit_arc[self.route] - (self.arc - self.length / 2),
            leader=leader,
            gap=gap,
            priority=lay.priority[self.route],
            maneuver=lay.maneuver[self.route],
            length=self.length,
            route_names=lay.route_names,
            conflicts=lay.conflicts,
            a_min=-self.max_acceleration,
            a_max=self.max_acceleration,
            width=self.width,
            s_ref=self.s_ref,
            arc=self.arc,
            layout=lay,
            human=self.human,
            substeps=self.substeps,
        )


class Simulation(VehicleTable):
    """Longitudinal motion of all vehicles along their routes.

    :param layout: the intersection
    :param simulation_frequency: integration rate [Hz]
    :param policy_frequency: rate of new commands [Hz]; must divide ``simulation_frequency``
    :param max_speed: speed cap [m/s]
    :param max_acceleration: commands are clipped to ``[-max_acceleration, max_acceleration]`` [m/s^2]
    :param s_ref: common reference length of the paths inside the intersection [m]
    :param max_vehicles: capacity; :meth:`add` refuses vehicles beyond it
    :param governor_deceleration: deceleration with which the speed governor slows vehicles down
        for a lower limit ahead [m/s^2]
    :param collision_resolution: largest distance a body moves between two collision checks [m]
    :param check_collisions: look for collisions in each step (off: a rollout behind a shield, which
        keeps every gap, skips the check; :attr:`StepEvents.collisions` is then always empty)
    """

    @classmethod
    def from_config(cls, layout: Layout, config: dict[str, Any], seed: int | None = None) -> Simulation:
        """The simulation that an environment's resolved ``default_config()`` settings ask for (the
        environment's ``reset`` and the edge server's scene builder both build it so).

        :param layout: the intersection
        :param config: a validated environment configuration
        :param seed: unused: our plant draws nothing (the SUMO plant seeds its drivers with it)
        """
        del seed
        return cls(layout, **table_settings(config), collision_resolution=config["collision_resolution"])

    def __init__(
        self,
        layout: Layout,
        simulation_frequency: int = 15,
        policy_frequency: int = 5,
        max_speed: float = 20.0,
        max_acceleration: float = 5.0,
        s_ref: float = 25.0,
        max_vehicles: int = 64,
        governor_deceleration: float = 3.0,
        collision_resolution: float = 0.1,
        check_collisions: bool = True,
    ) -> None:
        self.collision_resolution = float(collision_resolution)
        self.check_collisions = bool(check_collisions)
        # Faults (envs.simulation.faults.Actuator): (ids, commands, speeds) -> (S, n) realised accelerations.
        self.actuator: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None
        super().__init__(
            layout, simulation_frequency, policy_frequency, max_speed, max_acceleration, s_ref, max_vehicles,
            governor_deceleration,
        )  # fmt: skip

    # ------------------------------------------------------------------ dynamics
    def step(self, acceleration: np.ndarray, remove_collided: bool = False) -> StepEvents:
        """Apply the commanded accelerations for one policy period.

        Each sub-step, the speed governor caps the speed at the braking envelope of the lane
        limits (:meth:`envs.simulation.layouts.Layout.speed_envelope` for ``governor_deceleration``): whatever
        a planner commands, no vehicle exceeds the limit of the lane it is on, and it slows down
        for a lower limit ahead within that deceleration.

        Collisions are checked on the candidate pairs found once per policy step (pairs whose
        centres are closer than the sum of their half diagonals plus the farthest each can travel
        during the period), at times fine enough that no vehicle moves more than
        ``collision_resolution`` metres between two checks (the trajectory between sub-steps is the
        constant acceleration that joins their speeds).

        :param acceleration: ``(n,)`` commanded accelerations [m/s^2], row ``i`` = vehicle ``i``
        :param remove_collided: take the vehicles of this step's collisions out of the scene too
            (they appear in ``removed`` as well as in ``collisions``), so that an evaluation run
            goes on; otherwise they stay where they are
        :return: the events of the step; finished vehicles are already removed
        """
        n = self.num_vehicles
        a_max = self.max_acceleration
        acc = np.minimum(np.maximum(np.asarray(acceleration, float).reshape(n), -a_max), a_max)
        if self.actuator is not None:  # latency and lag: what each sub-step realises, (S, n)
            acc = self.actuator(self.vehicle_id, acc, self.speed)
        period = self.dt
        exit_arc = self.layout.exit_arc[self.route]
        before_exit = self.arc < exit_arc
        candidates = self._collision_candidates() if n > 1 and self.check_collisions else None
        speed, arc, governed = self._integrate(acc)
        stopped = (speed[1:] < STOP_SPEED).any(axis=0)
        collisions = self._collisions_along(speed, arc, *candidates) if candidates else np.zeros((0, 2), _INT)
        self.last_trajectory = (speed, arc)
        self.arc = arc[-1]
        self.speed = speed[-1]
        self.time += period
        crossed = before_exit & (self.arc >= exit_arc)
        events = StepEvents(
            stopped=self.vehicle_id[stopped],
            crossed=self.vehicle_id[crossed],
            collisions=self.vehicle_id[collisions] if collisions.size else collisions,
            governed=self.vehicle_id[governed],
            moved=self.vehicle_id,
            speeds=speed,
        )
        done = self.arc >= self.layout.length[self.route]
        if remove_collided and collisions.size:
            done[collisions.ravel()] = True
        events.kept = ~done
        events.removed = self.vehicle_id[done]
        if done.any():
            self._keep(~done)
        return events

    def _integrate(self, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Speeds and arcs at the sub-step boundaries under the governor (:func:`integrate`).

        :return: ``(S + 1, n)`` speeds, ``(S + 1, n)`` arcs (row 0: now) and ``(n,)`` bool: the
            governor lowered the vehicle's speed in some sub-step
        """
        return integrate(
            self.layout,
            self.route,
            self.arc,
            self.speed,
            acc,
            self.substeps,
            1.0 / self.simulation_frequency,
            self.max_speed,
            self.governor_deceleration,
        )

    def _collision_candidates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """Pairs that may touch during the coming policy period.

        On the spawn lanes and exit lanes, lanes are straight and lanes of different paths are
        parallel a lane width apart or far apart: there, only a leader and its follower can touch,
        when their gap along the path closes (a 1-D check). The separating-axis test runs on the
        close pairs of which at least one is (or may get within the period) past its spawn lane
        and not yet past the intersection exit.

        :return: ``(follower, leader, gap)`` rows and bumper gaps for the 1-D check and
            ``(cand_i, cand_j)`` rows for the separating-axis test, or ``None`` if there are none
        """
        lay, period, a_max = self.layout, self.dt, self.max_acceleration
        travel = np.minimum(self.speed * period + 0.5 * a_max * period**2, self.max_speed * period)
        margin = travel + 1.0
        in_area = (self.arc + self.length / 2 >= lay.touch_arc[self.route] - margin) & (
            self.arc - self.length / 2 <= lay.exit_arc[self.route] + margin
        )
        leader, gap = self.leaders()
        follower = np.flatnonzero((leader >= 0) & ~in_area)
        leader = leader[follower]
        keep = ~in_area[leader]
        follower, leader = follower[keep], leader[keep]
        position, _ = self.pose()
        reach = 0.5 * np.hypot(self.length, self.width) + travel
        delta = position[:, None, :] - position[None, :, :]
        close = (delta**2).sum(axis=-1) <= (reach[:, None] + reach[None, :]) ** 2
        close &= in_area[:, None] | in_area[None, :]
        cand_i, cand_j = np.nonzero(np.triu(close, 1))
        if follower.size == 0 and cand_i.size == 0:
            return None
        return follower, leader, gap[follower], cand_i, cand_j

    def _collisions_along(
        self,
        speed: np.ndarray,
        arc: np.ndarray,
        follower: np.ndarray,
        leader: np.ndarray,
        gap: np.ndarray,
        cand_i: np.ndarray,
        cand_j: np.ndarray,
    ) -> np.ndarray:
        """Row pairs ``i < j`` that touch at some check time along the sub-step trajectory.

        :return: ``(k, 2)`` int64 rows (of the state before the step)
        """
        h = 1.0 / self.simulation_frequency
        steps = np.diff(arc, axis=0)  # (S, n)
        # A body's corners sweep up to ~1.5x its centre's travel on the tightest curves (9 m radius).
        fastest = steps.max(initial=0.0)
        k = max(1, int(np.ceil(3.0 * fastest / self.collision_resolution)))
        t = (np.arange(1, k + 1) / k * h)[None, :, None]  # (1, K, 1)
        accel = (np.diff(speed, axis=0) / h)[:, None, :]  # (S, 1, n): constant within a sub-step
        fine = (arc[:-1, None, :] + speed[:-1, None, :] * t + 0.5 * accel * t**2).reshape(-1, arc.shape[1])
        hits: list[np.ndarray] = []
        if follower.size:
            moved = fine - self.arc
            bump = (gap + moved[:, leader] - moved[:, follower] < 0).any(axis=0)
            if bump.any():
                hits.append(np.sort(np.stack([follower[bump], leader[bump]], axis=1), axis=1))
        if cand_i.size:
            # Poses of the vehicles in a candidate pair at every check time in one gather; the
            # separating-axis test only where the circumscribed circles meet (a necessary condition).
            rows, slot = np.unique(np.concatenate([cand_i, cand_j]), return_inverse=True)
            p = cand_i.size
            pos, hd = self.layout.pose(self.route[rows][None, :], fine[:, rows])  # (T, m, 2), (T, m)
            si, sj = slot[:p], slot[p:]
            delta = pos[:, sj] - pos[:, si]  # (T, p, 2)
            radius = 0.5 * np.hypot(self.length, self.width)
            reach = (radius[cand_i] + radius[cand_j]) ** 2 + 1e-9
            near_t, near_p = np.nonzero(delta[..., 0] ** 2 + delta[..., 1] ** 2 <= reach)
            if near_t.size:
                i, j = cand_i[near_p], cand_j[near_p]
                overlap = _sat_test(
                    delta[near_t, near_p],
                    hd[near_t, si[near_p]],
                    hd[near_t, sj[near_p]],
                    self.length[i],
                    self.width[i],
                    self.length[j],
                    self.width[j],
                )
                if overlap.any():
                    hits.append(np.stack([i[overlap], j[overlap]], axis=1))
        if not hits:
            return np.zeros((0, 2), _INT)
        pairs = np.concatenate(hits)
        code = np.unique(pairs[:, 0] * self.num_vehicles + pairs[:, 1])  # sorted like rows i < j
        return np.stack([code // self.num_vehicles, code % self.num_vehicles], axis=1)


def integrate(
    layout: Layout,
    route: np.ndarray,
    arc: np.ndarray,
    speed: np.ndarray,
    acc: np.ndarray,
    substeps: int,
    h: float,
    max_speed: float,
    governor_deceleration: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vehicle model over one policy period: accelerations held for ``substeps`` sub-steps of
    ``h`` seconds, speed kept in ``[0, max_speed]`` and under the governor's envelope.

    A pure function, so that a planner-side check (:class:`envs.planners.shield.Shield`) predicts
    with exactly the simulation's model.

    :param layout: the intersection
    :param route: ``(n,)`` route indices
    :param arc: ``(n,)`` centre arcs now [m]
    :param speed: ``(n,)`` speeds now [m/s]
    :param acc: ``(n,)`` accelerations, already clipped to the bounds [m/s^2], or ``(S, n)``: one per sub-step
    :param substeps: sub-steps per policy period
    :param h: sub-step length [s]
    :param max_speed: speed cap [m/s]
    :param governor_deceleration: the governor's braking deceleration [m/s^2]
    :return: ``(S + 1, n)`` speeds, ``(S + 1, n)`` arcs (row 0: now) and ``(n,)`` bool: the
        governor lowered the vehicle's speed in some sub-step
    """
    b = governor_deceleration
    v_all = np.empty((substeps + 1, route.shape[0]))
    x_all = np.empty_like(v_all)
    v_all[0], x_all[0] = speed, arc
    governed = np.zeros(route.shape[0], bool)
    cap_now = layout.envelope_at(route, arc, b)
    for k in range(substeps):  # a loop over time (3 sub-steps), vectorized over vehicles
        v = np.minimum(np.maximum(v_all[k] + (acc[k] if acc.ndim == 2 else acc) * h, 0.0), max_speed)
        x = x_all[k] + 0.5 * (v_all[k] + v) * h
        cap_x = layout.envelope_at(route, x, b)
        cap = np.minimum(cap_now, cap_x)
        over = v > cap
        governed |= over
        v_all[k + 1] = np.where(over, cap, v)
        x_all[k + 1] = x_all[k] + 0.5 * (v_all[k] + v_all[k + 1]) * h
        # The next sub-step starts where this one ended: that is x (the same float) unless the
        # governor slowed the vehicle, so the envelope is looked up again only for those.
        if over.any():
            cap_x[over] = layout.envelope_at(route[over], x_all[k + 1][over], b)
        cap_now = cap_x
    return v_all, x_all, governed


def overlapping_pairs(position: np.ndarray, heading: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Pairs of oriented rectangles that overlap (separating-axis theorem, vectorized over pairs).

    Pairs whose centres are farther apart than the sum of the half diagonals are discarded first.

    :param position: ``(n, 2)`` centres
    :param heading: ``(n,)`` headings [rad]
    :param length: ``(n,)`` lengths
    :param width: ``(n,)`` widths
    :return: ``(k, 2)`` int64 row pairs ``i < j``
    """
    n = position.shape[0]
    if n < 2:
        return np.zeros((0, 2), _INT)
    radius = 0.5 * np.hypot(length, width)
    i, j = np.triu_indices(n, 1)
    delta = position[j] - position[i]
    near = (delta**2).sum(axis=1) <= (radius[i] + radius[j]) ** 2
    i, j, delta = i[near], j[near], delta[near]
    if i.size == 0:
        return np.zeros((0, 2), _INT)
    overlap = _sat_overlap(position, heading, length, width, i, j)
    return np.stack([i[overlap], j[overlap]], axis=1).astype(_INT)


def _sat_overlap(
    position: np.ndarray,
    heading: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
) -> np.ndarray:
    """``(k,)`` bool: rectangles ``i[k]`` and ``j[k]`` overlap.

    Separating-axis test on the four edge normals; the projections of one rectangle onto the
    other's axes depend only on ``|cos|`` and ``|sin|`` of the heading difference.
    """
    return _sat_test(position[j] - position[i], heading[i], heading[j], length[i], width[i], length[j], width[j])


def _sat_test(
    d: np.ndarray,
    heading_i: np.ndarray,
    heading_j: np.ndarray,
    length_i: np.ndarray,
    width_i: np.ndarray,
    length_j: np.ndarray,
    width_j: np.ndarray,
) -> np.ndarray:
    """``(k,)`` bool: rectangle ``j`` at offset ``d[k]`` (``(k, 2)``, centre ``j`` minus centre ``i``)
    overlaps rectangle ``i``; headings and sizes per pair."""
    ci, si = np.cos(heading_i), np.sin(heading_i)
    cj, sj = np.cos(heading_j), np.sin(heading_j)
    c = np.abs(ci * cj + si * sj)  # |cos(h_j - h_i)|
    s = np.abs(ci * sj - si * cj)  # |sin(h_j - h_i)|
    li, wi, lj, wj = 0.5 * length_i, 0.5 * width_i, 0.5 * length_j, 0.5 * width_j
    return (
        (np.abs(d[:, 0] * ci + d[:, 1] * si) < li + lj * c + wj * s)
        & (np.abs(-d[:, 0] * si + d[:, 1] * ci) < wi + lj * s + wj * c)
        & (np.abs(d[:, 0] * cj + d[:, 1] * sj) < lj + li * c + wi * s)
        & (np.abs(-d[:, 0] * sj + d[:, 1] * cj) < wj + li * s + wi * c)
    )
