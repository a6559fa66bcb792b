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

from envs.planners.yielding import YieldingPlanner, rank_by
from envs.scene import Scene


class FIFOPlanner(YieldingPlanner):
    """FIFO over groups of conflicting paths, IDM car following.

    :param name: the name shown in reports
    :param idm: IDM constants (default: highway-env's)
    :param crossing: timing rules of the admission logic
    """

    default_name = "FIFO"

    def rank(self, scene: Scene) -> np.ndarray:
        """Closest to the stop line first, ties by id."""
        return rank_by(scene.dist_to_entry, scene.vehicle_id)
