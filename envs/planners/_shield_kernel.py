"""The shield's prediction and its check, compiled with numba (:class:`envs.planners.shield.Shield`).

Why compiled: a prediction runs up to 40 sequential policy periods (the fallback is a feedback law
of the predicted state), each one ``integrate`` call (three sub-steps, six or more speed-envelope
look-ups) and one fallback evaluation, about 100 NumPy calls on arrays of 10-30 vehicles. On the
2-core development machine one such call costs 0.4-1.7 us whatever the array size, and a predicted
period about 250 us in all; for the shield to cost no more than the simulation's step (0.6-0.8 ms
per policy step, with 13-60 predicted periods per step), a period may cost about 15 us. That is the
per-call overhead of some 20 NumPy calls, less than ``integrate`` alone makes, so no vectorization
gets there (docs/speed.md, "Planners").

These kernels are the only implementation of the shield's prediction, fallback and check.
``tests/shield_reference.py`` holds the same rules in NumPy, with :func:`envs.simulation.engine.integrate`
itself: every function here performs the same floating-point operations in the same order as its
NumPy form (no ``fastmath``, so no reassociation or fused multiply-add), so that
``tests/test_shield.py`` can require the results to be bitwise equal:

- :func:`_envelope`: :meth:`envs.simulation.layouts.Layout.envelope_at` for one vehicle, from the tables of
  :func:`envs.planners.shield.envelope_table`,
- :func:`_integrate`: :func:`envs.simulation.engine.integrate` for one policy period (and :func:`integrate`,
  the simulation's step compiled for ``lookahead``'s rollouts),
- :func:`envs.simulation.commitment.is_committed` (the rule that the observation reads too), :func:`_fallback`:
  the reference's ``committed`` and ``fallback_given``
  (with ``yielding``, ``leaders_now`` and ``safe_gap_after``),
- :func:`predict`: the reference's ``predict_numpy``; :func:`fallback`: ``fallback_numpy``,
- :func:`conflicts`: ``conflicts_numpy``, the check of a prediction, and :func:`blame`: ``blame_numpy``, who
  is overridden for its conflicts.
- :func:`pairs`: ``plan_pairs_numpy``, the pairs that ``Shield._plan`` checks.

The first call compiles the kernels (about 6 s on the loaded 2-core development machine);
``cache=True`` stores the machine code next to this file (``__pycache__``, or numba's cache
directory where that is not writable), so that later processes only load it (0.7-0.9 s there, plus
0.2 s to import numba), once per process.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from envs.simulation.commitment import can_stop as _can_stop
from envs.simulation.commitment import is_committed as _committed


class PlanArrays(NamedTuple):
    """The arrays of a :class:`envs.planners.shield._Plan` that the kernels read (see there), contiguous."""

    route: np.ndarray
    hull_start: np.ndarray
    hull_end: np.ndarray
    follower: np.ndarray  # (k,) follow pairs' follower rows
    ahead: np.ndarray  # (k,) and the rows of the vehicles ahead
    follow_gap: np.ndarray
    follower_arc: np.ndarray  # (k,) arcs now
    ahead_arc: np.ndarray
    follow_floor: np.ndarray
    follow_until: np.ndarray  # (k,) the arc of the vehicle ahead at which the pair ends (it has turned off); inf
    follow_keep: np.ndarray  # (k,) room the fallback keeps over the gap margin [m] (0; under declared bounds, > 0)
    merge_keep: np.ndarray  # (g,) the same for the merging pairs
    cross: np.ndarray
    cross_lo: np.ndarray
    cross_hi: np.ndarray
    cross_already: np.ndarray
    cross_back: np.ndarray
    cross_stop: np.ndarray
    vehicle_id: np.ndarray
    merge: np.ndarray
    merge_lo: np.ndarray
    merge_exit: np.ndarray
    merge_sep: np.ndarray
    merge_yields: np.ndarray  # (n,) bool: keeps its gap to a merging vehicle ahead (a human driver does not)


class EnvelopeTable(NamedTuple):
    """The governor's speed envelope in flat tables (:func:`envs.planners.shield.envelope_table`)."""

    sq: np.ndarray  # flat (R * S,) squared envelope
    dsq: np.ndarray  # flat differences of the squared envelope to the next sample (0 at the last)
    limit: np.ndarray  # flat speed limits
    columns: int  # samples per route S
    last: int  # S - 1
    ds: float  # sample spacing [m]


@numba.njit(cache=True)
def _envelope(table: EnvelopeTable, route: int, arc: float) -> float:
    """The governor's speed envelope at one point: :meth:`envs.simulation.layouts.Layout.envelope_at`'s arithmetic.

    :param table: the envelope's tables
    :param route: route index
    :param arc: centre arc [m]
    """
    u = min(max(arc / table.ds, 0.0), float(table.last))
    i0 = min(int(u), table.last - 1)
    f = u - i0
    flat = route * table.columns + i0
    envelope = math.sqrt(table.sq[flat] + table.dsq[flat] * f)
    if u >= table.last:
        flat += 1
    return min(envelope, table.limit[flat])


