"""Reservation per conflict zone in the spirit of Dresner & Stone's AIM (autonomous intersection management).

Every route pair that crosses or merges has a conflict zone on each of the two routes
(:attr:`envs.layouts.Layout.zone_start`, :attr:`~envs.layouts.Layout.zone_end`). A vehicle's body
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

Steps 1 and 3 run compiled (:mod:`envs.planners._aim_kernel`, numba): bitwise what
:meth:`AIMPlanner.candidates_numpy`, :func:`windows_numpy` and :func:`settle_numpy` compute (the
NumPy reference, used with ``compiled = False``; ``tests/test_planner_regression.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from envs.planners import _aim_kernel
from envs.planners.base import Planner
from envs.planners.idm import (
    DEFAULT_IDM,
    IDMParams,
    idm_acceleration,
    leader_chain_max,
    travel_time,
)
from envs.planners.vehicle_model import earliest_arrival, inner_limit, line_speed
from envs.scene import Scene


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

    # Candidates, zone windows and reservation passes compiled (numba, :mod:`envs.planners._aim_kernel`,
    # bitwise the NumPy code); False: the NumPy reference (``candidates_numpy``, ``windows_numpy``, ``settle_numpy``).
    compiled = True
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

    # ------------------------------------------------------------------ planning
    def candidates(self, scene: Scene) -> dict[str, np.ndarray]:
        """Candidate plans of every vehicle: time and speed at the line (see the module docstring).

        Compiled (:func:`envs.planners._aim_kernel.candidates`), bitwise :meth:`candidates_numpy`.

        :param scene: the vehicles now
        :return: ``arrival``, ``line_speed``, ``feasible`` ``(n, C)``; ``kind``, ``cruise`` ``(C,)``;
            ``start`` ``(n, C)`` (stops: start from rest); ``rest``, ``earliest``, ``can_stop``,
            ``committed`` ``(n,)``
        """
        if not self.compiled:
            return self.candidates_numpy(scene)
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

    def candidates_numpy(self, scene: Scene) -> dict[str, np.ndarray]:
        """:meth:`candidates` in NumPy (the reference of the compiled one)."""
        p = self.params
        n, v, dist = scene.num_vehicles, scene.speed, scene.dist_to_entry
        approaching = scene.dist_to_exit > 0
        before = approaching & (dist > 0)
        inside = approaching & ~before
        a, b, b_gov = p.accel, p.decel, p.governor_deceleration
        v_line = line_speed(scene, b_gov)
        v_road = np.maximum(scene.speed_limit, v)
        # The earliest arrival.
        t0, w0, _ = earliest_arrival(dist, v, v_line, v_road, a, b_gov)
        # Slowed approaches: v -> u, cruise at u, u -> w at the line.
        u, waits = self._grids(v_road.max(initial=0.0))
        U, V, D, WL = u[None, :], v[:, None], dist[:, None], v_line[:, None]
        rate1 = np.where(U > V, a, b)
        d1 = np.abs(V**2 - U**2) / (2.0 * rate1)
        rest = D - d1
        w = np.where(U <= WL, np.minimum(WL, np.sqrt(U**2 + 2.0 * a * np.maximum(rest, 0.0))), WL)
        rate3 = np.where(w >= U, a, b_gov)
        d3 = np.abs(w**2 - U**2) / (2.0 * rate3)
        d2 = rest - d3
        cruise_ok = before[:, None] & (rest >= 0) & (d2 >= -1e-6) & (U <= v_road[:, None] + 1e-9)
        t_cruise = np.abs(V - U) / rate1 + np.maximum(d2, 0.0) / U + np.abs(w - U) / rate3
        # Stops: come to rest at the line, start from rest later.
        can_stop = before & (v**2 <= 2.0 * p.commit_decel * np.maximum(dist, 0.0))
        stop_dec = np.maximum(b, v**2 / (2.0 * np.maximum(dist, 1e-3)))
        at_stop = before & (dist <= self.stop_reach) & (v <= self.rest_speed)
        t_rest = np.where(at_stop, 0.0, earliest_arrival(dist, v, np.zeros(n), v_road, a, stop_dec)[0])
        start = np.maximum(t_rest[:, None], waits[None, :])  # from rest at the stop point, from now
        creep = np.where(at_stop, dist, 0.0)[:, None]  # what is left to the line from there
        t_stop = start + np.sqrt(2.0 * creep / a)
        w_stop = np.broadcast_to(np.sqrt(2.0 * a * creep), start.shape)

        kind, cruise = self._kinds(u, waits)
        arrival = np.concatenate([t0[:, None], t_cruise, t_stop], axis=1)  # (n, C)
        speed_at_line = np.concatenate([w0[:, None], w, w_stop], axis=1)
        return {
            "arrival": np.where(inside[:, None], 0.0, arrival),
            "line_speed": np.where(inside[:, None], v[:, None], speed_at_line),
            "feasible": np.concatenate(
                [np.ones((n, 1), bool), cruise_ok, np.broadcast_to(can_stop[:, None], t_stop.shape)], axis=1
            ),
            "kind": kind,
            "cruise": cruise,
            "start": np.concatenate([np.full((n, 1 + u.size), np.nan), start], axis=1),
            "rest": t_rest,
            "earliest": t0,
            "can_stop": can_stop,
            "committed": inside | (before & ~can_stop),
        }

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
        k = zi.size
        d_in = np.maximum(z_start[zi, zq] - ref[zi], 0.0)
        d_out = z_end[zi, zq] + L[zi] - ref[zi]
        windows = _aim_kernel.windows if self.compiled else windows_numpy
        zone_enter, zone_leave, base, score = windows(
            zi, d_in, d_out, arrival, speed_at_line, v_in, *self.leader_terms(scene, ref), a, kind == 2, p.stop_penalty
        )

        # Order: committed first, in the order they committed, then FIFO by the remembered arrival keys.
        keys, since = self.arrival_keys(scene, cand["earliest"], committed)
        order = np.empty(n, np.int64)
        order[np.lexsort((scene.vehicle_id, keys, since))] = np.arange(n)
        pair = lay.conflicts[route[:, None], route[None, :]] & zone[:, route] & zone[:, route].T
        pair &= order[None, :] < order[:, None]  # (i, j): j reserves before i
        np.fill_diagonal(pair, False)
        # Only the pairs that must not clash: i, j, and the rows of i's zone with j and j's zone with i.
        pi, pj = np.nonzero(pair)
        at = np.full(zone.shape, -1, np.int64)  # row of (i, q) in the zone windows
        at[zi, zq] = np.arange(k)
        leader = scene.leader
        follows = (leader >= 0) & before & before[np.maximum(leader, 0)]  # both still before the line
        # Without a clash-free plan: wait longest if it can stop, else arrive as late as it can.
        latest_go = np.where(feasible & (kind != 2)[None, :], arrival, -np.inf).argmax(axis=1)
        fallback = np.where(can_stop, arrival.shape[1] - 1, latest_go)
        settle = _aim_kernel.settle if self.compiled else settle_numpy
        choice = settle(
            p.passes, pi, pj, at[pi, route[pj]], at[pj, route[pi]], zone_enter, zone_leave, p.buffer,
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

    def leader_terms(self, scene: Scene, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What bounds when a vehicle's front can be ``d`` metres past ``ref``: its leader's rear must
        first be the jam distance beyond that point, and the leader accelerates at most at ``accel``
        up to the road's limit (:func:`windows_numpy`).

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
        n = scene.num_vehicles
        if n == 0:
            return np.zeros(0)
        p = self.params
        plan = self.reserve(scene)
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
        chosen_enter, chosen_leave = plan.chosen()  # (n, R)
        obstacle = zone_obstacle(scene, chosen_enter[:, scene.route], chosen_leave[:, scene.route].T, self.idm)
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


def windows_numpy(
    zone_row: np.ndarray,
    d_in: np.ndarray,
    d_out: np.ndarray,
    arrival: np.ndarray,
    line_speed: np.ndarray,
    v_in: np.ndarray,
    ahead: np.ndarray,
    v_lead: np.ndarray,
    limit: np.ndarray,
    has: np.ndarray,
    accel: float,
    stop: np.ndarray,
    stop_penalty: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Zone windows of every candidate and the candidates' scores (the reference of
    :func:`envs.planners._aim_kernel.windows`).

    A window is the arrival at the line plus the crossing from the line (``accel`` up to the
    inner limit), never before the leader has moved on (:meth:`AIMPlanner.leader_terms`).

    :param zone_row: ``(k,)`` vehicle of each zone it still has to pass (sorted)
    :param d_in: ``(k,)`` metres from the line (from the front once inside) to the zone's start
    :param d_out: ``(k,)`` and until the rear has left it
    :param arrival: ``(n, C)`` arrival at the line [s from now]
    :param line_speed: ``(n, C)`` speed at the line [m/s]
    :param v_in: ``(n,)`` lowest limit inside the intersection [m/s]
    :param ahead: ``(n,)`` from :meth:`AIMPlanner.leader_terms`
    :param v_lead: ``(n,)`` from :meth:`AIMPlanner.leader_terms`
    :param limit: ``(n,)`` from :meth:`AIMPlanner.leader_terms`
    :param has: ``(n,)`` from :meth:`AIMPlanner.leader_terms`
    :param accel: acceleration of the crossing and of the leader [m/s^2]
    :param stop: ``(C,)`` bool: the candidate stops at the line
    :param stop_penalty: seconds added to a stop's score
    :return: ``(k, C)`` enter and leave times [s from now]; ``(n, C)`` the window in a zone a vehicle
        no longer has to pass (its arrival, bounded likewise); ``(n, C)`` scores: the time the last
        zone is left (the arrival without zones), plus the penalty of a stop
    """
    n, k = arrival.shape[0], zone_row.size
    # Entering and leaving in one pass: (2k, C), the zones' starts then their ends; then, to
    # bound them by the leader, the same distances and 0 for each vehicle (its other zones).
    rows2 = np.concatenate([zone_row, zone_row])
    d_both = np.concatenate([d_in, d_out])
    both = arrival[rows2] + travel_time(d_both[:, None], line_speed[rows2], v_in[rows2, None], accel)
    rows, d = np.concatenate([rows2, np.arange(n)]), np.concatenate([d_both, np.zeros(n)])
    move = np.maximum(d + ahead[rows], 0.0)
    bound = np.where(has[rows], travel_time(move, v_lead[rows], limit[rows], accel), 0.0)
    both = np.maximum(both, bound[: 2 * k, None])
    base = np.maximum(arrival, bound[2 * k :, None])
    enter, leave = both[:k], both[k:]
    starts = np.flatnonzero(np.r_[True, zone_row[1:] != zone_row[:-1]]) if k else np.zeros(0, np.int64)
    last = np.full(arrival.shape, -np.inf)
    if k:
        last[zone_row[starts]] = np.maximum.reduceat(leave, starts, axis=0)
    score = np.where(np.isfinite(last), last, arrival) + np.where(stop, stop_penalty, 0.0)[None, :]
    return enter, leave, base, score


