"""AIM's rules in NumPy: the oracle that the compiled kernels (``envs/planners/_aim_kernel.py``, the
only implementation the planner runs) match bit for bit.

:func:`candidates_numpy`, :func:`windows_numpy`, :func:`settle_numpy`, :func:`pairs_numpy` and
:func:`zone_obstacle_numpy` take the arguments and return the results of ``_aim_kernel.candidates``,
``windows``, ``settle``, ``pairs`` and ``zone_obstacle``. :data:`REFERENCE` is
a stand-in for the kernel module: with ``envs.planners.aim._aim_kernel`` replaced by it (see
:func:`reference_kernels`), :class:`~envs.planners.aim.AIMPlanner` runs these NumPy rules end to end.
A change to a rule is made in the kernel; these functions change with it only if the test that
compares them says that the rule, not a rounding, changed.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from envs.planners.aim import Reservations, zone_obstacle
from envs.planners.idm import DEFAULT_IDM, travel_time
from envs.planners.vehicle_model import earliest_arrival


def candidates_numpy(
    speed: np.ndarray,
    dist: np.ndarray,
    dist_to_exit: np.ndarray,
    speed_limit: np.ndarray,
    v_line: np.ndarray,
    u: np.ndarray,
    waits: np.ndarray,
    accel: float,
    decel: float,
    governor_deceleration: float,
    commit_decel: float,
    stop_reach: float,
    rest_speed: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``_aim_kernel.candidates`` in NumPy (same parameters): ``arrival``, ``line_speed``,
    ``feasible``, ``start`` ``(n, C)``; ``rest``, ``earliest``, ``can_stop``, ``committed`` ``(n,)``."""
    n, v = speed.size, speed
    approaching = dist_to_exit > 0
    before = approaching & (dist > 0)
    inside = approaching & ~before
    a, b, b_gov = accel, decel, governor_deceleration
    v_road = np.maximum(speed_limit, v)
    # The earliest arrival.
    t0, w0, _ = earliest_arrival(dist, v, v_line, v_road, a, b_gov)
    # Slowed approaches: v -> u, cruise at u, u -> w at the line.
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
    can_stop = before & (v**2 <= 2.0 * commit_decel * np.maximum(dist, 0.0))
    stop_dec = np.maximum(b, v**2 / (2.0 * np.maximum(dist, 1e-3)))
    at_stop = before & (dist <= stop_reach) & (v <= rest_speed)
    t_rest = np.where(at_stop, 0.0, earliest_arrival(dist, v, np.zeros(n), v_road, a, stop_dec)[0])
    start = np.maximum(t_rest[:, None], waits[None, :])  # from rest at the stop point, from now
    creep = np.where(at_stop, dist, 0.0)[:, None]  # what is left to the line from there
    t_stop = start + np.sqrt(2.0 * creep / a)
    w_stop = np.broadcast_to(np.sqrt(2.0 * a * creep), start.shape)

    arrival = np.concatenate([t0[:, None], t_cruise, t_stop], axis=1)  # (n, C)
    speed_at_line = np.concatenate([w0[:, None], w, w_stop], axis=1)
    return (
        np.where(inside[:, None], 0.0, arrival),
        np.where(inside[:, None], v[:, None], speed_at_line),
        np.concatenate([np.ones((n, 1), bool), cruise_ok, np.broadcast_to(can_stop[:, None], t_stop.shape)], axis=1),
        np.concatenate([np.full((n, 1 + u.size), np.nan), start], axis=1),
        t_rest,
        t0,
        can_stop,
        inside | (before & ~can_stop),
    )


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
    inner limit), never before the leader has moved on (:meth:`~envs.planners.aim.AIMPlanner.leader_terms`).

    :param zone_row: ``(k,)`` vehicle of each zone it still has to pass (sorted)
    :param d_in: ``(k,)`` metres from the line (from the front once inside) to the zone's start
    :param d_out: ``(k,)`` and until the rear has left it
    :param arrival: ``(n, C)`` arrival at the line [s from now]
    :param line_speed: ``(n, C)`` speed at the line [m/s]
    :param v_in: ``(n,)`` lowest limit inside the intersection [m/s]
    :param ahead: ``(n,)`` from :meth:`~envs.planners.aim.AIMPlanner.leader_terms`
    :param v_lead: ``(n,)`` from :meth:`~envs.planners.aim.AIMPlanner.leader_terms`
    :param limit: ``(n,)`` from :meth:`~envs.planners.aim.AIMPlanner.leader_terms`
    :param has: ``(n,)`` from :meth:`~envs.planners.aim.AIMPlanner.leader_terms`
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


def pairs_numpy(
    route: np.ndarray, zone: np.ndarray, conflicts: np.ndarray, order: np.ndarray, human: np.ndarray, going: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pairs that must not clash and their zone rows (the reference of :func:`envs.planners._aim_kernel.pairs`,
    same parameters)."""
    pair = conflicts[route[:, None], route[None, :]] & zone[:, route] & zone[:, route].T
    pair &= order[None, :] < order[:, None]  # (i, j): j reserves before i
    if human.any():  # a human's own plan is moot; one that the rules hold books nothing (it yields)
        pair &= ~human[:, None] & ~(human & ~going)[None, :]
    np.fill_diagonal(pair, False)
    pi, pj = np.nonzero(pair)
    zi, zq = np.nonzero(zone)
    at = np.full(zone.shape, -1, np.int64)  # row of (i, q) in the zone windows
    at[zi, zq] = np.arange(zi.size)
    return pi, pj, at[pi, route[pj]], at[pj, route[pi]]


def zone_obstacle_numpy(
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
    """:func:`envs.planners.aim.zone_obstacle` of :meth:`envs.planners.aim.Reservations.chosen` (the reference of
    :func:`envs.planners._aim_kernel.zone_obstacle`, same parameters): the NumPy code itself, fed the arrays."""
    plan = SimpleNamespace(zone=zone, zone_enter=zone_enter, zone_leave=zone_leave, base=base, choice=choice)
    enter, leave = Reservations.chosen(plan)
    layout = SimpleNamespace(zone_start=zone_start, zone_end=zone_end)
    scene = SimpleNamespace(layout=layout, route=route, arc=arc, length=length, dist_to_exit=dist_to_exit)
    idm = replace(DEFAULT_IDM, jam_distance=jam_distance)
    return zone_obstacle(scene, enter[:, route], leave[:, route].T, idm)


#: Stand-in for ``envs.planners._aim_kernel``: the NumPy rules under the kernels' names.
REFERENCE = SimpleNamespace(
    candidates=candidates_numpy,
    windows=windows_numpy,
    settle=settle_numpy,
    pairs=pairs_numpy,
    zone_obstacle=zone_obstacle_numpy,
)


@contextlib.contextmanager
def reference_kernels() -> Iterator[None]:
    """Within the block, every :class:`~envs.planners.aim.AIMPlanner` runs the NumPy rules."""
    from envs.planners import aim

    kernels, aim._aim_kernel = aim._aim_kernel, REFERENCE
    try:
        yield
    finally:
        aim._aim_kernel = kernels
