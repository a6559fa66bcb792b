"""The reservation passes of :class:`envs.planners.aim.AIMPlanner`, compiled with numba.

Why compiled: the passes are a fixed-point iteration (each vehicle takes its best clash-free
candidate given the others' choices of the previous pass), 5-6 passes per policy step on average,
each about 15 NumPy calls on ``(n, C)`` arrays of some 12 vehicles and 52 candidates. On the loaded
2-core development machine a NumPy call costs 1-2 us whatever the array size, so the passes alone
made 0.15-0.2 ms of AIM's step, a quarter of the simulation's own step (benchmarks/README.md,
"AIM: compiled reservation passes").

:func:`settle` is :func:`envs.planners.aim.settle_numpy` (the reference) with the same
floating-point operations (two additions; the rest are comparisons), no ``fastmath``, so its
choices are the NumPy ones exactly (``tests/test_baselines.py`` checks it). ``cache=True`` stores
the machine code next to this file, so only the first process compiles it.
"""

from __future__ import annotations

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
    """The chosen candidate of every vehicle: :func:`envs.planners.aim.settle_numpy`, loop by loop.

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
    for _ in range(passes):
        clash[:] = False
        for r in range(pair_i.size):  # j's chosen window in its zone with i against each of i's candidates
            i, j = pair_i[r], pair_j[r]
            enter_j = zone_enter[row_j[r], choice[j]]
            leave_j = zone_leave[row_j[r], choice[j]] + buffer
            for c in range(c_count):
                if zone_enter[row_i[r], c] < leave_j and enter_j < zone_leave[row_i[r], c] + buffer:
                    clash[i, c] = True
        for i in range(n):
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
            same &= new[i] == choice[i]
        if same:
            break
        choice[:] = new
    return choice
