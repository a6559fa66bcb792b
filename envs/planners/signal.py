"""An actuated traffic signal: what real intersections run, and what traffic engineers compare against.

Two phases by default, one per road: the major road's approaches, then the minor road's (a T
junction's minor arm is a phase of its own). A phase's green lasts at least ``min_green``; it is
extended while its detectors keep seeing vehicles (a presence detector ``detector_length``
metres long before each stop line) and ends when no vehicle has been seen for ``gap`` seconds
(gap-out) or after ``max_green`` (max-out), but only when another phase has a vehicle waiting;
otherwise the green rests. Every green ends with ``yellow`` and ``all_red`` seconds.

Vehicles: on red, and on yellow or all-red when they can still stop comfortably (braking at most
``stop_decel``), they stop at the line (IDM with a standing obstacle there, see
:func:`envs.planners.idm.stop_line_acceleration`); a vehicle that cannot stop any more proceeds.
On green, turning vehicles yield as under the priority rules (permitted left turns give way to
oncoming traffic, and everyone to vehicles still in the intersection,
:func:`envs.planners.idm.blocked_by_rank`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envs.planners.base import Planner
from envs.planners.idm import DEFAULT_IDM, CrossingParams, IDMParams, accelerations_with_stops, blocked_by_rank
from envs.planners.priority_rules import maneuver_priority
from envs.planners.vehicle_model import model_crossing_times
from envs.planners.yielding import rank_by
from envs.simulation.scene import MAJOR, Scene

GREEN, YELLOW, ALL_RED = "green", "yellow", "all_red"


@dataclass(frozen=True)
class SignalParams:
    """Signal timing (defaults: tuned, see ``docs/baselines.md``).

    :param min_green: shortest green [s]
    :param max_green: longest green while another phase waits [s]
    :param gap: a green ends this long after its detectors last saw a vehicle [s]
    :param yellow: yellow time [s]
    :param all_red: all-red time after the yellow [s]
    :param detector_length: presence detector before each stop line [m]
    :param stop_decel: a vehicle stops for yellow when it can with at most this deceleration [m/s^2]
    """

    min_green: float = 6.5
    max_green: float = 36.0
    gap: float = 3.4
    yellow: float = 3.1
    all_red: float = 2.5
    detector_length: float = 36.0
    stop_decel: float = 3.0


class SignalController:
    """The phase state machine, one per intersection (scalar state, no vehicles).

    :param params: timing
    :param num_phases: number of phases, served in turn
    """

    def __init__(self, params: SignalParams, num_phases: int) -> None:
        self.params = params
        self.num_phases = num_phases
        self.reset()

    def reset(self, time: float = 0.0) -> None:
        """Green for phase 0 from ``time``."""
        self.phase = 0
        self.stage = GREEN
        self.since = time
        self.last_seen = time

    def update(self, time: float, detected: np.ndarray, waiting: np.ndarray) -> tuple[int, str]:
        """Advance to ``time``.

        :param time: now [s]
        :param detected: ``(P,)`` bool: a vehicle is on a detector of the phase
        :param waiting: ``(P,)`` bool: a vehicle of the phase approaches its line
        :return: ``(phase, stage)`` now
        """
        p = self.params
        if self.stage == GREEN:
            if detected[self.phase]:
                self.last_seen = time
            others = np.delete(np.asarray(waiting, bool), self.phase).any()
            elapsed = time - self.since
            gap_out = time - self.last_seen >= p.gap
            if others and elapsed >= p.min_green and (gap_out or elapsed >= p.max_green):
                self.stage, self.since = YELLOW, time
        elif self.stage == YELLOW and time - self.since >= p.yellow:
            self.stage, self.since = ALL_RED, time
        elif self.stage == ALL_RED and time - self.since >= p.all_red:
            later = [(self.phase + k) % self.num_phases for k in range(1, self.num_phases + 1)]
            self.phase = next((q for q in later if waiting[q]), later[0])
            self.stage, self.since, self.last_seen = GREEN, time, time
        return self.phase, self.stage


def route_phases(layout) -> np.ndarray:
    """``(R,)`` phase of each route: 0 for the major road's approaches, 1 for the minor road's."""
    return np.where(layout.priority == MAJOR, 0, 1).astype(np.int64)


class SignalPlanner(Planner):
    """Vehicles obey an actuated two-phase signal, IDM car following, permitted turns yield.

    :param name: the name shown in reports
    :param params: signal timing
    :param idm: IDM constants
    :param crossing: timing rules of the yielding on green
    :param governor_deceleration: the simulation's governor deceleration [m/s^2]
    """

    def __init__(
        self,
        name: str = "SIGNAL",
        params: SignalParams | None = None,
        idm: IDMParams = DEFAULT_IDM,
        crossing: CrossingParams | None = None,
        governor_deceleration: float = 3.0,
    ) -> None:
        super().__init__(name)
        self.params = params if params is not None else SignalParams()
        self.idm = idm
        self.crossing = crossing if crossing is not None else CrossingParams()
        self.governor_deceleration = governor_deceleration
        self.controller = SignalController(self.params, 2)

    def reset(self, seed: int | None = None) -> None:
        self.controller.reset()

    def act(self, scene: Scene) -> np.ndarray:
        if scene.time <= 0.0:  # a new episode (the harness also calls reset)
            self.controller.reset(scene.time)
        phase_of = route_phases(scene.layout)[scene.route]
        dist, v = scene.dist_to_entry, scene.speed
        before = (scene.dist_to_exit > 0) & (dist > 0)
        phases = np.arange(self.controller.num_phases)
        mine = phase_of[None, :] == phases[:, None]  # (P, n)
        detected = (mine & (before & (dist <= self.params.detector_length))[None, :]).any(axis=1)
        waiting = (mine & before[None, :]).any(axis=1)
        phase, stage = self.controller.update(scene.time, detected, waiting)
        if scene.num_vehicles == 0:
            return np.zeros(0)
        green = phase_of == phase if stage == GREEN else np.zeros(scene.num_vehicles, bool)
        can_stop = v**2 <= 2.0 * self.params.stop_decel * np.maximum(dist, 0.0)
        red_stop = before & ~green & can_stop
        times = model_crossing_times(scene, self.crossing, self.governor_deceleration)
        rank = rank_by(~green, maneuver_priority(scene.priority, scene.maneuver), times[0], scene.vehicle_id)
        blocked = blocked_by_rank(scene, rank, self.crossing, times=times)
        return accelerations_with_stops(scene, red_stop | (blocked & green), self.crossing, self.idm)
