"""Free-flow travel times: the fastest trip along a route that the lane speed limits allow.

The reference a vehicle's delay is measured against (see :mod:`envs.evaluation.metrics`). A lone vehicle
starts at its spawn point with its scheduled initial speed, accelerates at ``acceleration`` up to
the lane limit, never exceeds the limit sampled along the route (``Layout.speed_limit``, every
``Layout.ds`` metres: the road's limit on straight lanes, lower ones on curves where the layout
sets them), and brakes at ``deceleration`` in time for every lower limit ahead. The harness uses
the environment's acceleration bounds (``Scene.a_max`` and ``-Scene.a_min``), so no planner can
beat the reference: a delay is never negative except by the time discretization.

The speed profile comes from two envelopes on a grid of ``ds`` spacing, both vectorized over
vehicles (cumulative minima, no loop over samples)::

    braking   v_b(s_k)^2 = min_{j >= k} limit(s_j)^2 + 2 b (s_j - s_k)
    profile   v(s_k)^2   = min(v0^2 + 2 a s_k, min_{j <= k} v_b(s_j)^2 + 2 a (s_k - s_j))

and the time of each grid segment is that of a constant acceleration between its end speeds,
``2 ds / (v_k + v_{k+1})``.
"""

from __future__ import annotations

import numpy as np

from envs.simulation.layouts import Layout


def free_flow_table(
    layout: Layout,
    route: np.ndarray,
    start_arc: np.ndarray,
    start_speed: np.ndarray,
    acceleration: float,
    deceleration: float,
) -> np.ndarray:
    """Reference travel times from each vehicle's start to every grid point ahead of it.

    :param layout: the intersection
    :param route: ``(n,)`` route indices
    :param start_arc: ``(n,)`` start position (centre) along the route [m]
    :param start_speed: ``(n,)`` speed at the start [m/s]
    :param acceleration: largest acceleration of the reference [m/s^2], positive
    :param deceleration: largest deceleration of the reference [m/s^2], positive
    :return: ``(n, M)`` times [s] to reach ``start_arc + k * layout.ds``, ``k = 0..M-1``
        (``M`` covers the longest route; points past a route's end repeat its last limit)
    """
    if not (acceleration > 0 and deceleration > 0):
        raise ValueError(f"acceleration and deceleration must be positive, got {acceleration}, {deceleration}")
    route = np.asarray(route, np.int64)
    ds = float(layout.ds)
    samples = layout.speed_limit.shape[1]
    k = np.arange(samples)
    index = np.clip(((np.asarray(start_arc, float)[:, None] + k * ds) / ds).astype(np.int64), 0, samples - 1)
    cap2 = layout.speed_limit[route[:, None], index] ** 2  # (n, M)
    dist = k * ds
    brake = np.minimum.accumulate((cap2 + 2 * deceleration * dist)[:, ::-1], axis=1)[:, ::-1]
    brake -= 2 * deceleration * dist
    reach = np.minimum.accumulate(brake - 2 * acceleration * dist, axis=1)
    v0 = np.asarray(start_speed, float)[:, None] ** 2
    speed = np.sqrt(np.maximum(2 * acceleration * dist + np.minimum(v0, reach), 0.0))
    step = 2 * ds / np.maximum(speed[:, 1:] + speed[:, :-1], 1e-9)
    return np.concatenate([np.zeros((len(route), 1)), np.cumsum(step, axis=1)], axis=1)


def time_at(table: np.ndarray, distance: np.ndarray, ds: float) -> np.ndarray:
    """Interpolate :func:`free_flow_table` rows at a distance from each start.

    :param table: ``(n, M)`` cumulative times
    :param distance: ``(n,)`` metres from the start (clipped to the table; NaN stays NaN)
    :param ds: grid spacing [m]
    :return: ``(n,)`` times [s]
    """
    distance = np.asarray(distance, float)
    u = np.clip(np.nan_to_num(distance / ds), 0.0, table.shape[1] - 1.0)
    lo = np.minimum(u.astype(np.int64), table.shape[1] - 2)
    rows = np.arange(table.shape[0])
    t = table[rows, lo] + (u - lo) * (table[rows, lo + 1] - table[rows, lo])
    return np.where(np.isnan(distance), np.nan, t)
