"""Time-parametrised speed profiles from the vehicle model, for planners that schedule crossings.

The simulation's vehicle moves along its path with the commanded acceleration (at most ``a_max``)
under the speed governor: never above the braking envelope of the lane limits ahead
(:meth:`envs.simulation.layouts.Layout.envelope_at`). The profiles here use the same model, vectorized over
vehicles (and candidate plans), with closed forms per phase:

- the *earliest arrival* at the stop line: accelerate, cruise at the road's limit, brake at the
  governor's deceleration to the envelope's speed at the line (:func:`earliest_arrival`);
- the *crossing*: from the stop line with a given speed, accelerate up to the lowest limit inside
  the intersection (:func:`envs.planners.idm.travel_time`, with :func:`inner_limit`).
"""

from __future__ import annotations

import numpy as np

from envs.planners.idm import CrossingParams, leader_chain_max, travel_time
from envs.simulation.layouts import Layout

_INNER_LIMITS: dict[int, np.ndarray] = {}


def inner_limit(layout: Layout) -> np.ndarray:
    """``(R,)`` lowest lane limit of each route between its stop line and its intersection exit [m/s].

    Computed once per layout (layouts are built once per process and read-only).
    """
    key = id(layout)
    if key not in _INNER_LIMITS:
        arcs = np.arange(layout.speed_limit.shape[1]) * layout.ds
        inside = (arcs[None, :] >= layout.entry_arc[:, None]) & (arcs[None, :] <= layout.exit_arc[:, None])
        _INNER_LIMITS[key] = np.where(inside, layout.speed_limit, np.inf).min(axis=1)
    return _INNER_LIMITS[key]


def line_speed(scene, governor_deceleration: float) -> np.ndarray:
    """``(n,)`` highest speed the governor allows with the front bumper at the stop line [m/s]."""
    lay = scene.layout
    return lay.envelope_at(scene.route, lay.entry_arc[scene.route] - scene.length / 2, governor_deceleration)


def earliest_arrival(
    distance: np.ndarray,
    speed: np.ndarray,
    line_speed: np.ndarray,
    road_speed: np.ndarray,
    accel: float,
    decel: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fastest way to cover ``distance``: accelerate, cruise at ``road_speed``, brake to ``line_speed``.

    :param distance: ``(...)`` metres to the stop line (values <= 0 give time 0)
    :param speed: current speed [m/s]
    :param line_speed: highest speed allowed at the line [m/s]
    :param road_speed: highest speed before it [m/s]
    :param accel: acceleration [m/s^2], positive
    :param decel: deceleration of the final braking [m/s^2], positive
    :return: ``(time, speed at the line, peak speed)``; the speed at the line is lower than
        ``line_speed`` when the distance is too short to reach it
    """
    d = np.maximum(distance, 0.0)
    v = np.maximum(speed, 0.0)
    w = np.minimum(line_speed, np.sqrt(v**2 + 2.0 * accel * d))
    w = np.maximum(w, np.sqrt(np.maximum(v**2 - 2.0 * decel * d, 0.0)))  # too fast to brake to line_speed
    peak_sq = (2.0 * accel * decel * d + decel * v**2 + accel * w**2) / (accel + decel)
    peak = np.maximum(np.minimum(np.sqrt(peak_sq), np.maximum(road_speed, v)), np.maximum(v, w))
    d_acc = (peak**2 - v**2) / (2.0 * accel)
    d_dec = (peak**2 - w**2) / (2.0 * decel)
    cruise = np.maximum(d - d_acc - d_dec, 0.0)
    time = (peak - v) / accel + (peak - w) / decel + cruise / np.maximum(peak, 1e-6)
    return np.where(d > 0, time, 0.0), np.where(d > 0, w, v), peak


def model_crossing_times(
    scene, params: CrossingParams, governor_deceleration: float = 3.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`envs.planners.idm.crossing_times` from the vehicle model instead of fixed rules.

    The arrival is the earliest one under the lane limits (accelerating at ``arrival_accel``,
    braking for a turn's limit at the governor's deceleration); the clearing adds the time the
    rear needs to leave the intersection area from the line at ``clear_accel``, up to the lowest
    limit inside; a follower clears ``follow_offset`` seconds after its leader at the earliest.

    :param scene: the vehicles now (with its layout)
    :param params: timing rules
    :param governor_deceleration: the simulation's governor deceleration [m/s^2]
    :return: ``(arrival, clearing, inside, committed)`` as ``crossing_times`` returns them
    """
    v, dist = scene.speed, scene.dist_to_entry
    approaching = scene.dist_to_exit > 0
    inside = approaching & (dist <= 0)
    stopping = v**2 / (2.0 * params.commit_dec) + v * scene.dt
    committed = inside | (approaching & (dist <= stopping))
    v_line = line_speed(scene, governor_deceleration)
    v_road = np.maximum(scene.speed_limit, v)
    arrival, w, _ = earliest_arrival(dist, v, v_line, v_road, params.arrival_accel, governor_deceleration)
    crossing = scene.dist_to_exit - np.maximum(dist, 0.0)  # front from the line (or from now) to rear out
    clearing = arrival + travel_time(crossing, w, inner_limit(scene.layout)[scene.route], params.clear_accel)
    clearing = leader_chain_max(clearing, scene.leader, params.follow_offset)
    return arrival, np.where(approaching, clearing, 0.0), inside, committed
