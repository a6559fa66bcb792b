"""Reservation per conflict zone in the spirit of Dresner & Stone's AIM (autonomous intersection management).

Every route pair that crosses or merges has a conflict zone on each of the two routes
(:attr:`envs.simulation.layouts.Layout.zone_start`, :attr:`~envs.simulation.layouts.Layout.zone_end`). A vehicle's body
occupies a zone from the moment its front bumper reaches the zone's start until its rear bumper
leaves the zone's end. Each policy step the planner re-plans every vehicle that has not left the
intersection:

1. **Candidate plans** from the vehicle model (:mod:`envs.planners.vehicle_model`), each a
   time-parametrised speed profile to the stop line followed by the crossing at ``accel`` up to
   the lowest limit inside the intersection:

   - the earliest arrival (accelerate, cruise at the road's limit, brake for the line's limit);
   - *slowed approaches*: change speed to a cruise speed ``u`` (a grid in steps of
     ``speed_step``), cruise, and accelerate again in time to reach the line as fast as the
     remaining distance allows; a slower ``u`` arrives later, mostly without stopping;
   - *stops*: come to rest at the line and start from rest at a later time (steps of
     ``wait_step`` up to ``wait_horizon``).

   Each candidate gives, for every zone on the vehicle's path, the time window its body occupies
   it.
2. **Order**: first in, first out by the earliest possible arrival at the line, fixed when the
   vehicle is first seen (a follower never before its leader). Vehicles that can no longer stop
   before their line (braking harder than ``commit_decel``) or are inside keep their
   reservations: they come first.
3. **Reservations**: each vehicle takes its best candidate (the one that leaves its last zone
   soonest; a stop costs ``stop_penalty`` seconds) whose windows keep ``buffer`` seconds from the
   windows of every earlier vehicle in the zones they share, and that arrives ``follow_headway``
   seconds after its leader. The order is a chain of dependencies, so the reservations are settled
   by a few passes (at most ``passes``), each vehicle against the previous pass's choices.
4. **Control**: each vehicle follows the first phase of its plan (accelerate, change speed
   towards ``u`` or stop at the line), capped by IDM car following.

Human drivers (mixed traffic, issue 39) ignore their reservations: one that the priority rules let go
now is booked first, in every candidate alike, with the window the shield predicts for it
(:func:`envs.planners.human.human_window`, ``human_margin``, ``human_horizon``), and the automated
vehicles reserve around it; one that the rules hold books nothing (it yields). Without humans none of
this runs.

Steps 1 and 3 run compiled (:mod:`envs.planners._aim_kernel`, numba), the only implementation;
``tests/aim_reference.py`` holds their NumPy form, the oracle that the kernels match bit for bit
(``tests/test_planner_regression.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from envs.planners import _aim_kernel
from envs.planners.base import Planner
from envs.planners.human import approach_limit, human_commands, human_window
from envs.planners.idm import (
    DEFAULT_IDM,
    IDMParams,
    idm_acceleration,
    leader_chain_max,
)
from envs.planners.vehicle_model import inner_limit, line_speed
from envs.simulation.scene import Scene


@dataclass(frozen=True)
class AIMParams:
    """Free parameters of :class:`AIMPlanner` (defaults: tuned, see ``docs/baselines.md``).

    :param accel: acceleration planned and commanded when crossing or speeding up [m/s^2]
    :param decel: deceleration planned and commanded to slow an approach or stop [m/s^2]
    :param commit_decel: a vehicle that would need more than this to stop before its line cannot
        stop any more: it keeps its place at the front of the order [m/s^2]
    :param buffer: seconds kept between one vehicle's window in a zone and another's
    :param follow_headway: seconds between a leader's and its follower's arrival at the line
    :param stop_penalty: seconds a plan that stops at the line counts as slower than it is
    :param speed_step: spacing of the cruise speeds of slowed approaches [m/s]
    :param wait_step: spacing of the start times of plans that stop [s]
    :param wait_horizon: latest start time of a plan that stops, after coming to rest [s]
    :param passes: most passes to settle the reservations
    :param governor_deceleration: the simulation's governor deceleration [m/s^2]
    :param human_margin: seconds added on both sides of a going human driver's predicted window in a
        zone (:func:`envs.planners.human.human_window`, the shield's rule)
    :param human_horizon: latest exit predicted for a going human driver at a crawl [s]
    """

    accel: float = 3.09
    decel: float = 2.27
    commit_decel: float = 4.62
    buffer: float = 0.04
    follow_headway: float = 1.33
    stop_penalty: float = 1.9
    speed_step: float = 0.5
    wait_step: float = 0.4
    wait_horizon: float = 12.0
    passes: int = 12
    governor_deceleration: float = 3.0
    human_margin: float = 1.0
    human_horizon: float = 8.0


@dataclass(frozen=True)
class Reservations:
    """The plans of one step, row ``i`` = vehicle ``i``.

    :param choice: ``(n,)`` index of the chosen candidate
    :param kind: ``(C,)`` ``0`` earliest, ``1`` slowed approach, ``2`` stop, per candidate
    :param cruise: ``(C,)`` cruise speed of each slowed approach [m/s] (``nan`` otherwise)
    :param arrival: ``(n, C)`` time the front reaches the line (0 inside) [s from now]
    :param line_speed: ``(n, C)`` speed at the line [m/s]
    :param base: ``(n, C)`` window of a vehicle in a zone it no longer has to pass: its arrival,
        not before its leader lets it (enter and leave alike) [s from now]
    :param zone_enter: ``(k, C)`` time the body enters its zone, one row per ``True`` of ``zone``
        in row-major order [s from now]
    :param zone_leave: ``(k, C)`` time it has left it
    :param zone: ``(n, R)`` bool: the vehicle still has to pass its zone with route ``q``
    :param start: ``(n, C)`` time a stopping plan starts from rest (``nan`` for the others) [s from now]
    :param rest: ``(n,)`` earliest time the vehicle can be at rest at its line [s from now]
    :param committed: ``(n,)`` bool: inside, or unable to stop before its line
    :param order: ``(n,)`` rank in the order of reservation (0 first)
    """

    choice: np.ndarray
    kind: np.ndarray
    cruise: np.ndarray
    arrival: np.ndarray
    line_speed: np.ndarray
    base: np.ndarray
    zone_enter: np.ndarray
    zone_leave: np.ndarray
    zone: np.ndarray
    start: np.ndarray
    rest: np.ndarray
    committed: np.ndarray
    order: np.ndarray

    def _full(self, windows: np.ndarray) -> np.ndarray:
        out = np.repeat(self.base[:, :, None], self.zone.shape[1], axis=2)
        zi, zq = np.nonzero(self.zone)
        out[zi, :, zq] = windows
        return out

    @property
    def enter(self) -> np.ndarray:
        """``(n, C, R)`` time the body enters its zone with route ``q`` (``base`` where it has none left)."""
        return self._full(self.zone_enter)

    @property
    def leave(self) -> np.ndarray:
        """``(n, C, R)`` time it has left it."""
        return self._full(self.zone_leave)

    def chosen(self) -> tuple[np.ndarray, np.ndarray]:
        """``(n, R)`` enter and leave times of the chosen plans (``enter[rows, choice]`` without the full arrays)."""
        zi, zq = np.nonzero(self.zone)
        picked = self.choice[zi]
        out = []
        for windows in (self.zone_enter, self.zone_leave):
            full = np.repeat(self.base[np.arange(self.choice.size), self.choice][:, None], self.zone.shape[1], axis=1)
            full[zi, zq] = windows[np.arange(zi.size), picked]
            out.append(full)
        return out[0], out[1]

    def window(self, q: int | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(n,)`` chosen enter and leave times in the zone with route(s) ``q`` (``nan`` if none)."""
        rows = np.arange(self.choice.shape[0])
        enter, leave = self.chosen()
        valid = self.zone[rows, q]
        return np.where(valid, enter[rows, q], np.nan), np.where(valid, leave[rows, q], np.nan)


class AIMPlanner(Planner):
    """Reservations per conflict zone, FIFO by arrival, with approach speeds adapted to the slot.

    :param name: the name shown in reports
    :param params: free parameters
    :param idm: IDM constants of car following (its ``acc_max`` is replaced by ``params.accel``)
    """

    # A stopped vehicle this close to its line [m] is at its stop point (IDM settles within ~0.5 m).
    stop_reach = 1.0
    # ... and at rest below this speed [m/s].
    rest_speed = 0.5

    def __init__(self, name: str = "AIM", params: AIMParams | None = None, idm: IDMParams = DEFAULT_IDM) -> None:
        super().__init__(name)
        self.params = params if params is not None else AIMParams()
        self.idm = idm
        self._follow_idm: tuple[tuple, IDMParams | None] = ((None, None), None)  # IDM with acc_max = accel, cached
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        self._ids = np.zeros(0, np.int64)
        self._keys = np.zeros(0)
        self._committed_at = np.zeros(0)

    # ------------------------------------------------------------------ order
    def arrival_keys(self, scene: Scene, earliest: np.ndarray, committed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """FIFO keys and commitment times, remembered per vehicle id from step to step.

        :param scene: the vehicles now
        :param earliest: ``(n,)`` earliest arrival from now [s]
        :param committed: ``(n,)`` bool: the vehicle holds its reservation now
        :return: ``(n,)`` keys: the absolute earliest arrival at the line when first seen, never
            before the leader's; ``(n,)`` the time each vehicle first held its reservation
            (``inf`` while it does not): a vehicle that commits later never goes before one that
            committed earlier
        """
        ids = scene.vehicle_id
        keys = scene.time + np.asarray(earliest, float)
        since = np.full(len(ids), np.inf)
        if self._ids.size:
            pos = np.minimum(np.searchsorted(self._ids, ids), self._ids.size - 1)
            known = self._ids[pos] == ids
            keys = np.where(known, self._keys[pos], keys)
            since = np.where(known, self._committed_at[pos], since)
        keys = leader_chain_max(keys, scene.leader, 1e-3)
        since = np.where(committed & ~np.isfinite(since), scene.time, since)
        order = np.argsort(ids)
        self._ids, self._keys, self._committed_at = ids[order], keys[order], since[order]
        return keys, since

    def order_keys(self, scene: Scene, keys: np.ndarray) -> np.ndarray:
        """The keys that order this step's reservations (after the committed vehicles).

        :param scene: the vehicles now
        :param keys: ``(n,)`` remembered arrival keys (:meth:`arrival_keys`)
        :return: ``(n,)`` keys, lower first; here the arrival keys themselves (a subclass may shift them)
        """
        return keys

    # ------------------------------------------------------------------ planning
    def candidates(self, scene: Scene) -> dict[str, np.ndarray]:
        """Candidate plans of every vehicle: time and speed at the line (see the module docstring).

        Compiled (:func:`envs.planners._aim_kernel.candidates`).

        :param scene: the vehicles now
        :return: ``arrival``, ``line_speed``, ``feasible`` ``(n, C)``; ``kind``, ``cruise`` ``(C,)``;
            ``start`` ``(n, C)`` (stops: start from rest); ``rest``, ``earliest``, ``can_stop``,
            ``committed`` ``(n,)``
        """
        p = self.params
        v = scene.speed
        u, waits = self._grids(np.maximum(scene.speed_limit, v).max(initial=0.0))
        arrival, speed_at_line, feasible, start, rest, earliest, can_stop, committed = _aim_kernel.candidates(
            v, scene.dist_to_entry, scene.dist_to_exit, scene.speed_limit, line_speed(scene, p.governor_deceleration),
            u, waits, p.accel, p.decel, p.governor_deceleration, p.commit_decel, self.stop_reach, self.rest_speed,
        )  # fmt: skip
        kind, cruise = self._kinds(u, waits)
        return {
            "arrival": arrival,
            "line_speed": speed_at_line,
            "feasible": feasible,
            "kind": kind,
            "cruise": cruise,
            "start": start,
            "rest": rest,
            "earliest": earliest,
            "can_stop": can_stop,
            "committed": committed,
        }

    def _grids(self, top_speed: float) -> tuple[np.ndarray, np.ndarray]:
        """Cruise speeds of the slowed approaches up to ``top_speed`` and start times of the stops."""
        p = self.params
        u = np.arange(1, int(np.floor(top_speed / p.speed_step)) + 1) * p.speed_step
        waits = np.arange(int(np.floor(p.wait_horizon / p.wait_step)) + 1) * p.wait_step
        return u, waits

    @staticmethod
    def _kinds(u: np.ndarray, waits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``kind`` and ``cruise`` of the candidates (see :meth:`candidates`)."""
        kind = np.concatenate([[0], np.ones(u.size, np.int64), np.full(waits.size, 2)])
        return kind, np.concatenate([[np.nan], u, np.full(waits.size, np.nan)])

    def reserve(self, scene: Scene) -> Reservations:
        """Candidate plans, the order, and the reservations of every vehicle (see the module docstring)."""
        p = self.params
        lay = scene.layout
        n, route, L = scene.num_vehicles, scene.route, scene.length
        approaching = scene.dist_to_exit > 0
        before = approaching & (scene.dist_to_entry > 0)
        inside = approaching & ~before
        cand = self.candidates(scene)
        arrival, speed_at_line, feasible = cand["arrival"], cand["line_speed"], cand["feasible"]
        kind, committed, can_stop = cand["kind"], cand["committed"], cand["can_stop"]
        a = p.accel
        v_in = inner_limit(lay)[route]

        # Zone windows of every candidate, measured from the line (from the front once inside), only
        # for the zones a vehicle still has to pass: rows (i, q) of zone, row-major, (k, C) each.
        ref = np.where(inside, scene.arc + L / 2, lay.entry_arc[route])
        z_start, z_end = lay.zone_start[route], lay.zone_end[route]  # (n, R)
        zone = approaching[:, None] & np.isfinite(z_start) & (z_end + L[:, None] - ref[:, None] > 0)
        zi, zq = np.nonzero(zone)
        d_in = np.maximum(z_start[zi, zq] - ref[zi], 0.0)
        d_out = z_end[zi, zq] + L[zi] - ref[zi]
        zone_enter, zone_leave, base, score = _aim_kernel.windows(
            zi, d_in, d_out, arrival, speed_at_line, v_in, *self.leader_terms(scene, ref), a, kind == 2, p.stop_penalty
        )
        human = scene.humans
        going = self._book_humans(scene, zi, zq, zone_enter, zone_leave) if human.any() else human

        # Order: going human drivers first (fixed reservations), then the committed, in the order they
        # committed, then FIFO by the remembered arrival keys.
        keys, since = self.arrival_keys(scene, cand["earliest"], committed)
        keys = self.order_keys(scene, keys)
        order = np.empty(n, np.int64)
        order[np.lexsort((scene.vehicle_id, keys, np.where(going, -np.inf, since)))] = np.arange(n)
        # Only the pairs that must not clash (conflicting routes, both still before their zones with
        # each other, j reserving before i; a human's own plan is moot, and one that the rules hold
        # books nothing): i, j, and the rows of i's zone with j and j's zone with i (compiled).
        pi, pj, row_i, row_j = _aim_kernel.pairs(route, zone, lay.conflicts, order, human, going)
        leader = scene.leader
        follows = (leader >= 0) & before & before[np.maximum(leader, 0)]  # both still before the line
        # Without a clash-free plan: wait longest if it can stop, else arrive as late as it can.
        latest_go = np.where(feasible & (kind != 2)[None, :], arrival, -np.inf).argmax(axis=1)
        fallback = np.where(can_stop, arrival.shape[1] - 1, latest_go)
        choice = _aim_kernel.settle(
            p.passes, pi, pj, row_i, row_j, zone_enter, zone_leave, p.buffer,
            arrival, feasible, score, fallback, follows, np.maximum(leader, 0), p.follow_headway,
        )  # fmt: skip
        return Reservations(
            choice=choice,
            kind=kind,
            cruise=cand["cruise"],
            arrival=arrival,
            line_speed=speed_at_line,
            base=base,
            zone_enter=zone_enter,
            zone_leave=zone_leave,
            zone=zone,
            start=cand["start"],
            rest=cand["rest"],
            committed=committed,
            order=order,
        )

    def _book_humans(
        self, scene: Scene, zi: np.ndarray, zq: np.ndarray, zone_enter: np.ndarray, zone_leave: np.ndarray
    ) -> np.ndarray:
        """Overwrite the zone windows of the going human drivers (in place) with their predicted
        windows (:func:`envs.planners.human.human_window`, the shield's rule), the same for every
        candidate: a human ignores its reservation, so it is fixed, and the others plan around it.

        :param scene: the vehicles now (with human drivers)
        :param zi: ``(k,)`` vehicle of each zone row
        :param zq: ``(k,)`` route of the zone's other side
        :param zone_enter: ``(k, C)`` zone windows' starts [s from now], modified
        :param zone_leave: ``(k, C)`` and ends, modified
        :return: ``(n,)`` bool: the going human drivers (the priority rules let them go now)
        """
        p = self.params
        going = human_commands(scene)[1]
        rows = np.flatnonzero(going[zi])
        if rows.size:
            h, q, r = zi[rows], zq[rows], scene.route[zi[rows]]
            front = scene.arc[h] + scene.length[h] / 2
            v = scene.speed[h]
            gap_in = scene.layout.zone_start[r, q] - front
            start, until = human_window(
                gap_in,
                scene.layout.zone_end[r, q] + scene.length[h] - front,
                v,
                approach_limit(scene, h, gap_in),
                p.human_margin,
                p.human_horizon,
            )
            zone_enter[rows] = start[:, None]
            zone_leave[rows] = until[:, None]
        return going

    def leader_terms(self, scene: Scene, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What bounds when a vehicle's front can be ``d`` metres past ``ref``: its leader's rear must
        first be the jam distance beyond that point, and the leader accelerates at most at ``accel``
        up to the road's limit (:func:`envs.planners._aim_kernel.windows`).

        :param scene: the vehicles now
        :param ref: ``(n,)`` arc the distances are measured from
        :return: ``(n,)`` metres the leader has to move besides ``d``, its speed, its speed limit
            and whether there is a leader
        """
        leader = np.maximum(scene.leader, 0)
        has = scene.leader >= 0
        front = scene.arc + scene.length / 2
        ahead = ref - front + self.idm.jam_distance - np.where(has, scene.gap, 0.0)
        v_lead = scene.speed[leader]
        return ahead, v_lead, np.maximum(scene.speed_limit[leader], v_lead), has

    # ------------------------------------------------------------------ control
    def act(self, scene: Scene) -> np.ndarray:
        if scene.num_vehicles == 0:
            return np.zeros(0)
        return self.control(scene, self.reserve(scene))

    def control(self, scene: Scene, plan: Reservations) -> np.ndarray:
        """Each vehicle's command to follow its reservation (step 4 of the module docstring).

        :param scene: the vehicles now
        :param plan: the reservations of this step (:meth:`reserve`)
        :return: ``(n,)`` accelerations within the scene's bounds
        """
        n = scene.num_vehicles
        p = self.params
        rows = np.arange(n)
        kind, u = plan.kind[plan.choice], plan.cruise[plan.choice]
        v, dist, dt = scene.speed, scene.dist_to_entry, scene.dt
        before = (scene.dist_to_exit > 0) & (dist > 0)
        # Slowed approach: towards u, and accelerate again in time to reach w at the line.
        w = plan.line_speed[rows, plan.choice]
        speed_up = (w > v) & (dist <= (w**2 - v**2) / (2.0 * p.accel) + v * dt)
        towards_u = np.clip((np.where(np.isnan(u), 0.0, u) - v) / dt, -p.decel, p.accel)
        slowed = np.where(speed_up, p.accel, towards_u)
        # Stop: at the line, until the start time has come (no wait left once at the stop point).
        at_line = (plan.rest <= 0.0) & (plan.start[rows, plan.choice] <= 1e-9)
        # IDM with this planner's constants, three uses in one call (elementwise, so the same values
        # as three calls): towards the stop point (stop_line_acceleration), behind the zone a
        # vehicle must not enter (zone_guard), plain car following (follow_leaders).
        leader = scene.leader
        leader_speed = np.where(leader >= 0, scene.speed[np.maximum(leader, 0)], 0.0)
        # zone_obstacle(scene, enter[:, route], leave[:, route].T) of the chosen plans (plan.chosen()), compiled
        obstacle = _aim_kernel.zone_obstacle(
            scene.route, scene.arc, scene.length, scene.dist_to_exit, scene.layout.zone_start, scene.layout.zone_end,
            plan.zone, plan.zone_enter, plan.zone_leave, plan.base, plan.choice, self.idm.jam_distance,
        )  # fmt: skip
        to_stop = np.maximum(dist, 0.0) + self.idm.jam_distance  # stop_line_acceleration(scene, 0.0, idm)
        to_stop_target = np.where(dist <= 0.5, 0.0, scene.speed_limit)  # ... with its settle = 0.5
        far = np.full(n, 1e3)
        stop_idm, guard, plain = idm_acceleration(
            np.concatenate([v, v, v]),
            np.concatenate([to_stop_target, far, scene.speed_limit]),
            np.concatenate([to_stop, obstacle, scene.gap]),
            np.concatenate([np.zeros(2 * n), leader_speed]),
            dt,
            self.idm,
        ).reshape(3, n)
        stop = np.where(at_line, p.accel, stop_idm)
        planned = np.where(~before | (kind == 0), p.accel, np.where(kind == 1, slowed, stop))
        # Car following: IDM's interaction term (the lane limits are the governor's job).
        if self._follow_idm[0] != (self.idm, p.accel):
            self._follow_idm = ((self.idm, p.accel), replace(self.idm, acc_max=p.accel))
        follow = idm_acceleration(v, far, scene.gap, leader_speed, dt, self._follow_idm[1])
        # Past the intersection: plain IDM.
        acc = np.where(scene.dist_to_exit > 0, np.minimum(np.minimum(planned, follow), guard), plain)
        return np.clip(acc, scene.a_min, scene.a_max)


def zone_guard(scene: Scene, enter: np.ndarray, until: np.ndarray, idm: IDMParams = DEFAULT_IDM) -> np.ndarray:
    """Safety net under the plans: do not drive into a conflict zone another vehicle's body still occupies.

    Vehicle ``i`` treats the start of its zone with ``j`` as a standing obstacle (IDM, stopping at
    the zone's start) while ``j``'s body is in ``j``'s zone with ``i`` and ``i``'s plan enters its own
    zone before ``j`` is expected to have left. Consistent plans never trigger it; it matters when a
    plan slips, e.g. a vehicle held up in a merge by a queue on its exit lane. All pairs at once.

    :param scene: the vehicles now (with its layout)
    :param enter: ``(n, n)`` time ``i`` plans to enter its zone with ``j`` [s from now]
    :param until: ``(n, n)`` time ``j`` is expected to have left its zone with ``i`` [s from now]
    :param idm: IDM constants
    :return: ``(n,)`` accelerations (IDM's ``acc_max`` where nothing is in the way)
    """
    obstacle = zone_obstacle(scene, enter, until, idm)
    far = np.full(scene.num_vehicles, 1e3)
    return idm_acceleration(scene.speed, far, obstacle, np.zeros_like(obstacle), scene.dt, idm)


def zone_obstacle(scene: Scene, enter: np.ndarray, until: np.ndarray, idm: IDMParams = DEFAULT_IDM) -> np.ndarray:
    """The standing obstacle of :func:`zone_guard`: ``(n,)`` IDM gap to it [m], ``inf`` where none.

    :param scene: the vehicles now (with its layout)
    :param enter: ``(n, n)`` time ``i`` plans to enter its zone with ``j`` [s from now]
    :param until: ``(n, n)`` time ``j`` is expected to have left its zone with ``i`` [s from now]
    :param idm: IDM constants
    """
    lay, route = scene.layout, scene.route
    front, rear = scene.arc + scene.length / 2, scene.arc - scene.length / 2
    start, end = lay.zone_start[route[:, None], route[None, :]], lay.zone_end[route[:, None], route[None, :]]
    occupies = (front[:, None] >= start) & (rear[:, None] <= end)  # (j, i): j's body in its zone with i
    to_zone = start - front[:, None]  # (i, j): metres from i's front to its zone with j
    blocking = occupies.T & (to_zone > 0) & ~(enter >= until) & (scene.dist_to_exit > 0)[:, None]
    gap = np.where(blocking, to_zone, np.inf).min(axis=1)
    return np.where(np.isfinite(gap), gap + idm.jam_distance, np.inf)  # IDM keeps s0: stop at the start
