"""The leader search of :meth:`envs.simulation.engine.Simulation.leaders`, compiled with numba.

In NumPy the search builds five ``(n, n)`` arrays (every vehicle's position on every other's route): about
0.3 ms at 100 vehicles, paid by every simulation step and by every scene the planner server rebuilds. Here one
pass over the pairs keeps the nearest vehicle ahead. The floating-point operations are NumPy's, in the same
order (no ``fastmath``), so the leaders and gaps are bitwise the same; ``tests/test_simulation.py`` compares
them with the NumPy form on random scenes of every layout.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def leaders(
    route: np.ndarray,
    arc: np.ndarray,
    length: np.ndarray,
    lane: np.ndarray,
    back_lane: np.ndarray,
    lane_start: np.ndarray,
    parting: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest vehicle ahead on the same path and the bumper gap to it.

    :param route: ``(n,)`` route indices
    :param arc: ``(n,)`` centre arcs [m]
    :param length: ``(n,)`` lengths [m]
    :param lane: ``(n,)`` each vehicle's lane at its centre, ``back_lane`` at its split-clearance point behind
    :param lane_start: ``(R, L)`` arc of each lane's start on each route (NaN: not on it)
    :param parting: ``(R, R)`` arc where one route's path leaves the other's (``layouts.parting_arcs``)
    :return: ``(n,)`` leader rows (-1 if none) and ``(n,)`` gaps [m] (``inf`` if none)
    """
    n = arc.shape[0]
    into, into_back, rear = np.empty(n), np.empty(n), np.empty(n)
    for j in range(n):
        into[j] = arc[j] - lane_start[route[j], lane[j]]
        into_back[j] = arc[j] - lane_start[route[j], back_lane[j]]
        rear[j] = arc[j] - length[j] / 2
    leader, gap = np.full(n, -1, np.int64), np.full(n, np.inf)
    for i in range(n):
        r, best, found = route[i], np.inf, 0
        for j in range(n):
            if j == i:
                continue
            x = lane_start[r, lane[j]] + into[j]
            if np.isnan(x):  # j's lane is not on i's route: where paths split, its rear point decides
                x_back = lane_start[r, back_lane[j]] + into_back[j]
                x = arc[j] if np.isnan(x_back) and rear[j] < parting[route[j], r] else x_back
            ahead = x - arc[i]
            if np.isfinite(ahead) and ahead > 0 and ahead < best:
                best, found = ahead, j
        if np.isfinite(best):
            leader[i] = found
            gap[i] = best - (length[i] + length[found]) / 2
    return leader, gap


@numba.njit(cache=True)
def lanes(route: np.ndarray, arc: np.ndarray, route_lane_starts: np.ndarray, route_lane_ids: np.ndarray) -> np.ndarray:
    """:meth:`envs.simulation.layouts.Layout.lane_at` of ``(n,)`` points, compiled (the lane ids are the same).

    :param route: ``(n,)`` route indices
    :param arc: ``(n,)`` arcs along them [m]
    :param route_lane_starts: ``(R, K)`` arc where each lane of a route starts, padded with ``inf``
    :param route_lane_ids: ``(R, K)`` global lane ids along each route
    :return: ``(n,)`` lane ids
    """
    n = arc.shape[0]
    out = np.empty(n, np.int64)
    for i in range(n):
        r, k = route[i], -1
        for m in range(route_lane_starts.shape[1]):
            if route_lane_starts[r, m] <= arc[i]:
                k += 1
        out[i] = route_lane_ids[r, max(k, 0)]
    return out


@numba.njit(cache=True)
def leaders_at(
    route: np.ndarray,
    arc: np.ndarray,
    length: np.ndarray,
    split_clearance: float,
    route_lane_starts: np.ndarray,
    route_lane_ids: np.ndarray,
    lane_start: np.ndarray,
    parting: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`leaders` with the lanes looked up here: each vehicle's at its centre and at ``split_clearance``
    behind its rear (one compiled call per scene instead of a NumPy lookup over ``(2, n, K)`` and this kernel)."""
    back_arc = arc - length / 2 - split_clearance
    lane = lanes(route, arc, route_lane_starts, route_lane_ids)
    back_lane = lanes(route, back_arc, route_lane_starts, route_lane_ids)
    return leaders(route, arc, length, lane, back_lane, lane_start, parting)
