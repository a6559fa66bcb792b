"""Planners that ignore everyone else: the hard cases for the safety shield (:mod:`envs.planners.shield`).

Run them on the command line by class name, e.g.
``sb3-graph evaluate --planner envs/planners/adversarial.py:FullThrottle --shield``.
"""

from __future__ import annotations

import numpy as np

from envs.planners.base import Planner
from envs.simulation.scene import Scene


class FullThrottle(Planner):
    """Every vehicle always commands the largest acceleration.

    :param name: the name shown in reports
    """

    def __init__(self, name: str = "FullThrottle") -> None:
        super().__init__(name)

    def act(self, scene: Scene) -> np.ndarray:
        return np.full(scene.num_vehicles, float(scene.a_max))


class RandomAccel(Planner):
    """Every vehicle commands an acceleration drawn uniformly from ``[a_min, a_max]`` each step.

    :param name: the name shown in reports
    :param seed: seed used when :meth:`reset` gets none
    """

    def __init__(self, name: str = "RandomAccel", seed: int = 0) -> None:
        super().__init__(name)
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(self.seed if seed is None else seed)

    def act(self, scene: Scene) -> np.ndarray:
        return self.rng.uniform(scene.a_min, scene.a_max, scene.num_vehicles)
