"""Learning from an expert's actions: the masked imitation loss, its coefficient, and the labelling of
rollout states, shared by :func:`sb3_graph.behaviour_clone` and the ``bc_coef`` regularizer of the
algorithm aliases (:class:`~sb3_graph.common.algorithm.GraphAlgorithmMixin`).

An *expert* is a callable ``expert(obs) -> actions``: it takes a VecEnv's batched observation
dictionary and returns ``(n_envs, max_nodes)`` actions in the action space's units (padded slots are
ignored). It may read more than the observation (a planner reads each sub-environment's scene), so it
is called exactly once per environment state, before the environment steps.

The imitation loss of every registered policy is the squared error of its *deterministic action*
(:func:`sb3_graph.registry.deterministic_vertex_actions`) against the expert's, averaged over the real
vertices of the labelled graphs: TD3's and DDPG's actor output, ``tanh`` of the Gaussian mean of SAC,
TQC and CrossQ (the mean's error, in the squashed ``[-1, 1]`` units; the log-std is not trained by it),
the Gaussian mean of PPO and A2C (in the action space's units, the expert's action clipped to the
bounds). Padded slots never enter it: the prediction and the target are read at the real vertices only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback

from sb3_graph.registry import deterministic_vertex_actions

#: ``expert(obs) -> (n_envs, max_nodes)`` actions in the action space's units
Expert = Callable[[dict[str, np.ndarray]], np.ndarray]


def expert_targets(policy: Any, actions: np.ndarray) -> np.ndarray:
    """An expert's actions in the units that the policy's deterministic action has: scaled to
    ``[-1, 1]`` for a squashing policy (TD3, DDPG, SAC, TQC, CrossQ), clipped to the bounds otherwise
    (PPO, A2C).

    :param policy: an SB3 policy with a ``Box`` action space
    :param actions: ``(n_envs, max_nodes)`` actions in the action space's units
    """
    space = policy.action_space
    clipped = np.clip(np.asarray(actions, dtype=np.float32), space.low, space.high)
    if policy.squash_output:
        return np.asarray(policy.scale_action(clipped), dtype=np.float32)
    return clipped


def checked_expert_actions(actions: Any, n_envs: int, max_nodes: int, node_mask: np.ndarray) -> np.ndarray:
    """An expert's answer as a ``(n_envs, max_nodes)`` float32 array; its padded slots set to 0.

    :raises ValueError: a wrong shape, or a real vertex's action that is not a finite number
    """
    array = np.asarray(actions, dtype=np.float32)
    if array.shape != (n_envs, max_nodes):
        raise ValueError(f"expert: expected actions of shape ({n_envs}, {max_nodes}), got {array.shape}")
    real = np.asarray(node_mask).reshape(n_envs, max_nodes).astype(bool)
    if not np.isfinite(array[real]).all():
        raise ValueError("expert: returned an action that is not a finite number for a real vertex")
    return np.where(real, array, 0.0).astype(np.float32)


def demonstration_loss(policy: Any, samples: Any) -> torch.Tensor | None:
    """Squared error of the policy's deterministic action against the expert's, averaged over the real
    vertices of the labelled graphs of ``samples`` (see the module docstring).

    :param policy: a registered graph policy
    :param samples: samples with :class:`~sb3_graph.GraphBatch` observations and ``expert_actions``
        ``(B, max_nodes)`` / ``expert_mask`` ``(B,)`` fields (the graph buffers' expert samples)
    :return: the loss, or ``None`` when the samples carry no labelled vertex
    """
    expert = getattr(samples, "expert_actions", None)
    if expert is None:
        return None
    graphs = samples.observations
    labelled = samples.expert_mask[graphs.batch]
    if not bool(labelled.any()):
        return None
    predicted = deterministic_vertex_actions(policy, graphs)
    target = expert[graphs.batch, graphs.node_slot]
    return (predicted - target)[labelled].pow(2).mean()


def parse_bc_coef(value: Any, owner: str = "bc_coef") -> float | str | Callable[[float], float]:
    """Check a ``bc_coef``: a number >= 0, ``"lin_<number>"`` (linear decay to 0 over ``learn``, as
    rl-zoo3's schedules), or a callable of SB3's ``progress_remaining`` (1 at the start, 0 at the end).

    :raises ValueError: anything else, naming the allowed values
    """
    if callable(value):
        return value
    if isinstance(value, str):
        start = value[4:] if value.startswith("lin_") else None
        try:
            number = float(start) if start is not None else -1.0
        except ValueError:
            number = -1.0
        if np.isfinite(number) and number >= 0:
            return value
    elif isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
        if np.isfinite(value) and value >= 0:
            return float(value)
    raise ValueError(f"{owner} must be a number >= 0, 'lin_<number>' or a callable of the progress, got {value!r}")


def bc_coef_value(coef: float | str | Callable[[float], float], progress_remaining: float) -> float:
    """The coefficient now: ``coef`` itself, ``start * progress_remaining`` for ``"lin_<start>"``, or
    ``coef(progress_remaining)``."""
    if callable(coef):
        return float(coef(progress_remaining))
    if isinstance(coef, str):
        return float(coef[4:]) * float(progress_remaining)
    return float(coef)


class ExpertLabeller(BaseCallback):
    """Label every state of an on-policy rollout with an expert's actions, in the rollout buffer
    (:meth:`~sb3_graph.GraphRolloutBuffer.label_step`).

    The expert is asked once per state, before the environments step: the first state at the start
    of the rollout, each next one (``new_obs``, after an automatic reset the new episode's first
    observation) right after the step that led to it. The rollout's last ``new_obs`` is the next
    rollout's first state, labelled then.

    :param expert: ``expert(obs) -> (n_envs, max_nodes)`` actions in the action space's units
    :param rollout_buffer: the algorithm's :class:`~sb3_graph.GraphRolloutBuffer`
    """

    def __init__(self, expert: Expert, rollout_buffer: Any) -> None:
        super().__init__()
        self.expert = expert
        self.rollout_buffer = rollout_buffer

    def _label(self, step: int, obs: dict[str, np.ndarray]) -> None:
        buffer = self.rollout_buffer
        actions = checked_expert_actions(self.expert(obs), buffer.n_envs, buffer.max_nodes, obs["node_mask"])
        buffer.label_step(step, expert_targets(self.model.policy, actions))

    def _on_rollout_start(self) -> None:
        self._label(0, self.model._last_obs)

    def _on_step(self) -> bool:
        step = self.rollout_buffer.pos + 1  # the step being collected is not added yet
        if step < self.rollout_buffer.buffer_size:
            self._label(step, self.locals["new_obs"])
        return True
