"""Vectorized intelligent driver model (Treiber et al.) and the intersection helpers PR and FIFO share.

The constants are highway-env's (``highway_env.vehicle.behavior.IDMVehicle``), read from the class
and never written back: highway-env keeps them as class attributes, so changing them there would
change every IDM vehicle of the process.

The IDM acceleration of a vehicle with speed :math:`v`, target speed :math:`v_0`, gap :math:`s` and
leader speed :math:`v_l` is

.. math::
    a = a_{max} \\left(1 - (v / v_0)^\\delta - (s^*/s)^2\\right), \\quad
    s^* = s_0 + \\max\\left(0, vT + \\frac{v (v - v_l)}{2\\sqrt{a_{max} b}}\\right)

with two fixes against highway-env's implementation:

- **target speed zero** (paper, first tweak): highway-env divides by ``not_zero(v0)`` = 0.01, so a
  vehicle told to stand still brakes at the clipping limit while moving and *accelerates* at
  ``a_max`` once at rest. Here a target speed of zero means: brake comfortably to a standstill
  (never past it within the step) and stay there.
- the dynamic part of :math:`s^*` is clipped at zero (Treiber's definition), so a leader that
  pulls away quickly never makes the follower brake.

Gaps here are bumper to bumper (``Scene.gap``), so the jam distance is highway-env's
``DISTANCE_WANTED`` minus a vehicle length (highway-env measures centre to centre).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

from envs.simulation.scene import Scene


@dataclass(frozen=True)
class IDMParams:
    """IDM constants (defaults: highway-env's ``IDMVehicle``).

    :param acc_max: desired maximum acceleration :math:`a_{max}` [m/s^2]
    :param comfort_dec: desired deceleration :math:`b` [m/s^2], positive
    :param jam_distance: bumper-to-bumper jam distance :math:`s_0` [m]
    :param time_gap: desired time gap :math:`T` [s]
    :param delta: exponent :math:`\\delta` of the free-road term
    :param acc_limit: hard limit on the magnitude of the IDM output [m/s^2]
    """

    acc_max: float = IDMVehicle.COMFORT_ACC_MAX
    comfort_dec: float = -IDMVehicle.COMFORT_ACC_MIN
    jam_distance: float = IDMVehicle.DISTANCE_WANTED - Vehicle.LENGTH
    time_gap: float = IDMVehicle.TIME_WANTED
    delta: float = IDMVehicle.DELTA
    acc_limit: float = IDMVehicle.ACC_MAX


DEFAULT_IDM = IDMParams()


def idm_acceleration(
    speed: np.ndarray,
    target_speed: np.ndarray,
    gap: np.ndarray,
    leader_speed: np.ndarray,
    dt: float,
    params: IDMParams = DEFAULT_IDM,
) -> np.ndarray:
    """IDM acceleration of many vehicles at once.

    :param speed: ``(n,)`` own speed [m/s]
    :param target_speed: ``(n,)`` desired speed [m/s]; 0 means come to a stop and stay there
    :param gap: ``(n,)`` bumper-to-bumper gap to the obstacle ahead [m], ``inf`` if none
    :param leader_speed: ``(n,)`` speed of the obstacle ahead [m/s] (ignored where the gap is ``inf``)
    :param dt: how long the acceleration will be applied [s] (used so that a stop is not overshot)
    :param params: IDM constants
    :return: ``(n,)`` accelerations in ``[-params.acc_limit, params.acc_max]``
    """
    v = np.maximum(np.asarray(speed, dtype=float), 0.0)
    v0 = np.asarray(target_speed, dtype=float)
    gap = np.asarray(gap, dtype=float)
    moving_target = v0 > 1e-6
    free = np.where(
        moving_target,
        params.acc_max * (1.0 - np.power(v / np.where(moving_target, v0, 1.0), params.delta)),
        # target speed zero: comfortable braking, but never below a standstill within the step
        -np.minimum(params.comfort_dec, v / max(dt, 1e-6)),
    )
    has_leader = np.isfinite(gap)
    dv = v - np.where(has_leader, leader_speed, v)
    dynamic = v * params.time_gap + v * dv / (2.0 * np.sqrt(params.acc_max * params.comfort_dec))
    s_star = params.jam_distance + np.maximum(dynamic, 0.0)
    safe_gap = np.where(has_leader, np.maximum(gap, 1e-3), 1.0)
    interaction = np.where(has_leader, params.acc_max * (s_star / safe_gap) ** 2, 0.0)
    return np.clip(free - interaction, -params.acc_limit, params.acc_max)


def travel_time(distance: np.ndarray, speed: np.ndarray, v_max: np.ndarray, accel: float) -> np.ndarray:
    """Time to cover ``distance`` starting at ``speed``, accelerating at ``accel`` up to ``v_max``.

    :param distance: ``(n,)`` metres to cover (values <= 0 give 0)
    :param speed: ``(n,)`` current speed [m/s]
    :param v_max: ``(n,)`` speed that is never exceeded [m/s]
    :param accel: constant acceleration until ``v_max`` [m/s^2], positive
    :return: ``(n,)`` seconds
    """
    d = np.maximum(np.asarray(distance, dtype=float), 0.0)
    v = np.maximum(np.asarray(speed, dtype=float), 0.0)
    vmax = np.maximum(np.asarray(v_max, dtype=float), np.maximum(v, 0.1))
    d_acc = (vmax**2 - v**2) / (2.0 * accel)  # distance needed to reach v_max
    t_in_ramp = (np.sqrt(v**2 + 2.0 * accel * d) - v) / accel
    t_after = (vmax - v) / accel + (d - d_acc) / vmax
    return np.where(d <= d_acc, t_in_ramp, t_after)


def follow_leaders(scene: Scene, params: IDMParams = DEFAULT_IDM) -> np.ndarray:
    """IDM car following on every vehicle's path, with the lane's speed limit as target speed.

    :param scene: the vehicles now
    :param params: IDM constants
    :return: ``(n,)`` accelerations
    """
    leader = scene.leader
    leader_speed = np.where(leader >= 0, scene.speed[np.maximum(leader, 0)], 0.0) if leader.size else leader
    return idm_acceleration(scene.speed, scene.speed_limit, scene.gap, leader_speed, scene.dt, params)


def stop_line_acceleration(
    scene: Scene, margin: float = 0.0, params: IDMParams = DEFAULT_IDM, settle: float = 0.5
) -> np.ndarray:
    """IDM acceleration towards a stop point ``margin`` metres before each stop line.

    This is the paper's third tweak (yield at a stop point in front of the intersection), with its
    first (a target speed of zero): the stop point is a standing virtual obstacle placed the jam
    distance :math:`s_0` *beyond* it, so that IDM, which keeps :math:`s_0` to a standing obstacle,
    brings the front bumper to rest at the stop point rather than :math:`s_0` before it; within
    ``settle`` metres of the stop point the target speed is zero, so the vehicle settles there and
    stays at rest instead of creeping on.

    :param scene: the vehicles now
    :param margin: metres between the stopped front bumper and the stop line (0: at the line)
    :param params: IDM constants
    :param settle: metres before the stop point from which the target speed is zero
    :return: ``(n,)`` accelerations (meaningless for vehicles already past their stop line)
    """
    to_stop = scene.dist_to_entry - margin
    gap = np.maximum(to_stop, 0.0) + params.jam_distance
    target = np.where(to_stop <= settle, 0.0, scene.speed_limit)
    return idm_acceleration(scene.speed, target, gap, np.zeros_like(gap), scene.dt, params)


def leader_chain_max(values: np.ndarray, leader: np.ndarray, offset: float) -> np.ndarray:
    """``out[i] = max(values[i], out[leader[i]] + offset)`` along every chain of leaders.

    A follower cannot clear the intersection before its leader does; this propagates that bound
    by vectorized relaxation (one pass per vehicle of the longest chain).

    :param values: ``(n,)`` own estimates
    :param leader: ``(n,)`` row of the leader, -1 if none
    :param offset: added per link of the chain
    :return: ``(n,)`` propagated values
    """
    out = np.asarray(values, dtype=float).copy()
    has = leader >= 0
    if not has.any():
        return out
    src = np.maximum(leader, 0)
    for _ in range(len(out)):
        new = np.where(has, np.maximum(out, out[src] + offset), out)
        if np.array_equal(new, out):
            break
        out = new
    return out


@dataclass(frozen=True)
class CrossingParams:
    """Conservative timing rules shared by the intersection baselines.

    The conflict zone of two conflicting paths is the whole intersection area: a vehicle holds it
    from the moment its front passes the stop line until its rear has left the area.

    :param arrival_accel: acceleration assumed for the *earliest* arrival of another vehicle [m/s^2]
    :param clear_accel: acceleration assumed for the *latest* clearing of a vehicle [m/s^2]
    :param gap_margin: seconds between a higher-ranked vehicle's arrival and this vehicle's clearing
        required to go before it
    :param hold_margin: seconds between a vehicle in the intersection clearing it and this
        vehicle's arrival required to go
    :param commit_dec: a vehicle that would need more than this deceleration to stop before its
        stop line cannot stop any more: it goes, and others treat it as in the intersection [m/s^2]
    :param stop_margin: metres between a vehicle stopped at the stop point and the stop line (0: the
        front bumper stops at the line)
    :param follow_offset: seconds a follower needs after its leader has cleared
    """

    arrival_accel: float = IDMVehicle.COMFORT_ACC_MAX
    clear_accel: float = 2.0
    gap_margin: float = 1.0
    hold_margin: float = 0.5
    commit_dec: float = 4.0
    stop_margin: float = 0.0
    follow_offset: float = 0.5


def crossing_times(
    scene: Scene, params: CrossingParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Timing quantities of every vehicle for the yielding rules.

    :param scene: the vehicles now
    :param params: timing rules
    :return: ``(arrival, clearing, inside, committed)``: earliest time the front reaches the stop
        line [s] (0 once past it), latest time the rear leaves the intersection area [s], whether
        the vehicle is in the intersection area, whether it holds it (inside or unable to stop)
    """
    approaching = scene.dist_to_exit > 0
    inside = approaching & (scene.dist_to_entry <= 0)
    v = scene.speed
    stopping = v**2 / (2.0 * params.commit_dec) + v * scene.dt
    committed = inside | (approaching & (scene.dist_to_entry <= stopping))
    arrival = travel_time(scene.dist_to_entry, v, scene.speed_limit, params.arrival_accel)
    clearing = travel_time(scene.dist_to_exit, v, scene.speed_limit, params.clear_accel)
    clearing = leader_chain_max(clearing, scene.leader, params.follow_offset)
    return arrival, np.where(approaching, clearing, 0.0), inside, committed


def blocked_by_rank(
    scene: Scene,
    rank: np.ndarray,
    params: CrossingParams,
    passes: int = 4,
    times: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Which vehicles must wait at their stop point, given a precedence ``rank`` (lower goes first).

    Vehicle ``i`` (before its stop line, still able to stop) waits if some vehicle ``j`` on a
    conflicting route

    - holds the intersection (inside, or too close to stop) and will not have cleared it
      ``hold_margin`` seconds before ``i`` can arrive, or
    - ranks before ``i``, has not entered yet, and can arrive less than ``gap_margin`` seconds
      after ``i`` would have cleared.

    A vehicle cannot arrive before the vehicles ahead of it on its lane, and not at all while one
    of them waits: followers of a waiting vehicle are not counted as arriving. Without that, two
    queues whose heads wait for each other's followers block forever. Since who waits depends on
    who arrives, the rule is applied ``passes`` times (a few suffice: queues are short chains).

    All pairs at once: ``(n, n)`` boolean algebra, no loop per vehicle.

    :param scene: the vehicles now
    :param rank: ``(n,)`` precedence, lower first; ties must be broken by the caller
    :param params: timing rules
    :param passes: how often the waiting of leaders is fed back into the arrivals
    :param times: ``(arrival, clearing, inside, committed)`` as :func:`crossing_times` returns
        them (default: computed by it)
    :return: ``(n,)`` bool, True where the vehicle must stop at its stop point
    """
    n = scene.num_vehicles
    if n == 0:
        return np.zeros(0, dtype=bool)
    arrival, clearing, inside, committed = crossing_times(scene, params) if times is None else times
    arrival = leader_chain_max(arrival, scene.leader, 0.0)
    conflicts = np.asarray(scene.conflicts, dtype=bool).copy()
    np.fill_diagonal(conflicts, False)  # same route: plain car following
    pair = conflicts[scene.route[:, None], scene.route[None, :]]  # (i, j)
    pair &= ~np.eye(n, dtype=bool)
    approaching = scene.dist_to_exit > 0
    pair &= approaching[None, :]
    holds = (pair & committed[None, :] & (clearing[None, :] + params.hold_margin > arrival[:, None])).any(
        axis=1
    )
    deciding = approaching & ~committed
    earlier = pair & (rank[None, :] < rank[:, None]) & deciding[None, :]
    has_leader = scene.leader >= 0
    blocked = np.zeros(n, dtype=bool)
    for _ in range(passes):
        # 1.0 where some vehicle ahead in the queue waits: that vehicle's followers do not arrive
        held = leader_chain_max(blocked.astype(float), scene.leader, 0.0)
        queued = has_leader & (held[np.maximum(scene.leader, 0)] > 0)
        arrives = np.where(queued, np.inf, arrival)
        too_soon = (earlier & (arrives[None, :] < clearing[:, None] + params.gap_margin)).any(axis=1)
        new = deciding & (holds | too_soon)
        if np.array_equal(new, blocked):
            break
        blocked = new
    return blocked


def accelerations_with_stops(
    scene: Scene, blocked: np.ndarray, crossing: CrossingParams, idm: IDMParams = DEFAULT_IDM
) -> np.ndarray:
    """IDM car following, plus a standing obstacle at the stop point of the blocked vehicles.

    :param scene: the vehicles now
    :param blocked: ``(n,)`` bool from :func:`blocked_by_rank`
    :param crossing: timing rules (for the stop margin)
    :param idm: IDM constants
    :return: ``(n,)`` accelerations clipped to ``[scene.a_min, scene.a_max]``
    """
    acc = follow_leaders(scene, idm)
    if blocked.any():
        acc = np.where(
            blocked, np.minimum(acc, stop_line_acceleration(scene, crossing.stop_margin, idm)), acc
        )
    return np.clip(acc, scene.a_min, scene.a_max)
