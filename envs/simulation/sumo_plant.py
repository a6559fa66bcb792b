"""Eclipse SUMO as the plant (:mod:`envs.simulation.plant`), through libsumo.

The network is generated from the layout (:mod:`envs.simulation.sumo_network`), so both plants drive on the
same geometry. SUMO runs with:

- a step of ``1 / simulation_frequency`` seconds, which must be a whole number of milliseconds (SUMO counts
  time in ms: 20 Hz and 10 Hz are exact, our default 15 Hz is not) and divide the policy period;
- ballistic integration (``--step-method.ballistic``): over a step of constant acceleration the position
  moves by the mean of the two speeds times the step, as in our :func:`~envs.simulation.engine.integrate`;
- collision checks on the junction too (``--collision.check-junctions``), with action ``warn`` (the run goes
  on; the environment decides what a collision does) and ``--collision.mingap-factor 0`` (a collision is a
  contact, not a short gap); teleports off (``--time-to-teleport -1``); lane changes off.

Connected vehicles are commanded in speed mode 0 (SUMO checks nothing) with ``setAcceleration``, one per
sub-step: the speeds of our own vehicle model over the policy step (the acceleration bounds, ``[0,
max_speed]`` and our speed governor's envelope of the lane limits), so that their motion is ours, integrated
by SUMO. Their type has no driver imperfection and no speed deviation. Human-driven vehicles are SUMO's own:
its default type (Krauss car following with its imperfection, a random speed factor, SUMO's right of way at
the junction); the command of their rows is ignored.

The truth is read back each sub-step with one subscription per vehicle (``getAllSubscriptionResults``): the
speed and the distance driven since insertion. SUMO places a vehicle by its front bumper; our rows hold the
centre, half a length behind the front along the route. A vehicle appears in SUMO at the next sub-step (SUMO
inserts during a step): it enters at the state that our model gives it after the first sub-step, so that it
is where our plant would have it. A vehicle that SUMO refuses to insert, or removes on its own, leaves the
rows and is reported in :attr:`~envs.simulation.engine.StepEvents.lost` and :attr:`SumoPlant.lost`.

libsumo runs one simulation per process: the first open :class:`SumoPlant` of a process uses it, any other one
starts SUMO as a process of its own and talks to it over TraCI (the same calls, slower; an evaluation environment
next to a training one, say). :meth:`SumoPlant.close` ends either.
"""

from __future__ import annotations

import atexit
import contextlib
import io
import itertools
import shutil
import subprocess
from typing import Any

import numpy as np

from envs.simulation.engine import STOP_SPEED, PlantError, StepEvents, VehicleTable, integrate, table_settings
from envs.simulation.layouts import Layout
from envs.simulation.sumo_network import SumoNetwork, write_network

_INT = np.int64
SUMO_EXTRA_HINT = 'the SUMO plant needs the sumo extra: pip install "sb3-graph[sumo]"'
# SUMO's step at the 5 Hz policy: 50 ms (SUMO counts whole milliseconds: our default 15 Hz is not one).
SUMO_PLANT_FREQUENCY = 20
CONNECTED_TYPE = "connected"
HUMAN_TYPE = "human"
# libsumo's one simulation of this process: the plant that holds it, or None.
_OPEN: list[SumoPlant] = []
_LABELS = itertools.count()
# Networks generated in this process, per layout: netconvert runs once per layout, into a temporary folder
# that is removed when the process ends.
_NETWORKS: dict[tuple[str, float], SumoNetwork] = {}


def libsumo_module() -> Any:
    """The ``libsumo`` module.

    :raises ImportError: in one line naming the ``sumo`` extra, when it is not installed
    """
    try:
        import libsumo
        import sumolib  # noqa: F401  (netconvert's path and the network reader)
        import traci  # noqa: F401  (a second plant of the process)
    except ImportError:
        raise ImportError(SUMO_EXTRA_HINT) from None
    return libsumo


def sumo_errors() -> tuple[type[BaseException], ...]:
    """What libsumo and TraCI raise when SUMO fails: an error of a call, or a SUMO (process) that died."""
    libsumo = libsumo_module()
    import traci

    return (
        libsumo.TraCIException, libsumo.FatalTraCIError, traci.exceptions.TraCIException,
        traci.exceptions.FatalTraCIError, ConnectionError,
    )  # fmt: skip


def step_length_allowed(simulation_frequency: int) -> bool:
    """SUMO counts time in milliseconds: its step must be a whole number of them."""
    return 1000 % int(simulation_frequency) == 0


