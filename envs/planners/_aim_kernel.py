"""AIM's candidate plans, zone windows and reservation passes, compiled with numba
(:class:`envs.planners.aim.AIMPlanner`).

Why compiled: in NumPy, AIM's step made some 400 calls on arrays of 12 vehicles x 52 candidates
(x 3-4 zones each): the candidates about 150 (every phase of every plan kind, two earliest
arrivals), the zone windows about 40, and the reservation passes, a fixed-point iteration of 5-6
passes per policy step on average, about 15 per pass. On the loaded 2-core development machine a
NumPy call costs 1.4-2.4 us whatever the size of these arrays, so the calls alone made about as
much as the simulation's whole step (0.6-0.8 ms); removing NumPy calls (windows only for the zones
a vehicle still has to pass, the three IDM uses in one call) took AIM from 1.42 to 1.24 ms per
step only, 2.2x to 1.7x the simulation's (docs/speed.md, "Planners").

Every function here is the scalar form of a NumPy one, with the same floating-point operations in
the same order (no ``fastmath``, so no reassociation or fused multiply-add; ``np.maximum`` and
``np.minimum`` as :func:`_max` and :func:`_min`, which let a nan through), so that the results are
bitwise the NumPy ones. These kernels are the planner's only implementation; the NumPy form lives
in ``tests/aim_reference.py`` as the oracle (``tests/test_planner_regression.py`` checks them on
recorded scenes, and :func:`settle` on random inputs):

- :func:`candidates`: ``candidates_numpy`` (with :func:`envs.planners.vehicle_model.earliest_arrival`),
- :func:`windows`: ``windows_numpy`` (with :func:`envs.planners.idm.travel_time`),
- :func:`settle`: ``settle_numpy``,
- :func:`pairs`: ``pairs_numpy``; :func:`zone_obstacle`: ``zone_obstacle_numpy``.

``cache=True`` stores the machine code next to this file (or in numba's cache directory), so only
the first process compiles it.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def settle(
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
    """The chosen candidate of every vehicle: ``settle_numpy`` (tests/aim_reference.py), loop by loop.

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
    n, c_count = arrival.shape
    choice = np.zeros(n, np.int64)
    new = np.zeros(n, np.int64)
    clash = np.zeros((n, c_count), np.bool_)
    # Incremental passes, bitwise the full ones: a vehicle's clashes depend only on the choices of the
    # vehicles it pairs with, and its choice on its clashes and its leader's choice; so a pass recomputes
    # only the clash rows with a partner whose choice changed in the last pass, and the choices of those
    # rows and of the vehicles whose leader's choice changed (the others keep the last pass's answer).
    order = np.argsort(pair_i, kind="mergesort")  # the pairs of each i, contiguous
    first = np.zeros(n + 1, np.int64)
    for r in range(pair_i.size):
        first[pair_i[r] + 1] += 1
    for i in range(n):
        first[i + 1] += first[i]
    changed = np.ones(n, np.bool_)  # before the first pass: every choice is new
    dirty = np.zeros(n, np.bool_)
    for _ in range(passes):
        for i in range(n):
            dirty[i] = changed[lead_row[i]]
            for q in range(first[i], first[i + 1]):
                if changed[pair_j[order[q]]]:
                    dirty[i] = True
                    break
        for i in range(n):  # j's chosen window in its zone with i against each of i's candidates
            if not dirty[i]:
                continue
            clash[i, :] = False
            for q in range(first[i], first[i + 1]):
                r = order[q]
                j = pair_j[r]
                enter_j = zone_enter[row_j[r], choice[j]]
                leave_j = zone_leave[row_j[r], choice[j]] + buffer
                ri = row_i[r]
                for c in range(c_count):  # branch-free, so that it vectorizes
                    clash[i, c] |= (zone_enter[ri, c] < leave_j) & (enter_j < zone_leave[ri, c] + buffer)
        for i in range(n):
            if not dirty[i]:
                continue
            lead_arrival = arrival[lead_row[i], choice[lead_row[i]]] + follow_headway
            best, best_score, any_ok = 0, np.inf, False
            for c in range(c_count):
                ok = feasible[i, c] and not clash[i, c] and (not follows[i] or arrival[i, c] >= lead_arrival)
                value = score[i, c] if ok else np.inf
                any_ok |= ok
                if np.isnan(value):  # argmin's rule: the first nan
                    if not np.isnan(best_score):
                        best, best_score = c, value
                elif c == 0 or value < best_score:
                    best, best_score = c, value
            new[i] = best if any_ok else fallback[i]
        same = True
        for i in range(n):
            changed[i] = new[i] != choice[i]
            same &= not changed[i]
        if same:
            break
        choice[:] = new
    return choice


