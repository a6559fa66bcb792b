"""Static priority rules (PR): the baseline of today's intersections, as in the paper.

highway-env's driver model (IDM car following plus yielding at intersections) with the paper's
three tweaks:

1. a target speed of zero is handled correctly (:func:`envs.planners.idm.idm_acceleration`);
2. precedence comes from each vehicle's *intended maneuver* on its incoming road, not from the
   priority of the lane it is on right now;
3. a vehicle that yields does so at a stop point in front of the intersection, modelled as a
   standing virtual obstacle ``stop_margin`` metres before its stop line.

Precedence order (lower goes first), ties broken by the earliest possible arrival, then by id:

====  ==========================
rank  incoming road, maneuver
====  ==========================
0     major, straight or right
1     major, left (yields to oncoming major traffic)
2     minor, straight or right
3     minor, left
====  ==========================
"""

from __future__ import annotations

import numpy as np

from envs.planners.base import Planner
from envs.planners.idm import (
    DEFAULT_IDM,
    CrossingParams,
    IDMParams,
    accelerations_with_stops,
    blocked_by_rank,
    crossing_times,
)
from envs.scene import LEFT, MAJOR, Scene


def maneuver_priority(priority: np.ndarray, maneuver: np.ndarray) -> np.ndarray:
    """Precedence class from road priority and intended maneuver (lower goes first).

    :param priority: ``(n,)`` ``MAJOR`` or ``MINOR``
    :param maneuver: ``(n,)`` ``LEFT``, ``STRAIGHT`` or ``RIGHT``
    :return: ``(n,)`` int64 in ``{0, 1, 2, 3}`` (see the module table)
    """
    return np.where(priority == MAJOR, 0, 2) + (maneuver == LEFT).astype(np.int64)


def precedence_rank(klass: np.ndarray, arrival: np.ndarray, vehicle_id: np.ndarray) -> np.ndarray:
    """Dense rank by ``(klass, arrival, vehicle_id)``, lower first.

    :param klass: ``(n,)`` primary key
    :param arrival: ``(n,)`` secondary key
    :param vehicle_id: ``(n,)`` final tie-break
    :return: ``(n,)`` int64 rank
    """
    order = np.lexsort((vehicle_id, arrival, klass))
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    return rank


class PriorityRulesPlanner(Planner):
    """Static priority rules with maneuver-inferred priorities and a stop point.

    :param name: the name shown in reports
    :param idm: IDM constants (default: highway-env's)
    :param crossing: timing rules of the yielding logic
    """

    def __init__(
        self, name: str = "PR", idm: IDMParams = DEFAULT_IDM, crossing: CrossingParams | None = None
    ) -> None:
        super().__init__(name)
        self.idm = idm
        self.crossing = crossing if crossing is not None else CrossingParams()

    def blocked(self, scene: Scene) -> np.ndarray:
        """``(n,)`` bool: vehicles that must wait at their stop point now."""
        arrival = crossing_times(scene, self.crossing)[0]
        rank = precedence_rank(maneuver_priority(scene.priority, scene.maneuver), arrival, scene.vehicle_id)
        return blocked_by_rank(scene, rank, self.crossing)

    def act(self, scene: Scene) -> np.ndarray:
        if scene.num_vehicles == 0:
            return np.zeros(0)
        return accelerations_with_stops(scene, self.blocked(scene), self.crossing, self.idm)