def settle_numpy(
    passes: int,
    pair_i: np.ndarray,
    pair_j: np.ndarray,
    row_i: np.ndarray,
    row_j: np.ndarray,
    zone_enter: np.ndarray,
    zone_leave: np.ndarray,
    buffer: float,
    arrival: np.ndarray,
    feasible: np.ndarray,
    score: np.ndarray,
    fallback: np.ndarray,
    follows: np.ndarray,
    lead_row: np.ndarray,
    follow_headway: float,
) -> np.ndarray:
    """The reservation passes: every vehicle takes its best candidate that clashes with no choice of
    the previous pass, until no choice changes (the reference of :func:`envs.planners._aim_kernel.settle`).

    :param passes: most passes
    :param pair_i: ``(P,)`` vehicle ``i`` of each pair that must not clash (sorted)
    :param pair_j: ``(P,)`` the vehicle ``j`` that reserves before it
    :param row_i: ``(P,)`` row of ``i``'s zone with ``j`` in ``zone_enter``
    :param row_j: ``(P,)`` row of ``j``'s zone with ``i``
    :param zone_enter: ``(k, C)`` zone windows' starts [s from now]
    :param zone_leave: ``(k, C)`` and ends
    :param buffer: seconds kept between two windows
    :param arrival: ``(n, C)`` arrival at the line [s from now]
    :param feasible: ``(n, C)`` bool
    :param score: ``(n, C)`` lower is better
    :param fallback: ``(n,)`` candidate taken where none is clash-free
    :param follows: ``(n,)`` bool: arrives ``follow_headway`` after its leader
    :param lead_row: ``(n,)`` the leader's row (0 where none)
    :param follow_headway: seconds
    :return: ``(n,)`` chosen candidates
    """
    n = arrival.shape[0]
    enter_ij, leave_ij = zone_enter[row_i], zone_leave[row_i] + buffer  # (P, C), rows sorted by i
    clashing, starts = np.unique(pair_i, return_index=True)
    flat_enter, flat_leave = zone_enter.ravel(), zone_leave.ravel() + buffer
    row_j_flat = row_j * arrival.shape[1]
    rows = np.arange(n)
    choice = np.zeros(n, np.int64)
    clash = np.zeros(arrival.shape, bool)
    for _ in range(passes):
        if pair_i.size:  # j's chosen window in its zone with i against each of i's candidates
            chosen_j = row_j_flat + choice[pair_j]
            enter_j, leave_j = flat_enter[chosen_j], flat_leave[chosen_j]
            overlap = (enter_ij < leave_j[:, None]) & (enter_j[:, None] < leave_ij)
            clash[clashing] = np.logical_or.reduceat(overlap, starts, axis=0)
        lead_arrival = arrival[rows, choice][lead_row] + follow_headway
        ok = feasible & ~clash & (~follows[:, None] | (arrival >= lead_arrival[:, None]))
        best = np.where(ok, score, np.inf).argmin(axis=1)
        new = np.where(ok.any(axis=1), best, fallback)
        if np.array_equal(new, choice):
            break
        choice = new
    return choice


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
