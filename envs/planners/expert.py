"""Any planner as an expert for :func:`sb3_graph.behaviour_clone` on the intersection environments.

A planner reads the scene, not the graph observation, so the expert asks each sub-environment of the
VecEnv for its scene (``env_method("scene")``) and its step counter, keeps one planner per
sub-environment (``reset`` when that sub-environment starts an episode), and turns the planner's
accelerations into the environment's action:

- ``a / max_acceleration``, clipped to ``[-1, 1]`` (the environment applies ``action * max_acceleration``);
- with the environment's ``residual_base``, the correction that reproduces the planner's
  accelerations: ``(a - base) / (residual_scale * max_acceleration)``, clipped to ``[-1, 1]`` (the base
  is a planner of its own per sub-environment, fed the same scenes as the environment's copy);
- with the environment's ``shield``, the planner's own proposal: the environment shields whatever the
  policy proposes, so the policy learns to propose what the planner proposes (a word ending in
  ``+shield`` labels with the shielded command instead).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from envs.planners import make_planner
from envs.planners.residual import make_residual_base


class PlannerExpert:
    """``expert(obs) -> (n_envs, max_vehicles)`` actions of a planner, for every sub-environment of a VecEnv.

    Call it exactly once per VecEnv state, before the step (as ``behaviour_clone`` does): planners keep
    state within an episode (AIM's reservations, FIFO's order).

    :param spec: a planner word of :func:`envs.planners.make_planner` (``"aim"``, ``"fifo"``, ``"pr"``,
        ``"fullthrottle"``, a class spec ``file.py:Class``, a policy file...)
    :param vec_env: an SB3 VecEnv of intersection environments
    :param trust_files: passed to :func:`~envs.planners.make_planner`
    """

    def __init__(self, spec: str, vec_env: Any, trust_files: bool = False) -> None:
        self.spec = spec
        self.vec_env = vec_env
        n_envs = vec_env.num_envs
        self.planners = [make_planner(spec, trust_files=trust_files) for _ in range(n_envs)]
        configs = vec_env.get_attr("config")
        self.max_acceleration = np.array([c["max_acceleration"] for c in configs], dtype=np.float64)
        self.residual_scale = np.array([c["residual_scale"] for c in configs], dtype=np.float64)
        self.bases = [make_residual_base(c["residual_base"]) for c in configs]
        self.max_nodes = int(vec_env.action_space.shape[0])
        self._last_step = [-1] * n_envs

    def __call__(self, obs: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """The planner's actions for the sub-environments' current scenes.

        :param obs: the VecEnv's observation (unused: the scenes are read from the environments)
        :return: ``(n_envs, max_vehicles)`` float32 actions in ``[-1, 1]``, 0 in padded slots
        """
        scenes = self.vec_env.env_method("scene")
        steps = self.vec_env.get_attr("steps")
        actions = np.zeros((len(scenes), self.max_nodes), dtype=np.float32)
        for i, scene in enumerate(scenes):  # one planner call per sub-environment
            if steps[i] == 0 or steps[i] <= self._last_step[i]:  # a new episode
                self.planners[i].reset()
                if self.bases[i] is not None:
                    self.bases[i].reset()
            self._last_step[i] = steps[i]
            actions[i, : scene.num_vehicles] = self._action(i, scene, self.planners[i].act(scene))
        return actions

    def _action(self, i: int, scene: Any, acc: np.ndarray) -> np.ndarray:
        acc = np.asarray(acc, dtype=np.float64).reshape(scene.num_vehicles)
        a_max = self.max_acceleration[i]
        if self.bases[i] is None:
            return np.clip(acc / a_max, -1.0, 1.0)
        base = np.asarray(self.bases[i].act(scene), dtype=np.float64).reshape(scene.num_vehicles)
        return np.clip((acc - base) / (self.residual_scale[i] * a_max), -1.0, 1.0)


def make_expert(spec: str, vec_env: Any) -> PlannerExpert:
    """The ``sb3_graph.experts`` entry point of the intersection domain (``--pretrain-from PLANNER``).

    :raises ValueError: an unknown planner word, naming the accepted ones
    """
    return PlannerExpert(spec, vec_env)
