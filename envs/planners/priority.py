"""A priority policy: a learned planner whose output shifts the arrival order of glide's scheduler.

A policy trained with the intersection environments' ``"action": {"type": "priority"}`` outputs one
score per vehicle in ``[-1, 1]``; ``scale`` seconds per unit are added to the vehicle's arrival key in
:class:`~envs.planners.glide.GlidePlanner`'s order (lower goes earlier), and glide turns the order into
approach profiles and accelerations. A policy file trained so carries ``action`` in its header's
planner configuration (``sb3-graph export --planner-config``), and ``make_planner`` wraps it in this
class; ``+shield`` puts the shield behind it, as in training with ``shield``.
"""

from __future__ import annotations

import math

import numpy as np

from envs.planners.base import Planner
from envs.planners.glide import GlidePlanner
from envs.simulation.scene import Scene


class PriorityPlanner(Planner):
    """Glide's accelerations, with its order shifted by a scoring planner's output.

    :param scheduler: the scheduler whose order the scores shift
    :param scores: the learned planner; its command over ``scene.a_max`` is the score in ``[-1, 1]``
    :param scale: seconds of arrival key per unit of score, in ``(0, 3600]`` (as ``action``'s ``scale`` in training)
    :param name: report name (default: ``<scores>@<scheduler>``)
    """

    def __init__(self, scheduler: GlidePlanner, scores: Planner, scale: float, name: str | None = None) -> None:
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and 0 < scale <= 3600):
            raise ValueError(f"priority scale must be a number in (0, 3600], got {scale!r}")
        super().__init__(name or f"{scores.name}@{scheduler.name}")
        self.scheduler = scheduler
        self.scores = scores
        self.scale = float(scale)

    def reset(self, seed: int | None = None) -> None:
        self.scheduler.reset(seed)
        self.scores.reset(seed)

    def act(self, scene: Scene) -> np.ndarray:
        n = scene.num_vehicles
        score = np.asarray(self.scores.act(scene), dtype=float).reshape(n) / scene.a_max
        self.scheduler.set_priority(self.scale * np.clip(score, -1.0, 1.0))
        return self.scheduler.act(scene)