@numba.njit(cache=True)
def _integrate(
    table: EnvelopeTable,
    route: np.ndarray,
    acc: np.ndarray,
    arcs: np.ndarray,
    speeds: np.ndarray,
    row: int,
    substeps: int,
    h: float,
    max_speed: float,
    caps: np.ndarray,
    governed: np.ndarray,
) -> None:
    """One policy period of :func:`envs.simulation.engine.integrate`, written into ``arcs`` and ``speeds``.

    Vehicles are independent in the model. A vehicle's sub-steps form one chain of dependent
    divisions and square roots (the envelope look-ups), so the loop runs sub-step by sub-step over
    all vehicles, not vehicle by vehicle: the processor then overlaps the chains of several vehicles.
    Each vehicle sees the same operations in the same order either way.

    :param table: the governor's envelope
    :param route: ``(n,)`` route indices
    :param acc: ``(n,)`` accelerations held over the period [m/s^2]
    :param arcs: ``(T + 1, n)`` arcs; row ``row`` is the state now, rows ``row + 1 ..
        row + substeps`` are written
    :param speeds: ``(T + 1, n)`` speeds, as ``arcs``
    :param row: the row of the state now
    :param substeps: sub-steps per period
    :param h: sub-step length [s]
    :param max_speed: speed cap [m/s]
    :param caps: ``(n,)`` scratch: each vehicle's envelope at its last arc
    :param governed: ``(n,)`` bool, set where the governor lowered the vehicle's speed in a sub-step
    """
    n = route.shape[0]
    for i in range(n):
        if not (speeds[row, i] == 0.0 and acc[i] < 0.0):
            caps[i] = _envelope(table, route[i], arcs[row, i])
    for k in range(substeps):
        src, dst = row + k, row + k + 1
        for i in range(n):
            if speeds[row, i] == 0.0 and acc[i] < 0.0:
                # Standing and braking: every sub-step gives v = 0 and x = x0 + 0.0 (the envelope,
                # never below 0, cannot cap a speed of 0), so the look-ups are skipped, bitwise alike.
                speeds[dst, i], arcs[dst, i] = 0.0, arcs[row, i] + 0.0
                continue
            v0, x0 = speeds[src, i], arcs[src, i]
            v = min(max(v0 + acc[i] * h, 0.0), max_speed)
            x = x0 + 0.5 * (v0 + v) * h
            cap_x = _envelope(table, route[i], x)
            cap = min(caps[i], cap_x)
            if v > cap:  # the governor: the sub-step ends at the envelope, looked up again there
                governed[i] = True
                v = cap
                x = x0 + 0.5 * (v0 + v) * h
                cap_x = _envelope(table, route[i], x)
            speeds[dst, i], arcs[dst, i] = v, x
            caps[i] = cap_x


