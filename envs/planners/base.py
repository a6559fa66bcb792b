"""The one face every planner shows: given the scene, one acceleration per vehicle."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from envs.simulation.scene import Scene

if TYPE_CHECKING:
    from envs.planners.errors import PlannerError


class Planner(ABC):
    """A behaviour planner for every vehicle in the scene at once.

    The evaluation harness, the inD replay and an edge server call it the same way: ``reset``
    once per episode, then ``act`` once per policy step.

    :param name: the name shown in reports
    """

    #: Planner errors that this planner answered itself during the episode (a shield answers its
    #: planner's with the fallback), the first few; the evaluation reports their lines next to
    #: :meth:`stats`. None by default.
    errors: Sequence[PlannerError] = ()

    def __init__(self, name: str) -> None:
        self.name = name

    def reset(self, seed: int | None = None) -> None:
        """Forget everything about the previous episode.

        :param seed: seed for any randomness of the planner
        """
        return None

    @abstractmethod
    def act(self, scene: Scene) -> np.ndarray:
        """Commanded longitudinal accelerations.

        :param scene: the vehicles now
        :return: ``(scene.num_vehicles,)`` float accelerations in ``[scene.a_min, scene.a_max]`` m/s^2
        """

    def stats(self) -> dict[str, float]:
        """Counters of the episode since the last :meth:`reset`, reported with the run's metrics.

        The evaluation adds each key as a ``metrics.csv`` column of the run (a shield reports
        ``shield_interventions``, ``shield_vehicle_steps``, ``shield_unresolved`` and
        ``planner_errors``). None by default.

        :return: ``counter name -> value``
        """
        return {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"