def network_of(layout: Layout) -> SumoNetwork:
    """The SUMO network of ``layout``, generated once per process into a temporary folder."""
    key = (layout.name, float(layout.lateral_acceleration))
    if key not in _NETWORKS:
        libsumo_module()
        _NETWORKS[key] = write_network(layout)
        atexit.register(shutil.rmtree, _NETWORKS[key].folder, True)
    return _NETWORKS[key]


class SumoPlant(VehicleTable):
    """The vehicles moved by Eclipse SUMO (see the module docstring); the columns and the scene as in our plant.

    :param layout: the intersection
    :param simulation_frequency: SUMO's step rate [Hz]: ``1000`` must be a multiple of it, and it of
        ``policy_frequency`` (20 or 10 at the 5 Hz policy)
    :param policy_frequency: rate of new commands [Hz]
    :param max_speed: speed cap of connected vehicles [m/s]
    :param max_acceleration: commands are clipped to ``[-max_acceleration, max_acceleration]`` [m/s^2]
    :param s_ref: common reference length of the paths inside the intersection [m]
    :param max_vehicles: capacity; :meth:`add` refuses vehicles beyond it
    :param governor_deceleration: our speed governor's deceleration, applied to connected vehicles [m/s^2]
    :param network: the generated network (default: :func:`network_of` the layout)
    :param seed: SUMO's random seed (its drivers' imperfection and speed factors)
    :raises ImportError: without the ``sumo`` extra
    :raises PlantError: netconvert failed on the layout, or SUMO failed to start (one line)
    """

    COLUMNS = VehicleTable.COLUMNS + ("origin", "in_sumo", "front_position")
    drives_humans = True  # SUMO's own drivers: the environment's human model is not asked

    @classmethod
    def from_config(cls, layout: Layout, config: dict[str, Any], seed: int | None = None) -> SumoPlant:
        """The plant that a validated environment configuration asks for (as :meth:`Simulation.from_config`);
        ``seed`` seeds SUMO's drivers (default 0)."""
        return cls(layout, **table_settings(config), seed=0 if seed is None else int(seed))

    def __init__(
        self,
        layout: Layout,
        simulation_frequency: int = SUMO_PLANT_FREQUENCY,
        policy_frequency: int = 5,
        max_speed: float = 20.0,
        max_acceleration: float = 5.0,
        s_ref: float = 25.0,
        max_vehicles: int = 64,
        governor_deceleration: float = 3.0,
        network: SumoNetwork | None = None,
        seed: int = 0,
    ) -> None:
        libsumo_module()
        if not step_length_allowed(simulation_frequency):
            raise ValueError(
                f"simulation_frequency must divide 1000 for the SUMO plant (a step of whole milliseconds, "
                f"e.g. 20 or 10), got {simulation_frequency}"
            )
        try:
            self.network = network if network is not None else network_of(layout)
        except ValueError as error:  # netconvert failed: every run of this layout fails, each in one line
            raise PlantError(str(error)) from None
        self.seed = int(seed)
        self.lost: dict[int, str] = {}
        self.front_position = np.zeros((0, 2))
        self._sumo: Any = None  # libsumo, or a TraCI connection (see _open)
        self._errors = sumo_errors()
        self.backend = ""
        self._closed = False
        try:
            super().__init__(
                layout, simulation_frequency, policy_frequency, max_speed, max_acceleration, s_ref, max_vehicles,
                governor_deceleration,
            )  # fmt: skip
        except Exception:
            self.close()
            raise

    # ------------------------------------------------------------------ SUMO's life
    def _arguments(self) -> list[str]:
        return [
            "sumo", "-n", str(self.network.net_file), "--step-length", f"{1.0 / self.simulation_frequency:.6f}",
            "--step-method.ballistic", "--collision.check-junctions", "--collision.action", "warn",
            "--collision.mingap-factor", "0", "--time-to-teleport", "-1", "--seed", str(self.seed),
            "--no-step-log", "--no-warnings", "--duration-log.disable",
        ]  # fmt: skip

    def reset(self) -> None:
        """Empty the scene, set the clock to 0 and (re)start SUMO on the network.

        :raises PlantError: SUMO failed to start or load, in one line
        """
        if getattr(self, "_closed", True):
            raise RuntimeError("this SUMO plant is closed")
        super().reset()
        self.origin = np.zeros(0)  # the centre's arc when SUMO's odometer read 0 (at insertion)
        self.in_sumo = np.zeros(0, bool)  # inserted (a new row enters SUMO at the next step)
        self.front_position = np.zeros((0, 2))
        self.lost = {}
        try:
            if self._sumo is None:
                self._open()
            else:
                self._sumo.load(self._arguments()[1:])
            sumo = self._sumo
            for r, edges in enumerate(self.network.route_edges):
                sumo.route.add(f"r{r}", list(edges))
            self._define_types()
        except self._errors as error:  # SUMO refused the network or its options, or its process died
            raise PlantError(f"SUMO at reset: {_one_line(error)}") from None

    def _define_types(self) -> None:
        sumo, a_max = self._sumo, self.max_acceleration
        sumo.vehicletype.copy("DEFAULT_VEHTYPE", HUMAN_TYPE)  # SUMO's own driver, imperfection and all
        sumo.vehicletype.copy("DEFAULT_VEHTYPE", CONNECTED_TYPE)
        t = CONNECTED_TYPE
        sumo.vehicletype.setAccel(t, a_max)
        sumo.vehicletype.setDecel(t, a_max)
        sumo.vehicletype.setEmergencyDecel(t, max(a_max, 9.0))
        sumo.vehicletype.setMaxSpeed(t, self.max_speed)
        sumo.vehicletype.setSpeedFactor(t, 1.0)
        sumo.vehicletype.setSpeedDeviation(t, 0.0)
        sumo.vehicletype.setImperfection(t, 0.0)
        # Insertion checks only: connected vehicles are commanded in speed mode 0. Our spawn rule keeps the
        # gap for braking at a_max; a headway of one step makes SUMO's insertion check agree with it.
        sumo.vehicletype.setTau(t, 1.0 / self.simulation_frequency)

    def _open(self) -> None:
        """Start SUMO: in this process through libsumo when no other plant of the process holds it (libsumo runs
        one simulation per process), else as a process of its own over TraCI (the same calls, slower)."""
        libsumo = libsumo_module()
        if not _OPEN and not libsumo.simulation.isLoaded():
            libsumo.start(self._arguments())
            self._sumo, self.backend = libsumo, "libsumo"
            _OPEN.append(self)
            return
        import sumolib
        import traci

        port = sumolib.miscutils.getFreeSocketPort()
        command = [sumolib.checkBinary("sumo"), *self._arguments()[1:], "--remote-port", str(port)]
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL)
        label = f"sb3-graph-{next(_LABELS)}"  # TraCI's connections are named; each plant gets a new name
        with contextlib.redirect_stdout(io.StringIO()):  # traci prints a line per try while SUMO opens its port
            self._sumo = traci.connect(port, numRetries=500, proc=process, waitBetweenRetries=0.02, label=label)
        self.backend = "traci"

    def close(self) -> None:
        """Close SUMO (a plant made afterwards may use libsumo again)."""
        if not self._closed:
            self._closed = True
            if self in _OPEN:
                _OPEN.remove(self)
            if self._sumo is not None:
                with contextlib.suppress(*self._errors, OSError):  # a SUMO that died has nothing left to close
                    self._sumo.close()

    def set_state(self, *args: Any, **kwargs: Any) -> None:
        """Not available: SUMO's clock runs forward only, and it cannot place a vehicle inside a junction."""
        raise NotImplementedError("the SUMO plant cannot replace its scene; reset() it and add() vehicles")

    # ------------------------------------------------------------------ vehicles
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
        """Append vehicles (as :meth:`VehicleTable.add`); they enter SUMO at the next :meth:`step`.

        :raises ValueError: as :meth:`VehicleTable.add`, and for a vehicle whose front lies inside the
            junction (SUMO inserts vehicles on edges only)
        """
        k = np.atleast_1d(np.asarray(route)).shape[0]
        super().add(route, speed, vehicle_id, length, width, arc, human)
        rows = slice(self.num_vehicles - k, self.num_vehicles)
        self._edge_of_front(self.route[rows], self.arc[rows] + self.length[rows] / 2)  # checks the place
        self.origin = np.concatenate([self.origin, self.arc[rows]])
        self.in_sumo = np.concatenate([self.in_sumo, np.zeros(k, bool)])
        self.front_position = np.concatenate([self.front_position, np.full((k, 2), np.nan)])

    def _edge_of_front(self, route: np.ndarray, front: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The index of the route edge that holds each front and the front's position on it [m]."""
        net = self.network
        edge = np.empty(route.shape[0], _INT)
        position = np.empty(route.shape[0])
        for i, (r, x) in enumerate(zip(route.tolist(), front.tolist())):  # new vehicles only: a few per step
            starts = net.edge_arcs[r]
            lengths = [length for lane, length in net.lane_lengths[r] if not lane.startswith(":")]
            e = int(np.searchsorted(starts, x, side="right") - 1)
            if e < 0 or x > starts[e] + lengths[e]:
                raise ValueError(
                    f"the SUMO plant inserts vehicles on edges only: a front at {x:.2f} m on route "
                    f"{self.layout.route_names[r]!r} lies inside a junction"
                )
            edge[i], position[i] = e, x - starts[e]
        return edge, position

    def _insert(self, rows: np.ndarray, front: np.ndarray, speed: np.ndarray) -> None:
        """Add ``rows`` to SUMO with their fronts at ``front`` and ``speed`` (humans: SUMO's safe speed)."""
        sumo = self._sumo
        edge, position = self._edge_of_front(self.route[rows], front)
        for j, row in enumerate(rows.tolist()):  # new vehicles only
            vid, r, e = str(int(self.vehicle_id[row])), int(self.route[row]), int(edge[j])
            route_id = f"r{r}" if e == 0 else self._route_from(r, e)
            human = bool(self.human[row])
            sumo.vehicle.add(
                vid, route_id, HUMAN_TYPE if human else CONNECTED_TYPE, depart="now",
                departPos=f"{position[j]:.6f}", departSpeed="max" if human else f"{speed[j]:.9f}",
            )  # fmt: skip
            sumo.vehicle.setLength(vid, float(self.length[row]))
            sumo.vehicle.setWidth(vid, float(self.width[row]))
            sumo.vehicle.setLaneChangeMode(vid, 0)
            if not human:
                sumo.vehicle.setSpeedMode(vid, 0)
            sumo.vehicle.subscribe(vid, (_VAR_SPEED, _VAR_DISTANCE, _VAR_POSITION))

    def _route_from(self, r: int, e: int) -> str:
        """The route ``r`` from its edge ``e`` on (a vehicle placed further along its route)."""
        route_id = f"r{r}_{e}"
        if route_id not in self._sumo.route.getIDList():
            self._sumo.route.add(route_id, list(self.network.route_edges[r][e:]))
        return route_id

    # ------------------------------------------------------------------ dynamics
    def step(self, acceleration: np.ndarray, remove_collided: bool = False) -> StepEvents:
        """Apply the commanded accelerations for one policy period in SUMO (see the module docstring).

        :param acceleration: ``(n,)`` commanded accelerations [m/s^2]; ignored for human-driven rows
        :param remove_collided: take the vehicles of this step's collisions out of the scene (and SUMO)
        :return: the events of the step; finished and lost vehicles are already removed
        :raises PlantError: a libsumo or TraCI error (a refused call, a SUMO process that died), in one line
        """
        if self._closed:
            raise RuntimeError("this SUMO plant is closed: reset() the environment first")
        try:
            return self._step(acceleration, remove_collided)
        except self._errors as error:
            raise PlantError(f"SUMO at t = {self.time:.2f} s: {_one_line(error)}") from None

    def _step(self, acceleration: np.ndarray, remove_collided: bool) -> StepEvents:
        """:meth:`step` without its error handling."""
        n = self.num_vehicles
        a_max, h, substeps = self.max_acceleration, 1.0 / self.simulation_frequency, self.substeps
        acc = np.minimum(np.maximum(np.asarray(acceleration, float).reshape(n), -a_max), a_max)
        acc = np.where(self.human, 0.0, acc)
        exit_arc = self.layout.exit_arc[self.route]
        before_exit = self.arc < exit_arc
        plan_v, plan_x, governed = integrate(
            self.layout, self.route, self.arc, self.speed, acc, substeps, h, self.max_speed, self.governor_deceleration
        )
        new = np.flatnonzero(~self.in_sumo)
        if new.size:  # they appear in SUMO after its next step, where our model has them then
            self._insert(new, plan_x[1, new] + self.length[new] / 2, plan_v[1, new])
            self.origin = self.origin.copy()
            self.origin[new] = plan_x[1, new]
        ids = [str(i) for i in self.vehicle_id.tolist()]
        speed, distance, front, pairs, present = self._run(ids, plan_v, h, new)
        lost = ~present
        arc = self.origin + distance
        self.speed = np.where(present, speed[-1], self.speed)
        self.arc = np.where(present, arc, self.arc)
        self.front_position = front
        self.in_sumo = present
        self.time += self.dt
        rows = _collision_rows(pairs, ids, n)
        events = StepEvents(
            stopped=self.vehicle_id[(speed[1:] < STOP_SPEED).any(axis=0) & present],
            crossed=self.vehicle_id[before_exit & (self.arc >= exit_arc) & present],
            collisions=self.vehicle_id[rows],
            governed=self.vehicle_id[governed & ~self.human],
            moved=self.vehicle_id,
            speeds=np.where(np.isnan(speed), self.speed, speed),
            lost=self.vehicle_id[lost],
        )
        for vid in events.lost.tolist():
            self.lost[int(vid)] = "SUMO did not insert it" if vid in self.vehicle_id[new] else "SUMO removed it"
        done = (self.arc >= self.layout.length[self.route]) | lost
        if remove_collided and rows.size:
            done[rows.ravel()] = True
        for row in np.flatnonzero(done & present).tolist():  # the vehicles that leave: a few per step
            self._sumo.vehicle.unsubscribe(ids[row])  # else libsumo asks for it in the next step
            self._sumo.vehicle.remove(ids[row])
        pending = set(self._sumo.simulation.getPendingVehicles())
        for row in np.flatnonzero(lost).tolist():  # refused at insertion: SUMO would insert it later
            if ids[row] in pending:
                self._sumo.vehicle.unsubscribe(ids[row])
                self._sumo.vehicle.remove(ids[row])
        events.kept = ~done
        events.removed = self.vehicle_id[done]
        if done.any():
            self._keep(~done)
        return events

    def _run(
        self, ids: list[str], plan_v: np.ndarray, h: float, new: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, set[tuple[str, str]], np.ndarray]:
        """SUMO's sub-steps of one policy step.

        :return: ``(S + 1, n)`` speeds (row 0: now; NaN where SUMO no longer has the vehicle), ``(n,)``
            distances since insertion, ``(n, 2)`` front bumpers in the layout's frame, the colliding id pairs,
            ``(n,)`` bool: SUMO still has the vehicle
        """
        sumo = self._sumo
        n = len(ids)
        speed = np.full((self.substeps + 1, n), np.nan)
        speed[0] = self.speed
        distance = np.zeros(n)
        front = np.full((n, 2), np.nan)
        present = np.ones(n, bool)
        commanded = (~self.human).copy()
        commanded[new] = False  # their first sub-step is their insertion
        command = np.diff(plan_v, axis=0) / h
        pairs: set[tuple[str, str]] = set()
        for k in range(self.substeps):  # a loop over time, vectorized over vehicles but for libsumo's calls
            for row in np.flatnonzero(commanded & present).tolist():
                sumo.vehicle.setAcceleration(ids[row], float(command[k, row]), h)
            sumo.simulation.step()
            results = sumo.vehicle.getAllSubscriptionResults()
            # A vehicle that SUMO has not inserted (yet) answers its subscription with libsumo's invalid value.
            values = [v if v is not None and v[_VAR_SPEED] >= 0.0 else None for v in map(results.get, ids)]
            present &= np.array([v is not None for v in values], bool)
            speed[k + 1] = [v[_VAR_SPEED] if v is not None else np.nan for v in values]
            distance = np.array([v[_VAR_DISTANCE] if v is not None else np.nan for v in values])
            front = np.array([v[_VAR_POSITION] if v is not None else (np.nan, np.nan) for v in values], float)
            pairs.update((c.collider, c.victim) for c in sumo.simulation.getCollisions())
            commanded[new] = ~self.human[new]
        front = front.reshape(n, 2) * (1.0, -1.0)  # SUMO's y points north, the layout's south
        speed[:, ~present] = np.nan
        return speed, np.where(present, distance, 0.0), front, pairs, present


def _one_line(error: BaseException) -> str:
    """An error's message on one line (SUMO's may span several), with its kind when it says nothing."""
    text = " ".join(str(error).split())
    return text or type(error).__name__


def _collision_rows(pairs: set[tuple[str, str]], ids: list[str], n: int) -> np.ndarray:
    """``(k, 2)`` row pairs ``i < j`` of SUMO's collisions among the rows (sorted, each pair once)."""
    if not pairs:
        return np.zeros((0, 2), _INT)
    row = {vid: r for r, vid in enumerate(ids)}
    found = np.array([sorted((row[a], row[b])) for a, b in pairs if a in row and b in row], _INT).reshape(-1, 2)
    code = np.unique(found[:, 0] * n + found[:, 1])
    return np.stack([code // n, code % n], axis=1)


# libsumo's variable ids (libsumo.constants), kept here so that importing this module needs no SUMO.
_VAR_SPEED = 0x40
_VAR_POSITION = 0x42
_VAR_DISTANCE = 0x84
