"""What PR and FIFO share: an order of precedence, yielding at the stop point, IDM car following."""

from __future__ import annotations

from abc import abstractmethod

import numpy as np

from envs.planners.base import Planner
from envs.planners.idm import (
    DEFAULT_IDM,
    CrossingParams,
    IDMParams,
    accelerations_with_stops,
    blocked_by_rank,
)
from envs.simulation.scene import Scene


def rank_by(*keys: np.ndarray) -> np.ndarray:
    """Rank of each row by ``keys``, the first key most significant, lower first.

    :param keys: ``(n,)`` arrays; put a unique key (e.g. the vehicle id) last to break ties
    :return: ``(n,)`` int64 rank in ``[0, n)``
    """
    order = np.lexsort(keys[::-1])  # lexsort takes the most significant key last
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    return rank


class YieldingPlanner(Planner):
    """A planner that lets vehicles enter the intersection in an order of precedence.

    A vehicle waits at its stop point while one of lower rank on a conflicting path holds or is
    about to take the intersection (:func:`envs.planners.idm.blocked_by_rank`); otherwise it
    follows its leader with IDM.

    :param name: the name shown in reports (default: the class's ``default_name``)
    :param idm: IDM constants (default: highway-env's)
    :param crossing: timing rules of the yielding logic
    """

    default_name: str = "yielding"

    def __init__(
        self, name: str | None = None, idm: IDMParams = DEFAULT_IDM, crossing: CrossingParams | None = None
    ) -> None:
        super().__init__(name if name is not None else self.default_name)
        self.idm = idm
        self.crossing = crossing if crossing is not None else CrossingParams()

    @abstractmethod
    def rank(self, scene: Scene) -> np.ndarray:
        """``(n,)`` int64 order of precedence, lower goes first."""

    def blocked(self, scene: Scene) -> np.ndarray:
        """``(n,)`` bool: vehicles that must wait at their stop point now."""
        return blocked_by_rank(scene, self.rank(scene), self.crossing)

    def act(self, scene: Scene) -> np.ndarray:
        if scene.num_vehicles == 0:
            return np.zeros(0)
        return accelerations_with_stops(scene, self.blocked(scene), self.crossing, self.idm)
