"""Who is committed: the vehicles that braking at ``a_max`` can no longer stop before their first
conflict zone, or that have left their last one.

A fact of the simulation's state and layout, read by the observation's ``committed`` vertex feature
(:mod:`envs.simulation.graph`) and by the safety shield (:mod:`envs.planners.shield`, whose compiled
kernels call :func:`can_stop` and :func:`is_committed`), so that both apply one rule. Compiled with
numba (``cache=True``), as the shield's kernels that call it. numba's cache does not see a change to a
function called from another file: after editing a kernel here, delete the cached machine code of
:mod:`envs.planners._shield_kernel` (``envs/planners/__pycache__/_shield_kernel*.nb[ci]``).
"""

from __future__ import annotations

import numba
import numpy as np

from envs.simulation.layouts import ZONE_MARGIN, body_hull
from envs.simulation.scene import Scene

# A vehicle counts as standing below this speed [m/s] (speeds are clipped to exactly 0 when braking).
STANDING = 1e-6
# Slack on "can stop before the zone" [m]: the simulation's trapezoid integration overshoots the
# exact stopping distance by at most ``a_max * h^2 / 8`` (4 mm at 15 Hz).
STOP_SLACK = 0.05


@numba.njit(cache=True)
def can_stop(arc: float, speed: float, line: float, a_max: float, standing: float, slack: float) -> bool:
    """Whether braking at ``a_max`` stops a vehicle's centre at or before ``line``.

    A standing vehicle outside the line can always wait (the slack is for moving ones only).
    """
    return arc <= line and (speed <= standing or arc + speed * speed / (2 * a_max) + slack <= line)


@numba.njit(cache=True)
def is_committed(
    arc: float, speed: float, hull_start: float, hull_end: float, a_max: float, standing: float, slack: float
) -> bool:
    """``committed`` of one vehicle: it can no longer stop before its first zone, or has cleared them all."""
    return not can_stop(arc, speed, hull_start, a_max, standing, slack) or arc > hull_end


@numba.njit(cache=True)
def committed_rows(
    arc: np.ndarray,
    speed: np.ndarray,
    hull_start: np.ndarray,
    hull_end: np.ndarray,
    a_max: float,
    standing: float,
    slack: float,
) -> np.ndarray:
    """``(n,)`` bool ``committed`` of vehicles given their hulls, without a plan (the observation)."""
    go = np.zeros(arc.shape[0], np.bool_)
    for i in range(arc.shape[0]):
        go[i] = is_committed(arc[i], speed[i], hull_start[i], hull_end[i], a_max, standing, slack)
    return go


def committed_vehicles(scene: Scene, zone_margin: float = ZONE_MARGIN) -> np.ndarray:
    """``(n,)`` bool: the vehicles of a scene that can no longer stop before their first conflict zone,
    or have left their last one (:meth:`envs.planners.shield.Shield.committed`, from the scene alone).

    :param scene: a scene with its layout and arcs
    :param zone_margin: padding of every zone [m] (the shield's default)
    """
    hull_start, hull_end = body_hull(scene.layout, scene.route, scene.length, zone_margin)
    return committed_rows(
        np.ascontiguousarray(scene.arc, dtype=float),
        np.ascontiguousarray(scene.speed, dtype=float),
        np.ascontiguousarray(hull_start, dtype=float),
        np.ascontiguousarray(hull_end, dtype=float),
        float(scene.a_max),
        STANDING,
        STOP_SLACK,
    )