@numba.njit(cache=True)
def _max(x: float, y: float) -> float:
    """``np.maximum`` of two floats (a nan propagates)."""
    return x if (x >= y or x != x) else y


@numba.njit(cache=True)
def _min(x: float, y: float) -> float:
    """``np.minimum`` of two floats (a nan propagates)."""
    return x if (x <= y or x != x) else y


@numba.njit(cache=True)
def _earliest_arrival(
    distance: float, speed: float, line_speed: float, road_speed: float, accel: float, decel: float
) -> tuple[float, float]:
    """:func:`envs.planners.vehicle_model.earliest_arrival` for one vehicle: ``(time, speed at the line)``."""
    d = _max(distance, 0.0)
    v = _max(speed, 0.0)
    w = _min(line_speed, math.sqrt(v**2 + 2.0 * accel * d))
    w = _max(w, math.sqrt(_max(v**2 - 2.0 * decel * d, 0.0)))
    peak_sq = (2.0 * accel * decel * d + decel * v**2 + accel * w**2) / (accel + decel)
    peak = _max(_min(math.sqrt(peak_sq), _max(road_speed, v)), _max(v, w))
    d_acc = (peak**2 - v**2) / (2.0 * accel)
    d_dec = (peak**2 - w**2) / (2.0 * decel)
    cruise = _max(d - d_acc - d_dec, 0.0)
    time = (peak - v) / accel + (peak - w) / decel + cruise / _max(peak, 1e-6)
    return (time if d > 0 else 0.0), (w if d > 0 else v)


