"""A scheduling policy: a learned planner whose output drives glide's scheduler.

A policy trained with the intersection environments' ``"action": {"type": "priority"}`` or
``{"type": "advice"}`` outputs one score per vehicle in ``[-1, 1]``:

- ``"priority"``: ``scale`` seconds per unit are added to the vehicle's arrival key in
  :class:`~envs.planners.glide.GlidePlanner`'s order (lower goes earlier);
- ``"advice"``: ``scale`` metres per unit are added to glide's advice window for that vehicle (the
  distance from its line within which it follows its slot; never below 0, where it drives at full throttle).

Glide turns the order and the windows into approach profiles and accelerations. A policy file trained
so carries ``action`` in its header's planner configuration (``sb3-graph export --planner-config``),
and ``make_planner`` wraps it in this class; ``+shield`` puts the shield behind it, as in training
with ``shield``.
"""

from __future__ import annotations

import math

import numpy as np

from envs.planners.base import Planner
from envs.planners.glide import GlidePlanner
from envs.simulation.config import SCHEDULER_ACTION_TYPES
from envs.simulation.scene import Scene


class PriorityPlanner(Planner):
    """Glide's accelerations, with its order (``"priority"``) or its advice windows (``"advice"``)
    moved by a scoring planner's output.

    :param scheduler: the scheduler that the scores drive
    :param scores: the learned planner; its command over ``scene.a_max`` is the score in ``[-1, 1]``
    :param scale: seconds of arrival key (priority) or metres of advice window (advice) per unit of
        score, in ``(0, 3600]`` (as ``action``'s ``scale`` in training)
    :param name: report name (default: ``<scores>@<scheduler>``)
    :param kind: ``"priority"`` or ``"advice"`` (``action``'s ``type`` in training)
    :param critic_gate: ``None``, or a margin >= 0: the scores are used in a scene only where the scoring planner's
        critics value them above the zero action (glide alone) by more than it (``scores`` must then offer
        ``critic_gain``, as :class:`~envs.planners.gnn.GNNPlanner` does); the run's ``gate_open_steps`` and
        ``gate_steps`` count how often
    """

    def __init__(
        self,
        scheduler: GlidePlanner,
        scores: Planner,
        scale: float,
        name: str | None = None,
        kind: str = "priority",
        critic_gate: float | None = None,
    ) -> None:
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and 0 < scale <= 3600):
            raise ValueError(f"priority scale must be a number in (0, 3600], got {scale!r}")
        if kind not in SCHEDULER_ACTION_TYPES:
            raise ValueError(f"scheduling policy kind must be one of {list(SCHEDULER_ACTION_TYPES)}, got {kind!r}")
        super().__init__(name or f"{scores.name}@{scheduler.name}")
        self.scheduler = scheduler
        self.scores = scores
        self.scale = float(scale)
        self.kind = kind
        if critic_gate is not None and not (math.isfinite(critic_gate) and critic_gate >= 0):
            raise ValueError(f"critic_gate must be None or a number >= 0, got {critic_gate!r}")
        self.critic_gate = critic_gate
        self.gate_steps = self.gate_open_steps = 0

    def reset(self, seed: int | None = None) -> None:
        self.scheduler.reset(seed)
        self.scores.reset(seed)
        self.gate_steps = self.gate_open_steps = 0

    def stats(self) -> dict[str, float]:
        """With a critic gate: the steps planned and those in which the scores were used."""
        if self.critic_gate is None:
            return {}
        return {"gate_steps": self.gate_steps, "gate_open_steps": self.gate_open_steps}

    def offsets(self, scene: Scene) -> np.ndarray:
        """The scoring planner's scores for ``scene``, in ``[-1, 1]``, times ``scale``: what :meth:`act` hands the
        scheduler (seconds of arrival key, or metres of advice window).

        :return: ``(n,)`` offsets
        """
        n = scene.num_vehicles
        if self.critic_gate is not None:
            if n == 0:
                return np.zeros(0)
            score, gain = self.scores.critic_gain(scene)
            self.gate_steps += 1
            if gain <= self.critic_gate:  # the critics see no gain over glide's own plan: glide plans alone
                return np.zeros(n)
            self.gate_open_steps += 1
            return self.scale * score
        score = np.clip(np.asarray(self.scores.act(scene), dtype=float).reshape(n) / scene.a_max, -1.0, 1.0)
        return self.scale * score

    def act(self, scene: Scene) -> np.ndarray:
        self.scheduler.set_scores(self.kind, self.offsets(scene))  # as the environment's action does
        return self.scheduler.act(scene)
