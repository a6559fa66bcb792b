"""Static priority rules (PR): the baseline of today's intersections, as in the paper.

highway-env's driver model (IDM car following plus yielding at intersections) with the paper's
three tweaks:

1. a target speed of zero is handled correctly (:func:`envs.planners.idm.idm_acceleration`): a
   vehicle that yields gets target speed zero at its stop point and stays at rest there;
2. precedence comes from each vehicle's *intended maneuver* on its incoming road, not from the
   priority of the lane it is on right now;
3. a vehicle that yields does so at a stop point in front of the intersection: its front bumper
   comes to rest ``stop_margin`` metres before its stop line (default 0: at the line), see
   :func:`envs.planners.idm.stop_line_acceleration`.

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

from envs.planners.idm import crossing_times
from envs.planners.yielding import YieldingPlanner, rank_by
from envs.simulation.scene import LEFT, MAJOR, Scene


def maneuver_priority(priority: np.ndarray, maneuver: np.ndarray) -> np.ndarray:
    """Precedence class from road priority and intended maneuver (lower goes first).

    :param priority: ``(n,)`` ``MAJOR`` or ``MINOR``
    :param maneuver: ``(n,)`` ``LEFT``, ``STRAIGHT`` or ``RIGHT``
    :return: ``(n,)`` int64 in ``{0, 1, 2, 3}`` (see the module table)
    """
    return np.where(priority == MAJOR, 0, 2) + (maneuver == LEFT).astype(np.int64)


class PriorityRulesPlanner(YieldingPlanner):
    """Static priority rules with maneuver-inferred priorities and a stop point.

    :param name: the name shown in reports
    :param idm: IDM constants (default: highway-env's)
    :param crossing: timing rules of the yielding logic
    """

    default_name = "PR"

    def rank(self, scene: Scene) -> np.ndarray:
        """Maneuver-inferred precedence class, then the earliest possible arrival, then id."""
        arrival = crossing_times(scene, self.crossing)[0]
        return rank_by(maneuver_priority(scene.priority, scene.maneuver), arrival, scene.vehicle_id)
