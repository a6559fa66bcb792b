"""First in, first out per group of conflicting paths (FIFO), the paper's AIM-like baseline.

Vehicles are ordered by their distance to the intersection (closest first). A vehicle may enter
when no earlier vehicle on a *conflicting* path holds or is about to take the intersection
(see :func:`envs.planners.idm.blocked_by_rank`); vehicles on paths that do not conflict go at
the same time, so the order is strict only within groups of conflicting paths, not over the
whole intersection. Otherwise it waits at the stop point (a standing virtual obstacle before
its stop line). Car following is IDM.
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
)
from envs.scene import Scene


def fifo_rank(dist_to_entry: np.ndarray, vehicle_id: np.ndarray) -> np.ndarray:
    """Rank by distance to the stop line (closest first), ties by id.

    :param dist_to_entry: ``(n,)`` metres to the stop line
    :param vehicle_id: ``(n,)`` tie-break
    :return: ``(n,)`` int64 rank, lower first
    """
    order = np.lexsort((vehicle_id, dist_to_entry))
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    return rank


class FIFOPlanner(Planner):
    """FIFO over groups of conflicting paths, IDM car following.

    :param name: the name shown in reports
    :param idm: IDM constants (default: highway-env's)
    :param crossing: timing rules of the admission logic
    """

    def __init__(
        self, name: str = "FIFO", idm: IDMParams = DEFAULT_IDM, crossing: CrossingParams | None = None
    ) -> None:
        super().__init__(name)
        self.idm = idm
        self.crossing = crossing if crossing is not None else CrossingParams()

    def blocked(self, scene: Scene) -> np.ndarray:
        """``(n,)`` bool: vehicles that must wait at their stop point now."""
        return blocked_by_rank(scene, fifo_rank(scene.dist_to_entry, scene.vehicle_id), self.crossing)

    def act(self, scene: Scene) -> np.ndarray:
        if scene.num_vehicles == 0:
            return np.zeros(0)
        return accelerations_with_stops(scene, self.blocked(scene), self.crossing, self.idm)