@numba.njit(cache=True)
def candidates(
    speed: np.ndarray,
    dist: np.ndarray,
    dist_to_exit: np.ndarray,
    speed_limit: np.ndarray,
    v_line: np.ndarray,
    cruise: np.ndarray,
    waits: np.ndarray,
    accel: float,
    decel: float,
    governor_deceleration: float,
    commit_decel: float,
    stop_reach: float,
    rest_speed: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``candidates_numpy`` (tests/aim_reference.py) vehicle by vehicle, candidate by candidate.

    :param speed: ``(n,)`` [m/s]
    :param dist: ``(n,)`` metres to the stop line
    :param dist_to_exit: ``(n,)`` metres from the rear to the intersection's exit
    :param speed_limit: ``(n,)`` lane limit [m/s]
    :param v_line: ``(n,)`` highest speed at the line [m/s]
    :param cruise: ``(U,)`` cruise speeds of the slowed approaches [m/s]
    :param waits: ``(W,)`` earliest starts of the stops [s from now]
    :param accel: ``AIMParams.accel``
    :param decel: ``AIMParams.decel``
    :param governor_deceleration: ``AIMParams.governor_deceleration``
    :param commit_decel: ``AIMParams.commit_decel``
    :param stop_reach: ``AIMPlanner.stop_reach``
    :param rest_speed: ``AIMPlanner.rest_speed``
    :return: ``arrival``, ``line_speed``, ``feasible``, ``start`` ``(n, C)`` (``C = 1 + U + W``);
        ``rest``, ``earliest``, ``can_stop``, ``committed`` ``(n,)``
    """
    n, n_u, n_w = speed.size, cruise.size, waits.size
    c_count = 1 + n_u + n_w
    arrival = np.empty((n, c_count))
    line = np.empty((n, c_count))
    feasible = np.empty((n, c_count), np.bool_)
    start = np.full((n, c_count), np.nan)
    rest_time = np.empty(n)
    earliest = np.empty(n)
    can_stop = np.empty(n, np.bool_)
    committed = np.empty(n, np.bool_)
    a, b, b_gov = accel, decel, governor_deceleration
    for i in range(n):
        v, d_i, wl = speed[i], dist[i], v_line[i]
        approaching = dist_to_exit[i] > 0
        before = approaching and d_i > 0
        inside = approaching and not before
        v_road = _max(speed_limit[i], v)
        # The earliest arrival.
        t0, w0 = _earliest_arrival(d_i, v, wl, v_road, a, b_gov)
        arrival[i, 0], line[i, 0], feasible[i, 0] = t0, w0, True
        earliest[i] = t0
        # Slowed approaches: v -> u, cruise at u, u -> w at the line.
        for m in range(n_u):
            u = cruise[m]
            rate1 = a if u > v else b
            d1 = abs(v**2 - u**2) / (2.0 * rate1)
            rest = d_i - d1
            w = _min(wl, math.sqrt(u**2 + 2.0 * a * _max(rest, 0.0))) if u <= wl else wl
            rate3 = a if w >= u else b_gov
            d3 = abs(w**2 - u**2) / (2.0 * rate3)
            d2 = rest - d3
            c = 1 + m
            feasible[i, c] = before and rest >= 0 and d2 >= -1e-6 and u <= v_road + 1e-9
            arrival[i, c] = abs(v - u) / rate1 + _max(d2, 0.0) / u + abs(w - u) / rate3
            line[i, c] = w
        # Stops: come to rest at the line, start from rest later.
        stop = before and v**2 <= 2.0 * commit_decel * _max(d_i, 0.0)
        stop_dec = _max(b, v**2 / (2.0 * _max(d_i, 1e-3)))
        at_stop = before and d_i <= stop_reach and v <= rest_speed
        t_rest = 0.0 if at_stop else _earliest_arrival(d_i, v, 0.0, v_road, a, stop_dec)[0]
        creep = d_i if at_stop else 0.0  # what is left to the line from the stop point
        creep_time, w_stop = math.sqrt(2.0 * creep / a), math.sqrt(2.0 * a * creep)
        for m in range(n_w):
            c = 1 + n_u + m
            start[i, c] = _max(t_rest, waits[m])  # from rest at the stop point, from now
            arrival[i, c] = start[i, c] + creep_time
            line[i, c] = w_stop
            feasible[i, c] = stop
        if inside:
            for c in range(c_count):
                arrival[i, c], line[i, c] = 0.0, v
        rest_time[i], can_stop[i] = t_rest, stop
        committed[i] = inside or (before and not stop)
    return arrival, line, feasible, start, rest_time, earliest, can_stop, committed


@numba.njit(cache=True)
def _travel_time(distance: float, speed: float, v_max: float, accel: float) -> float:
    """:func:`envs.planners.idm.travel_time` for one distance."""
    d = _max(distance, 0.0)
    v = _max(speed, 0.0)
    vmax = _max(v_max, _max(v, 0.1))
    d_acc = (vmax**2 - v**2) / (2.0 * accel)  # distance needed to reach v_max
    if d <= d_acc:
        return (math.sqrt(v**2 + 2.0 * accel * d) - v) / accel
    return (vmax - v) / accel + (d - d_acc) / vmax


@numba.njit(cache=True)
def _leader_bound(d: float, ahead: float, v_lead: float, limit: float, has: bool, accel: float) -> float:
    """``windows_numpy``'s bound by the leader for one distance."""
    return _travel_time(_max(d + ahead, 0.0), v_lead, limit, accel) if has else 0.0


@numba.njit(cache=True)
def windows(
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
    """``windows_numpy`` (tests/aim_reference.py) zone by zone, candidate by candidate (same parameters)."""
    n, c_count = arrival.shape
    k = zone_row.size
    enter = np.empty((k, c_count))
    leave = np.empty((k, c_count))
    base = np.empty((n, c_count))
    last = np.full((n, c_count), -np.inf)
    for i in range(n):
        bound = _leader_bound(0.0, ahead[i], v_lead[i], limit[i], has[i], accel)
        for c in range(c_count):
            base[i, c] = _max(arrival[i, c], bound)
    for r in range(k):
        i = zone_row[r]
        bound_in = _leader_bound(d_in[r], ahead[i], v_lead[i], limit[i], has[i], accel)
        bound_out = _leader_bound(d_out[r], ahead[i], v_lead[i], limit[i], has[i], accel)
        first = r == 0 or zone_row[r - 1] != i
        for c in range(c_count):
            enter[r, c] = _max(arrival[i, c] + _travel_time(d_in[r], line_speed[i, c], v_in[i], accel), bound_in)
            leave[r, c] = _max(arrival[i, c] + _travel_time(d_out[r], line_speed[i, c], v_in[i], accel), bound_out)
            last[i, c] = leave[r, c] if first else _max(last[i, c], leave[r, c])
    score = np.empty((n, c_count))
    for i in range(n):
        for c in range(c_count):
            value = last[i, c] if math.isfinite(last[i, c]) else arrival[i, c]
            score[i, c] = value + (stop_penalty if stop[c] else 0.0)
    return enter, leave, base, score


@numba.njit(cache=True)
def zone_obstacle(
    route: np.ndarray,
    arc: np.ndarray,
    length: np.ndarray,
    dist_to_exit: np.ndarray,
    zone_start: np.ndarray,
    zone_end: np.ndarray,
    zone: np.ndarray,
    zone_enter: np.ndarray,
    zone_leave: np.ndarray,
    base: np.ndarray,
    choice: np.ndarray,
    jam_distance: float,
) -> np.ndarray:
    """:func:`envs.planners.aim.zone_obstacle` of the chosen plans (``Reservations.chosen``), pair by pair,
    without its ``(n, n)`` arrays (some 20 NumPy calls; a tenth of AIM's step at 100 vehicles).

    :param route: ``(n,)`` route indices
    :param arc: ``(n,)`` centre arcs [m]
    :param length: ``(n,)`` lengths [m]
    :param dist_to_exit: ``(n,)`` metres from the rear to the intersection's exit
    :param zone_start: ``(R, R)`` the layout's zone starts
    :param zone_end: ``(R, R)`` and ends
    :param zone: ``(n, R)`` bool: the vehicle still has to pass its zone with route ``q``
    :param zone_enter: ``(k, C)`` zone windows' starts, one row per ``True`` of ``zone`` (row-major)
    :param zone_leave: ``(k, C)`` and ends
    :param base: ``(n, C)`` window where a vehicle has no zone left
    :param choice: ``(n,)`` chosen candidates
    :param jam_distance: IDM's jam distance [m]
    :return: ``(n,)`` IDM gap to the obstacle [m], ``inf`` where none
    """
    n, num_r = zone.shape
    enter = np.empty((n, num_r))  # Reservations.chosen()
    leave = np.empty((n, num_r))
    row = 0
    for i in range(n):
        c = choice[i]
        for q in range(num_r):
            if zone[i, q]:
                enter[i, q], leave[i, q] = zone_enter[row, c], zone_leave[row, c]
                row += 1
            else:
                enter[i, q], leave[i, q] = base[i, c], base[i, c]
    out = np.full(n, np.inf)
    for i in range(n):
        if not dist_to_exit[i] > 0:
            continue
        front_i = arc[i] + length[i] / 2
        gap = np.inf
        for j in range(n):
            ri, rj = route[i], route[j]
            # j's body in its zone with i, i's front before its zone with j, i's plan not after j's exit
            to_zone = zone_start[ri, rj] - front_i
            if not to_zone > 0 or enter[i, rj] >= leave[j, ri]:
                continue
            if arc[j] + length[j] / 2 >= zone_start[rj, ri] and arc[j] - length[j] / 2 <= zone_end[rj, ri]:
                gap = min(gap, to_zone)
        if math.isfinite(gap):
            out[i] = gap + jam_distance  # IDM keeps s0: stop at the start
    return out


@numba.njit(cache=True)
def pairs(
    route: np.ndarray, zone: np.ndarray, conflicts: np.ndarray, order: np.ndarray, human: np.ndarray, going: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pairs that must not clash (:meth:`envs.planners.aim.AIMPlanner.reserve`), row-major as
    ``np.nonzero`` of its former ``(n, n)`` mask, without the mask (some 15 NumPy calls).

    :param route: ``(n,)`` route indices
    :param zone: ``(n, R)`` bool: the vehicle still has to pass its zone with route ``q``
    :param conflicts: ``(R, R)`` the layout's conflicting routes
    :param order: ``(n,)`` rank in the order of reservation
    :param human: ``(n,)`` bool: human drivers (their own plans are moot)
    :param going: ``(n,)`` bool: the human drivers that the priority rules let go (the others book nothing)
    :return: ``pair_i``, ``pair_j`` (``j`` reserves before ``i``), and the rows of ``i``'s zone with ``j``
        and of ``j``'s zone with ``i`` in the zone windows
    """
    n, num_r = zone.shape
    at = np.full((n, num_r), -1, np.int64)  # row of (i, q) in the zone windows (row-major over zone)
    rows = 0
    for i in range(n):
        for q in range(num_r):
            if zone[i, q]:
                at[i, q] = rows
                rows += 1
    most = 0
    for i in range(n):
        if not human[i]:
            most += n
    pair_i, pair_j = np.empty(most, np.int64), np.empty(most, np.int64)
    row_i, row_j = np.empty(most, np.int64), np.empty(most, np.int64)
    k = 0
    for i in range(n):
        if human[i]:
            continue
        for j in range(n):
            if j == i or (human[j] and not going[j]) or not order[j] < order[i]:
                continue
            if conflicts[route[i], route[j]] and zone[i, route[j]] and zone[j, route[i]]:
                pair_i[k], pair_j[k], row_i[k], row_j[k] = i, j, at[i, route[j]], at[j, route[i]]
                k += 1
    return pair_i[:k].copy(), pair_j[:k].copy(), row_i[:k].copy(), row_j[:k].copy()