@numba.njit(cache=True)
def integrate(
    table: EnvelopeTable,
    route: np.ndarray,
    arc: np.ndarray,
    speed: np.ndarray,
    acc: np.ndarray,
    substeps: int,
    h: float,
    max_speed: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`envs.simulation.engine.integrate` compiled, bit for bit (its outputs): a simulation that steps
    often on few vehicles (``lookahead``'s rollouts) spends most of a step in its NumPy calls.

    :param table: the governor's envelope (:func:`envs.planners.shield.envelope_table`)
    :param route: ``(n,)`` route indices
    :param arc: ``(n,)`` centre arcs now [m]
    :param speed: ``(n,)`` speeds now [m/s]
    :param acc: ``(n,)`` accelerations, already clipped to the bounds [m/s^2]
    :param substeps: sub-steps per policy period
    :param h: sub-step length [s]
    :param max_speed: speed cap [m/s]
    :return: ``(S + 1, n)`` speeds, ``(S + 1, n)`` arcs (row 0: now) and ``(n,)`` bool: governed
    """
    n = route.shape[0]
    arcs, speeds = np.empty((substeps + 1, n)), np.empty((substeps + 1, n))
    arcs[0], speeds[0] = arc, speed
    governed = np.zeros(n, np.bool_)
    _integrate(table, route, acc, arcs, speeds, 0, substeps, h, max_speed, np.empty(n), governed)
    return speeds, arcs, governed


@numba.njit(cache=True)
def _less_far(
    x: float, lo: float, hi: float, vid: int, x_other: float, lo_other: float, hi_other: float, vid_other: int
) -> bool:
    """Whether a vehicle is less far through a crossing pair's zone than its partner (ties: the higher
    id): the one to hold when both are in it."""
    through = (x - lo) / (hi - lo)
    through_other = (x_other - lo_other) / (hi_other - lo_other)
    return through < through_other or (through == through_other and vid > vid_other)


@numba.njit(cache=True)
def _pair_waits(
    plan: PlanArrays,
    p: int,
    arc: np.ndarray,
    speed: np.ndarray,
    go: np.ndarray,
    a_max: float,
    standing: float,
    slack: float,
) -> tuple[bool, bool]:
    """Whether each side of crossing pair ``p`` waits for the other (``yielding`` and ``waits``).

    Committed means past the point where a vehicle can stop before its *first* zone; a later zone,
    shared with one crossing route, may still be far enough to stop before. The fallback does not
    rely on timing there (timing rests on predicted leaders, and the leaders change when a vehicle
    ahead turns off or merges in): a committed vehicle that can still stop before a pair's zone
    waits while its partner can no longer stop before it (or is in it) and has not cleared it.
    Waiting can form a cycle only in a gridlock (each vehicle in one zone and before another),
    which the check rejects as it rejects any committed vehicle left standing. Two vehicles inside
    one zone at once (only after an unresolved step) are separated by holding the one less far
    through it.
    """
    lo, hi, vid = plan.cross_lo, plan.cross_hi, plan.vehicle_id
    i, j = plan.cross[p, 0], plan.cross[p, 1]
    xi, xj = arc[i], arc[j]
    stop_i = _can_stop(xi, speed[i], lo[p, 0], a_max, standing, slack)
    stop_j = _can_stop(xj, speed[j], lo[p, 1], a_max, standing, slack)
    wait_i = go[i] and stop_i and not stop_j and xj < hi[p, 1]
    wait_j = go[j] and stop_j and not stop_i and xi < hi[p, 0]
    if lo[p, 0] < xi < hi[p, 0] and lo[p, 1] < xj < hi[p, 1]:
        if _less_far(xi, lo[p, 0], hi[p, 0], vid[i], xj, lo[p, 1], hi[p, 1], vid[j]):
            wait_i = True
        if _less_far(xj, lo[p, 1], hi[p, 1], vid[j], xi, lo[p, 0], hi[p, 0], vid[i]):
            wait_j = True
    return wait_i, wait_j


@numba.njit(cache=True)
def _merge_leader(plan: PlanArrays, g: int, arc: np.ndarray, go: np.ndarray) -> tuple[int, int, bool, float]:
    """Merging pair ``g`` as a leader relation: ``(follower, ahead, active, distance)``, the one behind
    along the common exit lane following the one ahead while that one proceeds (``go``) or has reached
    the merge; ``distance``: how far apart along the exit lane, less their separation [m]."""
    m0, m1 = plan.merge[g, 0], plan.merge[g, 1]
    a0, a1 = arc[m0], arc[m1]
    e0, e1 = a0 - plan.merge_exit[g, 0], a1 - plan.merge_exit[g, 1]
    distance = abs(e0 - e1) - plan.merge_sep[g]
    if e0 >= e1:  # vehicle 1 is behind along the common exit lane
        return m1, m0, a0 > plan.merge_lo[g, 0] or go[m0], distance
    return m0, m1, a1 > plan.merge_lo[g, 1] or go[m1], distance


@numba.njit(cache=True)
def _all_committed(
    plan: PlanArrays, arc: np.ndarray, speed: np.ndarray, go: np.ndarray, a_max: float, standing: float, slack: float
) -> bool:
    """``committed`` of every vehicle, into ``go``; whether all are settled (the reference's ``settled``)."""
    settled = True
    for i in range(arc.shape[0]):
        go[i] = _committed(arc[i], speed[i], plan.hull_start[i], plan.hull_end[i], a_max, standing, slack)
        if not ((speed[i] <= standing and not go[i]) or arc[i] > plan.hull_end[i]):
            settled = False
    return settled


@numba.njit(cache=True)
def _gaps_hold(
    plan: PlanArrays,
    arc: np.ndarray,
    speed: np.ndarray,
    reach: np.ndarray,
    go: np.ndarray,
    a_max: float,
    gap_margin: float,
    slack: float,
) -> bool:
    """``gaps_hold``: whether every leader relation that the fallback keeps (:func:`leaders`) can keep its gap
    from here on, whatever the vehicle ahead does within ``a_max`` braking: the gap is at the check's floor or
    above, and so is what is left of it once both have stopped at ``a_max`` (with ``slack`` for the sub-steps)
    when the follower is the faster. Only then may a prediction end once everyone has settled: the fallback,
    which brakes a follower that has less room, then keeps the gap; a planner that closed it for one period
    (a leader rammed past the intersection) must be predicted on. A merging pair's floor is half a gap margin
    over its separation (as the fallback keeps it, the check's distance of 0). ``reach``: the followers' speeds as
    their stopping distance reads them (:func:`reach_speeds`; ``speed`` itself without an actuation lag)."""
    for k in range(plan.follower.shape[0]):
        f, ahead = plan.follower[k], plan.ahead[k]
        if arc[ahead] >= plan.follow_until[k]:
            continue
        gap = plan.follow_gap[k] + (arc[ahead] - plan.ahead_arc[k]) - (arc[f] - plan.follower_arc[k])
        if not _room(gap, reach[f], speed[ahead], plan.follow_floor[k], a_max, slack):
            return False
    for g in range(plan.merge.shape[0]):
        f, ahead, active, distance = _merge_leader(plan, g, arc, go)
        gap, floor = distance + 0.5 * gap_margin, 0.5 * gap_margin
        if active and plan.merge_yields[f] and not _room(gap, reach[f], speed[ahead], floor, a_max, slack):
            return False
    return True


@numba.njit(cache=True)
def _room(gap: float, v_follower: float, v_ahead: float, floor: float, a_max: float, slack: float) -> bool:
    """``room``: the gap stays at ``floor`` or above if both brake at ``a_max`` from now."""
    if gap < floor:
        return False
    if v_follower <= v_ahead:
        return True
    return gap - (v_follower * v_follower - v_ahead * v_ahead) / (2 * a_max) >= floor + slack


@numba.njit(cache=True)
def _travel(speed: float, acc: float, dt: float) -> tuple[float, float]:
    """``travel`` of one vehicle: distance and end speed after ``dt`` at ``acc``, stopping at 0."""
    end = speed + acc * dt
    if end < 0:
        return speed * speed / (2 * max(-acc, 1e-12)), 0.0
    return 0.5 * (speed + end) * dt, end


@numba.njit(cache=True)
def _unsafe(
    gap: float, v_follower: float, v_ahead: float, proceed: float, a_max: float, dt: float, margin: float
) -> bool:
    """Not ``safe_gap_after``: the follower could not stop behind a leader braking at ``a_max``."""
    travel_f, v_f = _travel(v_follower, proceed, dt)
    travel_a, v_a = _travel(v_ahead, -a_max, dt)
    after = gap + travel_a - travel_f
    return not (after - max(v_f * v_f - v_a * v_a, 0.0) / (2 * a_max) >= margin)


@numba.njit(cache=True)
def _fallback(
    plan: PlanArrays,
    arc: np.ndarray,
    speed: np.ndarray,
    reach: np.ndarray,
    go: np.ndarray,
    hold: np.ndarray,
    acc: np.ndarray,
    a_max: float,
    dt: float,
    proceed: float,
    gap_margin: float,
    standing: float,
    slack: float,
) -> None:
    """``fallback_given``: the fallback's accelerations in a state, written into ``acc``.

    :param plan: the scene's arrays
    :param arc: ``(n,)`` arcs [m]
    :param speed: ``(n,)`` speeds [m/s]
    :param reach: ``(n,)`` the speeds that the stopping distances read (:func:`reach_speeds`; ``speed`` without lag)
    :param go: ``(n,)`` committed vehicles
    :param hold: ``(n,)`` scratch for the yielding vehicles
    :param acc: ``(n,)`` output [m/s^2]
    """
    hold[:] = False
    # yielding: a committed vehicle waits before a pair's zone that it can still stop before while
    # its partner cannot (or is in it) and has not cleared it; two inside one zone: the one less far through.
    for p in range(plan.cross.shape[0]):
        wait_i, wait_j = _pair_waits(plan, p, arc, reach, go, a_max, standing, slack)
        if wait_i:
            hold[plan.cross[p, 0]] = True
        if wait_j:
            hold[plan.cross[p, 1]] = True
    for i in range(arc.shape[0]):
        acc[i] = proceed if go[i] and not hold[i] else -a_max
    # leaders_now and safe_gap_after: a committed follower too close to its leader brakes.
    slow = min(proceed, -a_max)
    for k in range(plan.follower.shape[0]):
        f, ahead = plan.follower[k], plan.ahead[k]
        if not go[f] or arc[ahead] >= plan.follow_until[k]:  # braking anyway, or the one ahead has turned off
            continue
        gap = plan.follow_gap[k] + (arc[ahead] - plan.ahead_arc[k]) - (arc[f] - plan.follower_arc[k])
        if _unsafe(gap - plan.follow_keep[k], reach[f], speed[ahead], proceed, a_max, dt, gap_margin):
            acc[f] = slow
    for g in range(plan.merge.shape[0]):
        f, ahead, active, distance = _merge_leader(plan, g, arc, go)
        if not active:
            continue
        gap = distance + 0.5 * gap_margin - plan.merge_keep[g]  # kept at gap_margin: half a margin over the check's
        if go[f] and plan.merge_yields[f] and _unsafe(gap, reach[f], speed[ahead], proceed, a_max, dt, gap_margin):
            acc[f] = slow


@numba.njit(cache=True)
def committed(
    plan: PlanArrays, arc: np.ndarray, speed: np.ndarray, a_max: float, standing: float, slack: float
) -> np.ndarray:
    """``(n,)`` bool: the vehicles that can no longer stop before their first zone, or have cleared them all."""
    go = np.zeros(arc.shape[0], np.bool_)
    _all_committed(plan, arc, speed, go, a_max, standing, slack)
    return go


@numba.njit(cache=True)
def waits(
    plan: PlanArrays, arc: np.ndarray, speed: np.ndarray, go: np.ndarray, a_max: float, standing: float, slack: float
) -> np.ndarray:
    """``(c, 2)`` bool over the crossing pairs: this side waits for the other (:func:`_pair_waits`).

    :param go: ``(n,)`` the committed vehicles (:func:`committed`)
    """
    out = np.zeros((plan.cross.shape[0], 2), np.bool_)
    for p in range(plan.cross.shape[0]):
        out[p, 0], out[p, 1] = _pair_waits(plan, p, arc, speed, go, a_max, standing, slack)
    return out


@numba.njit(cache=True)
def leaders(plan: PlanArrays, arc: np.ndarray, go: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(follower, ahead)`` rows of every leader relation that the fallback keeps a gap in: every
    follow pair, and every active merging pair (:func:`_merge_leader`)."""
    k, g_all = plan.follower.shape[0], plan.merge.shape[0]
    follower, ahead = np.empty(k + g_all, np.int64), np.empty(k + g_all, np.int64)
    rows = 0
    for p in range(k):
        if arc[plan.ahead[p]] < plan.follow_until[p]:
            follower[rows], ahead[rows] = plan.follower[p], plan.ahead[p]
            rows += 1
    for g in range(g_all):
        f, a, active, _ = _merge_leader(plan, g, arc, go)
        if active:
            follower[rows], ahead[rows] = f, a
            rows += 1
    return follower[:rows], ahead[:rows]


@numba.njit(cache=True)
def fallback(
    plan: PlanArrays,
    arc: np.ndarray,
    speed: np.ndarray,
    reach: np.ndarray,
    a_max: float,
    dt: float,
    proceed: float,
    gap_margin: float,
    standing: float,
    slack: float,
) -> np.ndarray:
    """``fallback_numpy``: the fallback's ``(n,)`` accelerations in a state (see :func:`predict`); ``reach``: the
    speeds that the stopping distances read (:func:`reach_speeds`; ``speed`` itself without an actuation lag)."""
    n = arc.shape[0]
    go, hold, acc = np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.empty(n)
    _all_committed(plan, arc, reach, go, a_max, standing, slack)
    _fallback(plan, arc, speed, reach, go, hold, acc, a_max, dt, proceed, gap_margin, standing, slack)
    return acc


@numba.njit(cache=True)
def predict(
    plan: PlanArrays,
    table: EnvelopeTable,
    command: np.ndarray,
    arcs: np.ndarray,
    speeds: np.ndarray,
    steps: int,
    substeps: int,
    h: float,
    max_speed: float,
    a_max: float,
    dt: float,
    proceed: float,
    gap_margin: float,
    standing: float,
    slack: float,
) -> int:
    """``predict_numpy``: ``command`` for one period, then the fallback until all settle (:func:`_gaps_hold` too) or
    ``steps`` periods.

    :param plan: the scene's arrays
    :param table: the governor's envelope
    :param command: ``(n,)`` accelerations of the first period [m/s^2]
    :param arcs: ``(steps * substeps + 1, n)`` output, row 0 filled with the arcs now
    :param speeds: as ``arcs``, the speeds
    :param steps: most periods
    :param substeps: simulation sub-steps per period
    :param h: sub-step length [s]
    :param max_speed: the simulation's speed cap [m/s]
    :param a_max: braking of the fallback and the acceleration bound [m/s^2]
    :param dt: policy period [s]
    :param proceed: acceleration of the fallback's committed vehicles [m/s^2]
    :param gap_margin: the fallback's gap to a leader braking at ``a_max`` [m]
    :param standing: speed below which a vehicle stands [m/s]
    :param slack: slack on "can stop before the zone" [m]
    :return: the number of rows written (row 0 included)
    """
    n = plan.route.shape[0]
    acc = command.copy()
    go, hold, caps, governed = np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.empty(n), np.zeros(n, np.bool_)
    row = 0
    for _ in range(steps):
        _integrate(table, plan.route, acc, arcs, speeds, row, substeps, h, max_speed, caps, governed)
        row += substeps
        if _all_committed(plan, arcs[row], speeds[row], go, a_max, standing, slack) and _gaps_hold(
            plan, arcs[row], speeds[row], speeds[row], go, a_max, gap_margin, slack
        ):
            break  # everyone stands before its zones or has left them, with room behind: the fallback keeps it so
        v = speeds[row]
        _fallback(plan, arcs[row], v, v, go, hold, acc, a_max, dt, proceed, gap_margin, standing, slack)
    return row + 1


class Actuation(NamedTuple):
    """The actuation model of a prediction under declared latency and lag (``Shield`` with bounds): each sub-step
    the command in flight, then the new one, through a first-order lag, as :class:`envs.simulation.faults.Actuator`.

    The realised acceleration ``r`` follows the command ``c`` as ``r(t) = c + (r0 - c) exp(-t / lag)``: over a sub-step
    of length ``h`` it decays by ``decay`` and its mean (what the speed change needs) is ``c + (r0 - c) mean_share``.
    """

    realised: np.ndarray  # (n,) realised accelerations now [m/s^2]
    previous: np.ndarray  # (n,) the commands in flight now (they hold for the latency) [m/s^2]
    old_share: np.ndarray  # (S,) share of each sub-step of a period under the previous command
    decay: float
    mean_share: float
    lag: float  # time constant of the lag [s]
    latency: float  # how much later than planned a command applies [s]
    margin: float  # [m] added to a moving vehicle's stop at the prediction's later states (`reach_speeds`)


@numba.njit(cache=True)
def _lagged_stop(v: float, r: float, c: float, a: float, lag: float, latency: float) -> float:
    """How far a moving vehicle travels until it stands when it is commanded to brake at ``a`` now: the command in
    flight ``c`` holds for ``latency``, then ``-a``, each realised through the first-order lag from ``r`` now.

    Closed form per phase (``r(t) = c + (r0 - c) exp(-t / lag)`` integrates twice exactly); the braking phase ends
    where the speed ``v1 - a t + k lag (1 - exp(-t / lag))`` (``k = r1 + a``) reaches 0, found by Newton's method from
    ``(v1 + k lag) / a``, to the right of the root: the speed is concave in ``t``, so the iterates decrease to it.
    """
    if lag > 0.0:
        e1 = math.exp(-latency / lag)
        v1 = v + c * latency + (r - c) * lag * (1.0 - e1)
        x1 = v * latency + 0.5 * c * latency * latency + (r - c) * lag * (latency - lag * (1.0 - e1))
        r1 = c + (r - c) * e1
    else:
        v1 = v + c * latency
        x1 = v * latency + 0.5 * c * latency * latency
        r1 = c
    if v1 <= 0.0:  # it stands within the latency: no farther than at its speed, plus what a push now adds
        return v * latency + 0.5 * max(r, c, 0.0) * latency * latency
    k = r1 + a
    if lag <= 0.0 or k <= 0.0:
        return x1 + v1 * v1 / (2.0 * a)
    t = (v1 + k * lag) / a
    for _ in range(12):
        e = math.exp(-t / lag)
        f = v1 - a * t + k * lag * (1.0 - e)
        step = f / (-a + k * e)
        t -= step
        if -1e-12 < step < 1e-12:
            break
    e = math.exp(-t / lag)
    return x1 + v1 * t - 0.5 * a * t * t + k * lag * (t - lag * (1.0 - e))


@numba.njit(cache=True)
def reach_speeds(
    speed: np.ndarray,
    realised: np.ndarray,
    previous: np.ndarray,
    a_max: float,
    lag: float,
    latency: float,
    standing: float,
    margin: float = 0.0,
) -> np.ndarray:
    """``(n,)`` the speeds whose stopping distance at ``a_max`` at once, ``v^2 / (2 a_max)``, is the distance each
    vehicle travels until it stands when braked now under latency and lag (:func:`_lagged_stop`, from its realised
    acceleration ``r`` and the command in flight ``c``; never below its speed). A standing vehicle only creeps while
    ``max(r, c) > 0``: ``max(r, c, 0) (lag + latency)``. Every rule that reads a stopping distance (committed, waits,
    the gaps kept) reads these; without lag or latency the shield passes the speeds themselves. ``margin`` [m]
    lengthens a moving vehicle's stop: the prediction's later states are judged so (``Actuation.margin``), that the
    next step's view, which may differ by that much, still finds the vehicles that the plan let go able to stop.
    """
    out = np.empty(speed.shape[0])
    for i in range(speed.shape[0]):
        if speed[i] > standing:
            d = _lagged_stop(speed[i], realised[i], previous[i], a_max, lag, latency)
            out[i] = max(math.sqrt(2.0 * a_max * max(d + margin, 0.0)), speed[i])
        else:
            out[i] = speed[i] + max(realised[i], previous[i], 0.0) * (lag + latency)
    return out


@numba.njit(cache=True)
def _actuate(actuation: Actuation, command: np.ndarray, speed: np.ndarray, r: np.ndarray, previous: np.ndarray,
             acc: np.ndarray) -> None:  # fmt: skip
    """One period of :class:`envs.simulation.faults.Actuator`: the ``(S, n)`` mean accelerations ``acc`` of each
    sub-step under ``command`` (after ``previous`` for the latency), from the realised ``r``; ``r`` and
    ``previous`` move on to the period's end. A vehicle at rest starts from no less than 0 (its brakes hold it)."""
    old, decay, mean = actuation.old_share, actuation.decay, actuation.mean_share
    for i in range(command.shape[0]):
        ri = r[i]
        if speed[i] <= 0.0:
            ri = max(ri, 0.0)
        for k in range(old.shape[0]):
            c = old[k] * previous[i] + (1.0 - old[k]) * command[i]
            acc[k, i] = c + (ri - c) * mean
            ri = c + (ri - c) * decay
        r[i] = ri
        previous[i] = command[i]


@numba.njit(cache=True)
def _integrate_substeps(
    table: EnvelopeTable,
    route: np.ndarray,
    acc: np.ndarray,
    arcs: np.ndarray,
    speeds: np.ndarray,
    row: int,
    substeps: int,
    h: float,
    max_speed: float,
    caps: np.ndarray,
) -> None:
    """:func:`_integrate` with one acceleration per sub-step (``acc``: ``(S, n)``), as
    :func:`envs.simulation.engine.integrate` with a two-dimensional ``acc``."""
    n = route.shape[0]
    for i in range(n):
        caps[i] = _envelope(table, route[i], arcs[row, i])
    for k in range(substeps):
        src, dst = row + k, row + k + 1
        for i in range(n):
            v0, x0 = speeds[src, i], arcs[src, i]
            v = min(max(v0 + acc[k, i] * h, 0.0), max_speed)
            x = x0 + 0.5 * (v0 + v) * h
            cap_x = _envelope(table, route[i], x)
            cap = min(caps[i], cap_x)
            if v > cap:
                v = cap
                x = x0 + 0.5 * (v0 + v) * h
                cap_x = _envelope(table, route[i], x)
            speeds[dst, i], arcs[dst, i] = v, x
            caps[i] = cap_x


@numba.njit(cache=True)
def predict_lagged(
    plan: PlanArrays,
    table: EnvelopeTable,
    actuation: Actuation,
    command: np.ndarray,
    arcs: np.ndarray,
    speeds: np.ndarray,
    steps: int,
    substeps: int,
    h: float,
    max_speed: float,
    a_max: float,
    dt: float,
    proceed: float,
    gap_margin: float,
    standing: float,
    slack: float,
) -> int:
    """:func:`predict` under latency and lag (``predict_lagged_numpy``): every period's command, the first one's and
    the fallback's, is realised through :class:`Actuation` (the fallback's braking too), and the rules of the fallback
    and of the end read the reach speeds (:func:`reach_speeds`). Arguments as :func:`predict`.
    """
    n = plan.route.shape[0]
    acc = command.copy()
    r, previous = actuation.realised.copy(), actuation.previous.copy()
    sub = np.empty((substeps, n))
    go, hold, caps = np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.empty(n)
    row = 0
    for _ in range(steps):
        _actuate(actuation, acc, speeds[row], r, previous, sub)
        _integrate_substeps(table, plan.route, sub, arcs, speeds, row, substeps, h, max_speed, caps)
        row += substeps
        v = speeds[row]
        reach = reach_speeds(v, r, previous, a_max, actuation.lag, actuation.latency, standing, actuation.margin)
        if _all_committed(plan, arcs[row], reach, go, a_max, standing, slack) and _gaps_hold(
            plan, arcs[row], v, reach, go, a_max, gap_margin, slack
        ):
            break
        _fallback(plan, arcs[row], v, reach, go, hold, acc, a_max, dt, proceed, gap_margin, standing, slack)
    return row + 1


@numba.njit(cache=True)
def conflicts(
    plan: PlanArrays, arcs: np.ndarray, speed: np.ndarray, a_max: float, standing: float, slack: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``conflicts_numpy``: the conflicts of a prediction, in one pass over its sub-steps.

    :param plan: the scene's arrays
    :param arcs: ``(T + 1, n)`` predicted arcs (row 0: now)
    :param speed: ``(n,)`` predicted speeds at the end
    :return: ``(k,)``, ``(c,)``, ``(g,)`` bool conflicting follow, crossing and merging pairs and
        ``(n,)`` bool vehicles that end neither standing before their zones nor past them
    """
    cross, lo, hi, merge = plan.cross, plan.cross_lo, plan.cross_hi, plan.merge
    bad_follow = np.zeros(plan.follower.shape[0], np.bool_)
    bad_cross = np.zeros(cross.shape[0], np.bool_)
    bad_merge = np.zeros(merge.shape[0], np.bool_)
    for t in range(1, arcs.shape[0]):
        x = arcs[t]
        for k in range(plan.follower.shape[0]):
            if x[plan.ahead[k]] >= plan.follow_until[k]:  # it has turned off: no longer on the follower's path
                continue
            gap = (
                plan.follow_gap[k]
                + (x[plan.ahead[k]] - plan.ahead_arc[k])
                - (x[plan.follower[k]] - plan.follower_arc[k])
            )
            if gap < plan.follow_floor[k]:
                bad_follow[k] = True
        for p in range(cross.shape[0]):
            both = lo[p, 0] < x[cross[p, 0]] < hi[p, 0] and lo[p, 1] < x[cross[p, 1]] < hi[p, 1]
            if both and plan.cross_already[p]:
                both = x[cross[p, plan.cross_back[p]]] > plan.cross_stop[p]
            if both:
                bad_cross[p] = True
        for g in range(merge.shape[0]):
            x0, x1 = x[merge[g, 0]], x[merge[g, 1]]
            if x0 > plan.merge_lo[g, 0] and x1 > plan.merge_lo[g, 1]:
                if abs((x0 - plan.merge_exit[g, 0]) - (x1 - plan.merge_exit[g, 1])) < plan.merge_sep[g]:
                    bad_merge[g] = True
    arc = arcs[arcs.shape[0] - 1]
    go = np.zeros(arc.shape[0], np.bool_)
    _all_committed(plan, arc, speed, go, a_max, standing, slack)
    stuck = np.zeros(arc.shape[0], np.bool_)
    for i in range(arc.shape[0]):
        stuck[i] = not ((speed[i] <= standing and not go[i]) or arc[i] > plan.hull_end[i])
    return bad_follow, bad_cross, bad_merge, stuck


@numba.njit(cache=True)
def _on_path(mine: int, other: int, merging: np.ndarray, parting: np.ndarray) -> bool:
    """``on_path``: whether a vehicle on route ``other`` can be ahead on a vehicle on route ``mine``'s path: the same
    route, one from the same spawn lane (until the lines part), or one that ends on the same exit lane. A leader
    that has turned onto its own branch (inD's split lanes, the 4-way's left turn lane) leads vehicles that its
    former follower never meets on a lane: that pair of the leader's leader is no follow pair (its gap, a
    difference of arcs on two unrelated paths, closed where nobody was near)."""
    return mine == other or parting[other, mine] > -np.inf or merging[mine, other]


@numba.njit(cache=True)
def pairs(
    route: np.ndarray,
    arc: np.ndarray,
    speed: np.ndarray,
    length: np.ndarray,
    gap: np.ndarray,
    leader: np.ndarray,
    vehicle_id: np.ndarray,
    hull_start: np.ndarray,
    candidate: np.ndarray,
    prune: bool,
    conflicts: np.ndarray,
    merging: np.ndarray,
    parting: np.ndarray,
    zone_start: np.ndarray,
    zone_end: np.ndarray,
    exit_arc: np.ndarray,
    zone_margin: np.ndarray,
    merge_margin: float,
    standing: float,
    slack: float,
) -> tuple[np.ndarray, ...]:
    """The pairs of a scene that the shield checks (``Shield._plan``), in the order and with the
    arithmetic of its former NumPy form, which built and scanned ``(n, n)`` arrays in about 40 calls.

    :param route: ``(n,)`` route indices
    :param arc: ``(n,)`` centre arcs [m]
    :param speed: ``(n,)`` speeds [m/s]
    :param length: ``(n,)`` lengths [m]
    :param gap: ``(n,)`` bumper gaps to the leaders [m]
    :param leader: ``(n,)`` leader rows (-1: none)
    :param vehicle_id: ``(n,)`` ids
    :param hull_start: ``(n,)`` centre arcs from which the bodies may touch a zone (padded) [m]
    :param candidate: ``(n,)`` bool: may commit within the prediction (``Shield._may_commit``)
    :param prune: leave out the conflicting pairs of non-candidates and crossing pairs one of which has
        passed the zone
    :param conflicts: ``(R, R)`` the layout's conflicting routes
    :param merging: ``(R, R)`` those that merge
    :param parting: ``(R, R)`` :func:`envs.simulation.layouts.parting_arcs`
    :param zone_start: ``(R, R)`` the layout's zone starts
    :param zone_end: ``(R, R)`` and ends
    :param exit_arc: ``(R,)`` the routes' exit arcs
    :param zone_margin: ``(n,)`` each vehicle's zone padding: the shield's ``zone_margin``, 0 for a waiting human
    :param merge_margin: the shield's ``merge_margin``
    :param standing: speed below which a vehicle stands [m/s]
    :param slack: the stopping slack [m]
    :return: ``follow`` ``(k, 2)``, ``follow_gap`` ``(k,)``, ``cross`` ``(c, 2)``, ``cross_lo``,
        ``cross_hi`` ``(c, 2)``, ``cross_already``, ``cross_back``, ``cross_stop`` ``(c,)``, ``merge``
        ``(g, 2)``, ``merge_lo``, ``merge_exit`` ``(g, 2)``, ``merge_sep`` ``(g,)``, ``rank`` ``(n,)``
        (the fields of :class:`envs.planners.shield._Plan`)
    """
    n = route.shape[0]
    # Follow pairs: the leader, the leader's leader, the next vehicle ahead on the same route, and a
    # vehicle ahead on another route from the same spawn lane until its rear has passed the parting arc.
    by_arc = np.argsort(arc, kind="mergesort")  # by route, then arc, then row: np.lexsort((arc, route))
    by_route = by_arc[np.argsort(route[by_arc], kind="mergesort")]
    most = 2 * n + max(n - 1, 0) + n * n
    follower, ahead, follow_gap = np.empty(most, np.int64), np.empty(most, np.int64), np.empty(most)
    k = 0
    for i in range(n):
        if leader[i] >= 0:
            follower[k], ahead[k], follow_gap[k] = i, leader[i], gap[i]
            k += 1
    for i in range(n):
        lead = leader[i]
        if lead >= 0 and leader[lead] >= 0 and _on_path(route[i], route[leader[lead]], merging, parting):
            follower[k], ahead[k] = i, leader[lead]
            follow_gap[k] = gap[i] + length[lead] + gap[lead]
            k += 1
    for s in range(n - 1):
        b, a = by_route[s], by_route[s + 1]
        if route[b] == route[a]:
            follower[k], ahead[k] = b, a
            follow_gap[k] = arc[a] - arc[b] - (length[a] + length[b]) / 2
            k += 1
    for b in range(n):
        for a in range(n):
            span = arc[a] - arc[b] - (length[a] + length[b]) / 2
            if span > 0 and arc[a] - length[a] / 2 < parting[route[a], route[b]]:
                follower[k], ahead[k], follow_gap[k] = b, a, span
                k += 1
    follow = np.empty((k, 2), np.int64)
    follow[:, 0], follow[:, 1] = follower[:k], ahead[:k]
    # Conflicting pairs (i < j) among the candidates, split into crossing and merging ones.
    most = n * (n - 1) // 2
    cross, cross_lo, cross_hi = np.empty((most, 2), np.int64), np.empty((most, 2)), np.empty((most, 2))
    merge, merge_lo, merge_exit = np.empty((most, 2), np.int64), np.empty((most, 2)), np.empty((most, 2))
    merge_sep = np.empty(most)
    c, g = 0, 0
    for i in range(n):
        if not candidate[i]:
            continue
        for j in range(i + 1, n):
            if not (candidate[j] and conflicts[route[i], route[j]]):
                continue
            ri, rj = route[i], route[j]
            if merging[ri, rj]:
                merge[g, 0], merge[g, 1] = i, j
                merge_lo[g, 0] = zone_start[ri, rj] - zone_margin[i] - length[i] / 2
                merge_lo[g, 1] = zone_start[rj, ri] - zone_margin[j] - length[j] / 2
                merge_exit[g, 0], merge_exit[g, 1] = exit_arc[ri], exit_arc[rj]
                merge_sep[g] = (length[i] + length[j]) / 2 + merge_margin
                g += 1
                continue
            lo_i = zone_start[ri, rj] - zone_margin[i] - length[i] / 2
            lo_j = zone_start[rj, ri] - zone_margin[j] - length[j] / 2
            hi_i = zone_end[ri, rj] + zone_margin[i] + length[i] / 2
            hi_j = zone_end[rj, ri] + zone_margin[j] + length[j] / 2
            if prune and not (arc[i] < hi_i and arc[j] < hi_j):  # one has passed the zone
                continue
            cross[c, 0], cross[c, 1] = i, j
            cross_lo[c, 0], cross_lo[c, 1], cross_hi[c, 0], cross_hi[c, 1] = lo_i, lo_j, hi_i, hi_j
            c += 1
    cross, cross_lo, cross_hi = cross[:c].copy(), cross_lo[:c].copy(), cross_hi[:c].copy()
    # Both in the zone now, the one less far through (`back`) standing: it must not move past `stop`.
    back, already, stop = np.zeros(c, np.int64), np.empty(c, np.bool_), np.empty(c)
    for p in range(c):
        i, j = cross[p, 0], cross[p, 1]
        if _less_far(arc[j], cross_lo[p, 1], cross_hi[p, 1], vehicle_id[j], arc[i], cross_lo[p, 0], cross_hi[p, 0],
                     vehicle_id[i]):  # fmt: skip
            back[p] = 1
        inside = cross_lo[p, 0] < arc[i] < cross_hi[p, 0] and cross_lo[p, 1] < arc[j] < cross_hi[p, 1]
        x_back = arc[cross[p, back[p]]]
        already[p] = inside and speed[cross[p, back[p]]] <= standing
        stop[p] = x_back + slack
    # A total order (farthest into the hull first, then the lowest id): np.lexsort((vehicle_id, hull_start - arc)).
    by_id = np.argsort(vehicle_id, kind="mergesort")
    order = by_id[np.argsort((hull_start - arc)[by_id], kind="mergesort")]
    rank = np.empty(n, np.int64)
    for s in range(n):
        rank[order[s]] = s
    return (follow, follow_gap[:k].copy(), cross, cross_lo, cross_hi, already, back, stop, merge[:g].copy(),
            merge_lo[:g].copy(), merge_exit[:g].copy(), merge_sep[:g].copy(), rank)  # fmt: skip


@numba.njit(cache=True)
def _blame_pair(blamed: np.ndarray, free: np.ndarray, second: int, first: int) -> None:
    """Blame the free one of a conflicting pair; ``second`` if both are free."""
    pick = second if free[second] else first
    if free[pick]:
        blamed[pick] = True


@numba.njit(cache=True)
def blame(
    plan: PlanArrays,
    arcs: np.ndarray,
    speed: np.ndarray,
    arc_now: np.ndarray,
    rank: np.ndarray,
    free: np.ndarray,
    bad_follow: np.ndarray,
    bad_cross: np.ndarray,
    bad_merge: np.ndarray,
    stuck: np.ndarray,
    a_max: float,
    standing: float,
    slack: float,
) -> np.ndarray:
    """``blame_numpy``: who to override for the conflicts of a prediction (``Shield._blame``'s rules).

    :param arcs: ``(T + 1, n)`` predicted arcs (row 0: now)
    :param speed: ``(n,)`` predicted speeds at the end
    :param arc_now: ``(n,)`` arcs now
    :param rank: ``(n,)`` who goes first when two would enter a zone at once
    :param free: ``(n,)`` bool: vehicles whose command still differs from the fallback
    :param bad_follow: ``(k,)``, ``bad_cross`` ``(c,)``, ``bad_merge`` ``(g,)``: the conflicting pairs
    :param stuck: ``(n,)`` bool: automated vehicles that end neither standing before their zones nor past them
    :return: ``(n,)`` bool
    """
    n = arc_now.shape[0]
    blamed = np.zeros(n, np.bool_)
    for k in range(bad_follow.shape[0]):
        if bad_follow[k]:
            _blame_pair(blamed, free, plan.follower[k], plan.ahead[k])
    if bad_cross.any():
        # Who comes second: the later to enter the intersection's zones (one time per vehicle, so that the
        # order is total and a cycle of conflicts leaves one to go).
        later = arcs.shape[0] - 1
        key = np.empty(n, np.int64)
        for i in range(n):
            t_in = later
            for t in range(1, arcs.shape[0]):
                if arcs[t, i] > plan.hull_start[i]:
                    t_in = t - 1
                    break
            key[i] = t_in * (n + 1) + rank[i]
        for p in range(bad_cross.shape[0]):
            if bad_cross[p]:
                a, b = plan.cross[p, 0], plan.cross[p, 1]
                if key[b] > key[a]:
                    _blame_pair(blamed, free, b, a)
                else:
                    _blame_pair(blamed, free, a, b)
    for g in range(bad_merge.shape[0]):
        if bad_merge[g]:
            a, b = plan.merge[g, 0], plan.merge[g, 1]
            if arc_now[a] - plan.merge_exit[g, 0] >= arc_now[b] - plan.merge_exit[g, 1]:
                _blame_pair(blamed, free, b, a)
            else:
                _blame_pair(blamed, free, a, b)
    if stuck.any():
        # A gridlock in the prediction (each waits for another inside its zone): spare the first in order;
        # if it still fails, the next round blames it too.
        spare, count = -1, 0
        for i in range(n):
            if stuck[i] and free[i]:
                count += 1
                if spare < 0 or rank[i] < rank[spare]:
                    spare = i
        for i in range(n):
            if stuck[i] and free[i] and not (count > 1 and i == spare):
                blamed[i] = True
        # A committed vehicle stuck behind a vehicle ahead: that one's command is to blame.
        end = arcs[arcs.shape[0] - 1]
        go = committed(plan, end, speed, a_max, standing, slack)
        follower, ahead = leaders(plan, end, go)
        for r in range(follower.shape[0]):
            if stuck[follower[r]] and not free[follower[r]] and free[ahead[r]]:
                blamed[ahead[r]] = True
    return blamed
