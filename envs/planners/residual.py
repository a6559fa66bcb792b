"""A residual planner: a base planner's command plus a learned, bounded correction.

``a_i = clip(base_i + scale * correction_i, a_min, a_max)``, where ``correction_i`` is the learned
planner's own command (its action times ``a_max``). A zero correction reproduces the base planner
exactly, so a residual policy starts where its base planner is and learns only what improves on it.
It is what the environment applies with ``residual_base`` and ``residual_scale`` in training
(:class:`envs.simulation.env.CoopIntersectionEnv`); a policy file trained that way carries both
in its header (``sb3-graph export --planner-config``), and ``make_planner`` wraps it in this class.
"""

from __future__ import annotations

import math

import numpy as np

from envs.planners.base import Planner
from envs.simulation.scene import Scene


class ResidualPlanner(Planner):
    """``base + scale * correction``, clipped to the scene's bounds (see the module docstring).

    :param base: the planner whose command is corrected
    :param correction: the learned planner (its command in m/s^2 is the correction before scaling)
    :param scale: the correction's weight, in ``(0, 2]`` (as ``residual_scale`` in training)
    :param name: report name (default: ``<correction>@<base>``)
    """

    def __init__(self, base: Planner, correction: Planner, scale: float, name: str | None = None) -> None:
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and 0 < scale <= 2):
            raise ValueError(f"residual_scale must be a number in (0, 2], got {scale!r}")
        super().__init__(name or f"{correction.name}@{base.name}")
        self.base = base
        self.correction = correction
        self.scale = float(scale)

    def reset(self, seed: int | None = None) -> None:
        self.base.reset(seed)
        self.correction.reset(seed)

    def act(self, scene: Scene) -> np.ndarray:
        n = scene.num_vehicles
        base = np.asarray(self.base.act(scene), dtype=float).reshape(n)
        correction = np.asarray(self.correction.act(scene), dtype=float).reshape(n)
        return np.clip(base + self.scale * correction, scene.a_min, scene.a_max)

