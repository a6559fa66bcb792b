"""The shield's liveness watchdog: when traffic waits before the lines and nothing crosses, a live planner drives.

The shield (:class:`envs.planners.shield.Shield`) keeps the vehicles *inside* the intersection moving,
but before its stop line a planner decides: one that holds every vehicle there forever stalls the
junction, shield or not. :class:`LivenessWatchdog` reads the scenes the shield is handed (the
simulation's state, never the planner's copy) and decides, every step, who proposes: the wrapped
planner, or a live fallback planner (FIFO's order by default) whose commands the shield checks as any
other proposal.

Definitions, from the scene alone:

- A vehicle's *phase* is 0 before its stop line (``dist_to_entry >= 0``: its front has not passed the
  line), 1 inside the intersection area, 2 once its rear has left it (``dist_to_exit <= 0``). A
  *crossing* is a vehicle (matched by ``vehicle_id`` to the previous scene) whose phase rose since the
  previous scene: it entered or left the intersection.
- A vehicle *waits* from the first scene in which it stands (speed below
  :data:`envs.simulation.scene.STOP_SPEED`) before its line, until it enters (moving on again before
  the line does not end its wait: a planner cannot reset the clock by creeping). A vehicle still
  before its line when it is *due* there (when it would have reached the line in free flow,
  :mod:`envs.simulation.free_flow`, from where and how fast it was first seen) has waited since it was
  first seen, as the harness's standstill counts: a planner that holds its vehicles at a crawl, never
  standing, starves the junction as surely as one that stops them.
- The junction has *stalled for* ``now - max(last crossing, earliest start of a wait among the vehicles
  now before their lines)``; 0 when no vehicle before its line waits.

The rule: once the junction has stalled for ``after`` seconds, the live planner takes over (a
*takeover*, counted). It hands control back ``hold`` seconds after the first vehicle entered the
intersection under its control (a vehicle leaving does not count: the takeover is there to let the
waiting ones in), and the clock restarts from the last crossing. A scene earlier than the previous one starts
a new run (the watchdog forgets the traffic of the old one; :meth:`LivenessWatchdog.reset` also zeroes
the counters). Vectorized over vehicles (a sorted id lookup per step).
"""

from __future__ import annotations

import numpy as np

from envs.simulation.free_flow import free_flow_table, time_at
from envs.simulation.scene import STOP_SPEED, Scene

# Default seconds without a crossing, while vehicles wait before their lines, before the live planner
# takes over; and seconds after its first crossing before it hands back.
WATCHDOG_AFTER = 10.0
WATCHDOG_HOLD = 5.0


def phases(scene: Scene) -> np.ndarray:
    """``(n,)`` int8: 0 before the stop line, 1 inside the intersection area, 2 once the rear has left it."""
    return (np.asarray(scene.dist_to_entry) < 0).astype(np.int8) + (np.asarray(scene.dist_to_exit) <= 0)


class LivenessWatchdog:
    """Decides per scene whether the live planner drives (see the module docstring).

    :param after: seconds stalled before a takeover (> 0)
    :param hold: seconds after the first entry of a takeover before control returns (>= 0)
    """

    def __init__(self, after: float = WATCHDOG_AFTER, hold: float = WATCHDOG_HOLD) -> None:
        after, hold = float(after), float(hold)
        if not after > 0 or not np.isfinite(after):
            raise ValueError(f"watchdog_after must be a finite number of seconds > 0 (or None: off), got {after}")
        if not hold >= 0 or not np.isfinite(hold):
            raise ValueError(f"watchdog_hold must be a finite number of seconds >= 0, got {hold}")
        self.after = after
        self.hold = hold
        self.reset()

    def reset(self) -> None:
        """Forget the run: no takeover, counters at 0."""
        self.takeovers = 0
        self.vehicle_steps = 0
        self._forget()

    def _forget(self) -> None:
        """Forget the traffic seen (a new run): no takeover, no clock."""
        self.active = False
        self._started = 0.0
        self._time: float | None = None
        self._crossed_at = 0.0
        self._entered_at = -np.inf
        self._first_entry: float | None = None  # of the takeover in progress
        self._ids = np.zeros(0, np.int64)  # the previous scene's ids, sorted
        self._phase = np.zeros(0, np.int8)  # and their phases
        self._waits = np.zeros(0)  # and when each started to wait (inf: never stood before its line)
        self._due = np.zeros(0)  # and when each would have reached its line in free flow (inf: unknown)
        self._seen = np.zeros(0)  # and when each was first seen

    def stalled_for(self, scene: Scene) -> float:
        """Update the clock with a scene; how long the junction has stalled [s] (see the module docstring)."""
        now = float(scene.time)
        if self._time is None or now < self._time:  # the first scene of a run
            self._forget()
            self._crossed_at = now
        self._time = now
        ids = np.asarray(scene.vehicle_id, np.int64)
        phase = phases(scene)
        waits = np.full(ids.shape, np.inf)
        known = np.zeros(ids.shape, bool)
        due = np.full(ids.shape, np.inf)
        seen = np.full(ids.shape, now)
        if self._ids.size and ids.size:
            k = np.minimum(np.searchsorted(self._ids, ids), self._ids.size - 1)
            known = self._ids[k] == ids
            rose = known & (phase > self._phase[k])
            if rose.any():
                self._crossed_at = now
                if (rose & (self._phase[k] == 0)).any():
                    self._entered_at = now
            waits = np.where(known, self._waits[k], np.inf)
            due = np.where(known, self._due[k], np.inf)
            seen = np.where(known, self._seen[k], now)
        before = phase == 0
        due = np.where(known, due, now + _free_flow_to_line(scene, ~known & before))
        waits = np.where(before & (np.asarray(scene.speed) < STOP_SPEED), np.minimum(waits, now), waits)
        order = np.argsort(ids, kind="stable")
        self._ids, self._phase, self._waits = ids[order], phase[order], waits[order]
        self._due, self._seen = due[order], seen[order]
        started = np.minimum(waits, np.where(due <= now, seen, np.inf))
        since = started[before].min(initial=np.inf)
        return now - max(self._crossed_at, since) if np.isfinite(since) else 0.0

    def observe(self, scene: Scene) -> bool:
        """Read one scene (once per step, in order); whether the live planner drives this step.

        :param scene: the vehicles now (the simulation's state)
        :return: ``True`` while a takeover lasts
        """
        stalled = self.stalled_for(scene)
        now = float(scene.time)
        if self.active:
            if self._first_entry is None and self._entered_at > self._started:
                self._first_entry = self._entered_at
            if self._first_entry is not None and now - self._first_entry >= self.hold:
                self.active = False
        elif stalled >= self.after:
            self.active = True
            self.takeovers += 1
            self._started = now
            self._first_entry = None
        if self.active:
            self.vehicle_steps += scene.num_vehicles
        return self.active


def _free_flow_to_line(scene: Scene, rows: np.ndarray) -> np.ndarray:
    """``(n,)`` seconds that each of ``rows`` needs to reach its stop line in free flow from where it is (at the
    scene's acceleration bounds); ``inf`` for the other rows and without a layout (hand-built scenes)."""
    out = np.full(scene.num_vehicles, np.inf)
    if not rows.any() or getattr(scene, "layout", None) is None or getattr(scene, "arc", None) is None:
        return out
    a_max, a_min = float(scene.a_max), float(scene.a_min)
    table = free_flow_table(scene.layout, scene.route[rows], scene.arc[rows], scene.speed[rows], a_max, -a_min)
    out[rows] = time_at(table, np.maximum(scene.dist_to_entry[rows], 0.0), scene.layout.ds)
    return out
