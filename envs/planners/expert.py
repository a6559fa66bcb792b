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

With the environment's ``action`` type ``"priority"`` or ``"advice"`` an action is a score per vehicle
that shifts the arrival order of glide's scheduler or moves its advice window, not an acceleration.
``glide`` is the one planner with an exact score: zero for every vehicle (the environment then drives
exactly as ``glide``, shielded with ``shield``; ``glide+shield`` is exact only with ``shield`` on).
``lookahead`` (:mod:`envs.planners.lookahead`) chooses glide's advice windows by search: with ``"advice"``
its label is the score that moves each vehicle's window to the one it chose, ``(window - glide's
window) / scale`` clipped to ``[-1, 1]`` (the whole approach: +1), searched from the memory of the
environment's own scheduler (its order and the advice it already holds), with the action's ``glide``
parameters. A class spec (``file.py:Class``) of a :class:`~envs.planners.lookahead.LookaheadPlanner` over the
same glide labels so too: a search with a learned proposer (``scripts/lookahead_variants.py:WithStudent``) is the
teacher of the next round of expert iteration. No score reproduces another planner's accelerations (they come
from another order *and* other profiles), so any other planner is refused.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from envs.planners import SHIELD_SUFFIX, check_planner_spec, make_planner, make_residual_base
from envs.planners.glide import GLIDE_VERSIONS
from envs.planners.loading import is_class_spec
from envs.planners.lookahead import LookaheadPlanner
from envs.simulation.config import SCHEDULER_ACTION_TYPES

#: The planner whose exact label, with the ``"priority"`` and ``"advice"`` action types, is the zero score.
PRIORITY_PLANNER = "glide"
#: The planner whose label, with the ``"advice"`` action type, is the window its search chose.
SEARCH_PLANNER = "lookahead"


