"""The shield's prediction loop, compiled with numba: :meth:`envs.planners.shield.Shield.predict`.

Why compiled: a prediction runs up to 40 sequential policy periods (the fallback is a feedback law
of the predicted state), each one ``integrate`` call (three sub-steps, six or more speed-envelope
look-ups) and one fallback evaluation, about 100 NumPy calls on arrays of 10-30 vehicles. On the
2-core development machine one such call costs 0.4-1.7 us whatever the array size, and a predicted
period about 250 us in all; for the shield to cost no more than the simulation's step (0.7-1 ms per
policy step, with 13-60 predicted periods per step), a period may cost about 15 us. That is the
per-call overhead of some 20 NumPy calls, less than ``integrate`` alone makes, so no vectorization
gets there (benchmarks/README.md, "envs: planners in the evaluation loop").

Every function here is the scalar form of a NumPy one, with the same floating-point operations in
the same order (no ``fastmath``, so no reassociation or fused multiply-add), so that the prediction
is bitwise the NumPy one (``tests/test_shield.py`` checks it against
:meth:`~envs.planners.shield.Shield.predict_numpy`, which calls :func:`envs.simulation.integrate`):

- :func:`_envelope`: :meth:`envs.planners.shield._PredictionLayout.envelope_at` for one vehicle,
- :func:`_integrate`: :func:`envs.simulation.integrate` for one policy period,
- :func:`_committed`, :func:`_fallback`: ``Shield.committed`` and ``Shield._fallback_given``
  (with ``_yielding``, ``_leaders_now`` and ``_safe_gap_after``),
- :func:`predict`: the loop of ``Shield.predict_numpy``; :func:`fallback`: the fallback in one state.

The first call compiles the kernel (a few seconds); ``cache=True`` stores the machine code next to
this file (``__pycache__``), so later processes load it in milliseconds.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _envelope(sq, dsq, limit, columns, last, ds, route, arc):
    """The governor's speed envelope at one point: ``_PredictionLayout.envelope_at``'s arithmetic.

    :param sq: flat ``(R * S,)`` squared envelope
    :param dsq: flat squared envelope's differences to the next sample (0 at the last)
    :param limit: flat speed limits
    :param columns: samples per route ``S``
    :param last: ``S - 1``
    :param ds: sample spacing [m]
    :param route: route index
    :param arc: centre arc [m]
    """
    u = min(max(arc / ds, 0.0), float(last))
    i0 = min(int(u), last - 1)
    f = u - i0
    flat = route * columns + i0
    envelope = math.sqrt(sq[flat] + dsq[flat] * f)
    if u >= last:
        flat += 1
    return min(envelope, limit[flat])


@numba.njit(cache=True)
def _integrate(table, route, acc, arcs, speeds, row, substeps, h, max_speed):
    """One policy period of :func:`envs.simulation.integrate`, written into ``arcs`` and ``speeds``.

    Vehicles are independent in the model, so each runs its sub-steps on its own.

    :param table: ``(sq, dsq, limit, columns, last, ds)`` of the governor's envelope
    :param route: ``(n,)`` route indices
    :param acc: ``(n,)`` accelerations held over the period [m/s^2]
    :param arcs: ``(T + 1, n)`` arcs; row ``row`` is the state now, rows ``row + 1 ..
        row + substeps`` are written
    :param speeds: ``(T + 1, n)`` speeds, as ``arcs``
    :param row: the row of the state now
    :param substeps: sub-steps per period
    :param h: sub-step length [s]
    :param max_speed: speed cap [m/s]
    """
    sq, dsq, limit, columns, last, ds = table
    for i in range(route.shape[0]):
        r = route[i]
        v0, x0 = speeds[row, i], arcs[row, i]
        cap_now = _envelope(sq, dsq, limit, columns, last, ds, r, x0)
        for k in range(substeps):
            v = min(max(v0 + acc[i] * h, 0.0), max_speed)
            x = x0 + 0.5 * (v0 + v) * h
            cap_x = _envelope(sq, dsq, limit, columns, last, ds, r, x)
            cap = min(cap_now, cap_x)
            if v > cap:  # the governor: the sub-step ends at the envelope, looked up again there
                v = cap
                x = x0 + 0.5 * (v0 + v) * h
                cap_x = _envelope(sq, dsq, limit, columns, last, ds, r, x)
            speeds[row + k + 1, i], arcs[row + k + 1, i] = v, x
            v0, x0, cap_now = v, x, cap_x


@numba.njit(cache=True)
def _committed(arc, speed, hull_start, hull_end, a_max, standing, slack):
    """``Shield.committed`` of one vehicle: it can no longer stop before its first zone, or has cleared them all."""
    cannot_stop = arc > hull_start or (speed > standing and arc + speed * speed / (2 * a_max) + slack > hull_start)
    return cannot_stop or arc > hull_end


@numba.njit(cache=True)
def _travel(speed, acc, dt):
    """``shield._travel`` of one vehicle: distance and end speed after ``dt`` at ``acc``, stopping at 0."""
    end = speed + acc * dt
    if end < 0:
        return speed * speed / (2 * max(-acc, 1e-12)), 0.0
    return 0.5 * (speed + end) * dt, end


@numba.njit(cache=True)
def _unsafe(gap, v_follower, v_ahead, proceed, a_max, dt, margin):
    """Not ``shield._safe_gap_after``: the follower could not stop behind a leader braking at ``a_max``."""
    travel_f, v_f = _travel(v_follower, proceed, dt)
    travel_a, v_a = _travel(v_ahead, -a_max, dt)
    after = gap + travel_a - travel_f
    return not (after - max(v_f * v_f - v_a * v_a, 0.0) / (2 * a_max) >= margin)


@numba.njit(cache=True)
def _fallback(plan, arc, speed, go, hold, acc, a_max, dt, proceed, gap_margin, standing, slack):
    """``Shield._fallback_given``: the fallback's accelerations in a state, written into ``acc``.

    :param plan: the arrays of :attr:`envs.planners.shield._Plan.kernel_arrays`
    :param go: ``(n,)`` committed vehicles
    :param hold: ``(n,)`` scratch for the yielding vehicles
    """
    _, _, _, f_rows, a_rows, follow_gap, f_arc, a_arc, cross, lo, hi, vid, merge, merge_lo, merge_exit, merge_sep = plan
    n = arc.shape[0]
    hold[:] = False
    # _yielding: a committed vehicle waits before a pair's zone that it can still stop before while
    # its partner cannot (or is in it) and has not cleared it; two inside one zone: the one less far through.
    for p in range(cross.shape[0]):
        i, j = cross[p, 0], cross[p, 1]
        xi, xj, vi, vj = arc[i], arc[j], speed[i], speed[j]
        stop_i = xi <= lo[p, 0] and (vi <= standing or xi + vi * vi / (2 * a_max) + slack <= lo[p, 0])
        stop_j = xj <= lo[p, 1] and (vj <= standing or xj + vj * vj / (2 * a_max) + slack <= lo[p, 1])
        if go[i] and stop_i and not stop_j and xj < hi[p, 1]:
            hold[i] = True
        if go[j] and stop_j and not stop_i and xi < hi[p, 0]:
            hold[j] = True
        if lo[p, 0] < xi < hi[p, 0] and lo[p, 1] < xj < hi[p, 1]:
            through_i = (xi - lo[p, 0]) / (hi[p, 0] - lo[p, 0])
            through_j = (xj - lo[p, 1]) / (hi[p, 1] - lo[p, 1])
            if through_i < through_j or (through_i == through_j and vid[i] > vid[j]):
                hold[i] = True
            if through_j < through_i or (through_j == through_i and vid[j] > vid[i]):
                hold[j] = True
    for i in range(n):
        acc[i] = proceed if go[i] and not hold[i] else -a_max
    # _leaders_now and _safe_gap_after: a committed follower too close to its leader brakes.
    slow = min(proceed, -a_max)
    for k in range(f_rows.shape[0]):
        f, ahead = f_rows[k], a_rows[k]
        gap = follow_gap[k] + (arc[ahead] - a_arc[k]) - (arc[f] - f_arc[k])
        if go[f] and _unsafe(gap, speed[f], speed[ahead], proceed, a_max, dt, gap_margin):
            acc[f] = slow
    for g in range(merge.shape[0]):
        m0, m1 = merge[g, 0], merge[g, 1]
        a0, a1 = arc[m0], arc[m1]
        e0, e1 = a0 - merge_exit[g, 0], a1 - merge_exit[g, 1]
        if e0 >= e1:  # vehicle 1 is behind along the common exit lane
            f, ahead, active = m1, m0, a0 > merge_lo[g, 0] or go[m0]
        else:
            f, ahead, active = m0, m1, a1 > merge_lo[g, 1] or go[m1]
        if not active:
            continue
        gap = abs(e0 - e1) - merge_sep[g] + 0.5 * gap_margin
        if go[f] and _unsafe(gap, speed[f], speed[ahead], proceed, a_max, dt, gap_margin):
            acc[f] = slow


@numba.njit(cache=True)
def fallback(plan, arc, speed, a_max, dt, proceed, gap_margin, standing, slack):
    """``Shield._fallback``: the fallback's ``(n,)`` accelerations in a state (``Shield.committed`` first).

    :param plan: the arrays of :attr:`envs.planners.shield._Plan.kernel_arrays`
    :param arc: ``(n,)`` arcs [m]
    :param speed: ``(n,)`` speeds [m/s]
    """
    hull_start, hull_end = plan[1], plan[2]
    n = arc.shape[0]
    go = np.zeros(n, np.bool_)
    for i in range(n):
        go[i] = _committed(arc[i], speed[i], hull_start[i], hull_end[i], a_max, standing, slack)
    acc = np.empty(n)
    _fallback(plan, arc, speed, go, np.zeros(n, np.bool_), acc, a_max, dt, proceed, gap_margin, standing, slack)
    return acc


@numba.njit(cache=True)
def predict(
    plan, table, command, arcs, speeds, steps, substeps, h, max_speed, a_max, dt, proceed, gap_margin, standing, slack
):
    """``Shield.predict_numpy``: ``command`` for one period, then the fallback until all settle or ``steps`` periods.

    :param plan: the arrays of :attr:`envs.planners.shield._Plan.kernel_arrays`
    :param table: ``(sq, dsq, limit, columns, last, ds)`` of the governor's envelope
    :param command: ``(n,)`` accelerations of the first period [m/s^2]
    :param arcs: ``(steps * substeps + 1, n)`` output, row 0 filled with the arcs now
    :param speeds: as ``arcs``, the speeds
    :return: the number of rows written (row 0 included)
    """
    route, hull_start, hull_end = plan[0], plan[1], plan[2]
    n = route.shape[0]
    acc = command.copy()
    go = np.zeros(n, np.bool_)
    hold = np.zeros(n, np.bool_)
    row = 0
    for _ in range(steps):
        _integrate(table, route, acc, arcs, speeds, row, substeps, h, max_speed)
        row += substeps
        arc, speed = arcs[row], speeds[row]
        settled = True
        for i in range(n):
            go[i] = _committed(arc[i], speed[i], hull_start[i], hull_end[i], a_max, standing, slack)
            if not ((speed[i] <= standing and not go[i]) or arc[i] > hull_end[i]):
                settled = False
        if settled:
            break  # everyone stands before its zones or has left them: the fallback keeps it so
        _fallback(plan, arc, speed, go, hold, acc, a_max, dt, proceed, gap_margin, standing, slack)
    return row + 1