class PlannerExpert:
    """``expert(obs) -> (n_envs, max_vehicles)`` actions of a planner, for every sub-environment of a VecEnv.

    Call it exactly once per VecEnv state, before the step (as ``behaviour_clone`` does): planners keep
    state within an episode (AIM's reservations, FIFO's order).

    :param spec: a planner word of :func:`envs.planners.make_planner` (``"aim"``, ``"fifo"``, ``"pr"``,
        ``"fullthrottle"``, a class spec ``file.py:Class``, a policy file...)
    :param vec_env: an SB3 VecEnv of intersection environments
    :param trust_files: passed to :func:`~envs.planners.make_planner`
    :raises ValueError: with the ``"priority"`` or ``"advice"`` action type, a planner other than ``glide`` (one line)
    """

    def __init__(self, spec: str, vec_env: Any, trust_files: bool = False) -> None:
        self.spec = spec
        self.vec_env = vec_env
        n_envs = vec_env.num_envs
        configs = vec_env.get_attr("config")
        self.max_nodes = int(vec_env.action_space.shape[0])
        #: what the labels depend on beyond the spec (a search's parameters), for a label cache's key
        self.cache_key: str | None = None
        scheduled = _priority_expert(spec, configs)
        self.zero_scores = scheduled == PRIORITY_PLANNER
        if self.zero_scores:  # glide's own order: nothing to ask a planner
            return
        self.searches = scheduled == SEARCH_PLANNER or is_class_spec(scheduled or "")
        if self.searches:
            self.planners = [_search_planner(scheduled, c, trust_files) for c in configs]
            self.scales = [c["action"]["scale"] for c in configs]
            self.cache_key = f"{self.planners[0].search!r} {self.planners[0].params!r}"
            self._last_step = [-1] * n_envs
            return
        self.planners = [make_planner(spec, trust_files=trust_files) for _ in range(n_envs)]
        self.max_acceleration = np.array([c["max_acceleration"] for c in configs], dtype=np.float64)
        self.residual_scale = np.array([c["residual_scale"] for c in configs], dtype=np.float64)
        self.bases = [make_residual_base(c["residual_base"]) for c in configs]
        self._last_step = [-1] * n_envs

    def __call__(self, obs: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """The planner's actions for the sub-environments' current scenes.

        :param obs: the VecEnv's observation (unused: the scenes are read from the environments)
        :return: ``(n_envs, max_vehicles)`` float32 actions in ``[-1, 1]``, 0 in padded slots (with the
            ``"priority"`` or ``"advice"`` action type, glide's zero scores)
        """
        if self.zero_scores:
            return np.zeros((self.vec_env.num_envs, self.max_nodes), dtype=np.float32)
        scenes = self.vec_env.env_method("scene")
        steps = self.vec_env.get_attr("steps")
        schedulers = self.vec_env.get_attr("scheduler") if self.searches else None
        actions = np.zeros((len(scenes), self.max_nodes), dtype=np.float32)
        for i, scene in enumerate(scenes):  # one planner call per sub-environment
            if steps[i] == 0 or steps[i] <= self._last_step[i]:  # a new episode
                self.planners[i].reset()
                if not self.searches and self.bases[i] is not None:
                    self.bases[i].reset()
            self._last_step[i] = steps[i]
            if self.searches:
                actions[i, : scene.num_vehicles] = self._scores(i, scene, schedulers[i])
            else:
                actions[i, : scene.num_vehicles] = self._action(i, scene, self.planners[i].act(scene))
        return actions

    def _scores(self, i: int, scene: Any, scheduler: Any) -> np.ndarray:
        """The advice scores that move each vehicle's window to the one the search chose."""
        planner = self.planners[i]
        planner.adopt(scheduler)
        windows = planner.windows_for(scene)
        return np.clip((windows - planner.params.window) / self.scales[i], -1.0, 1.0)  # the whole approach: +1

    def _action(self, i: int, scene: Any, acc: np.ndarray) -> np.ndarray:
        acc = np.asarray(acc, dtype=np.float64).reshape(scene.num_vehicles)
        a_max = self.max_acceleration[i]
        if self.bases[i] is None:
            return np.clip(acc / a_max, -1.0, 1.0)
        base = np.asarray(self.bases[i].act(scene), dtype=np.float64).reshape(scene.num_vehicles)
        return np.clip((acc - base) / (self.residual_scale[i] * a_max), -1.0, 1.0)


def _priority_expert(spec: str, configs: list[dict[str, Any]]) -> str | None:
    """``None`` where the environments take accelerations; where they take scores over glide's scheduler,
    the planner that labels them (``"glide"``, or ``"lookahead"`` with ``"advice"``), or a ValueError."""
    types = {(c.get("action") or {}).get("type", "acceleration") for c in configs}
    scheduled = types & set(SCHEDULER_ACTION_TYPES)
    if not scheduled:
        return None
    kind = sorted(scheduled)[0]
    key = check_planner_spec(spec)
    shielded = key.endswith(SHIELD_SUFFIX)
    base = key[: -len(SHIELD_SUFFIX)] if shielded else key
    shield = all(c["shield"] for c in configs)
    search = (base == SEARCH_PLANNER or is_class_spec(base)) and kind == "advice"
    if len(types) > 1 or not (base == PRIORITY_PLANNER or search) or (shielded and not shield):
        exact = f"{PRIORITY_PLANNER!r}" + (f" or '{PRIORITY_PLANNER}{SHIELD_SUFFIX}'" if shield else "")
        raise ValueError(
            f"planner {spec!r} has no exact label for action type {kind!r} (scores over glide's scheduler): "
            f"only {exact} can be cloned there (zero scores), and {SEARCH_PLANNER!r} or a class spec of a "
            f"LookaheadPlanner with 'advice' (the windows it searched); use action type 'acceleration' to clone "
            f"{spec!r}"
        )
    return base


def _search_planner(spec: str, config: dict[str, Any], trust_files: bool) -> LookaheadPlanner:
    """The search that labels an ``"advice"`` environment: ``lookahead`` over the environment's glide, or a class
    spec of a :class:`~envs.planners.lookahead.LookaheadPlanner` (e.g. one with a proposer: expert iteration)
    whose glide must be the environment's.

    :raises ValueError: a class that is no ``LookaheadPlanner``, or one over another glide (one line)
    """
    glide = GLIDE_VERSIONS[config["action"]["glide"]]
    if spec == SEARCH_PLANNER:
        return LookaheadPlanner(glide=glide)
    planner = make_planner(spec, trust_files=trust_files)
    if not isinstance(planner, LookaheadPlanner):
        raise ValueError(f"expert {spec!r}: with action type 'advice' a class must be a LookaheadPlanner, "
                         f"got {type(planner).__name__}")  # fmt: skip
    if planner.params != glide:
        raise ValueError(f"expert {spec!r}: its glide is not the environment's (action glide "
                         f"{config['action']['glide']!r}); their windows would not mean the same")  # fmt: skip
    return planner


def make_expert(spec: str, vec_env: Any) -> PlannerExpert:
    """The ``sb3_graph.experts`` entry point of the intersection domain (``--pretrain-from PLANNER``).

    :raises ValueError: an unknown planner word, naming the accepted ones
    """
    return PlannerExpert(spec, vec_env)
