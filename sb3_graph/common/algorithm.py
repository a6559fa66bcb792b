"""What the ``sb3_graph`` algorithm aliases (``sb3_graph.TD3``, ``SAC``, ``PPO``...) add to SB3's classes.

- Graph buffers by default: :class:`~sb3_graph.GraphReplayBuffer` (off-policy, with the
  algorithm's ``n_steps`` for n-step returns) or :class:`~sb3_graph.GraphRolloutBuffer`
  (on-policy) when the observation space is a :class:`~sb3_graph.GraphSpace` and no buffer class
  is given.
- A ``VecNormalize`` that normalizes graph observations is refused at construction and at
  ``set_env`` (:func:`check_vec_normalize`), not deep inside training.
- For the maximum-entropy algorithms (SAC, TQC, CrossQ), an entropy target that scales with the
  number of real vertices (:class:`VertexEntropyMixin`).
- Off-policy: an environment that replaces the agent's action before applying it (a safety
  shield) reports what it applied in ``info["executed_action"]`` (in the action space); that
  action, not the proposal, is stored in the replay buffer, so the critics learn the value of
  what happened (:data:`EXECUTED_ACTION`).

- A regularizer toward an expert's actions, ``bc_coef`` (default 0: off, and the updates are exactly
  SB3's): see :meth:`GraphAlgorithmMixin.bc_coefficient`.

Training itself is SB3's (or sb3-contrib's) own ``train``; around it, a graph critic leaves its own
weights out of the policy loss's autograd graph (SB3 discards those gradients; same updates).
"""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from sb3_graph.common.demonstrations import ExpertLabeller, bc_coef_value, demonstration_loss, parse_bc_coef
from sb3_graph.common.networks import GraphCritic
from sb3_graph.common.spaces import EDGE_ATTR, GRAPH_KEYS, GraphSpace

#: ``info`` key of an environment's applied action when it differs from the agent's (a shield).
EXECUTED_ACTION = "executed_action"


def is_graph_space(space: spaces.Space) -> bool:
    """True for a :class:`~sb3_graph.GraphSpace` or a ``Dict`` with its keys."""
    keys = set(getattr(space, "spaces", {}) or {})
    return isinstance(space, spaces.Dict) and keys in (set(GRAPH_KEYS), {*GRAPH_KEYS, EDGE_ATTR})


def check_vec_normalize(env: VecEnv | None, observation_space: spaces.Space) -> None:
    """Refuse a ``VecNormalize`` that normalizes any entry of a graph observation.

    VecNormalize keeps one running mean per array *slot*: it would turn vertex ids and masks into
    fractions, and scale a vertex's features by the statistics of whatever slot it sits in (so the
    same vehicle would look different in slot 0 and slot 5). Normalize the vertex features inside
    the environment instead; ``VecNormalize(norm_obs=False, norm_reward=True)`` is fine.

    :param env: the algorithm's ``VecNormalize`` wrapper (or ``None``)
    :param observation_space: the observation space
    :raises ValueError: when graph entries would be normalized
    """
    if not isinstance(env, VecNormalize) or not env.norm_obs or not is_graph_space(observation_space):
        return
    keys = env.norm_obs_keys if env.norm_obs_keys is not None else list(observation_space.spaces)
    normalized = sorted(set(keys) & set(observation_space.spaces))
    if normalized:
        raise ValueError(
            f"VecNormalize(norm_obs=True) would normalize the graph observation entries {normalized}: "
            "vertex ids and masks would stop being integers, and each vertex would be scaled by the "
            "statistics of its array slot. Use VecNormalize(norm_obs=False) (reward normalization is "
            "fine) and scale the vertex features in the environment."
        )


class GraphAlgorithmMixin:
    """Graph defaults for an SB3 algorithm; put it before the SB3 class in the bases.

    The subclass names its graph buffer in ``graph_buffer_class`` and the constructor argument
    that selects a buffer in ``buffer_class_attribute``.

    Two constructor arguments of its own, the regularizer toward an expert (TD3+BC, Fujimoto & Gu
    2021, in its plain additive form):

    :param bc_coef: weight ``c`` of the imitation term added to the actor's loss,
        ``loss + c * mean_i (pi(s)_i - a^E_i)^2`` over the real vertices of the labelled graphs of
        each batch (:func:`sb3_graph.common.demonstrations.demonstration_loss`): a number >= 0,
        ``"lin_<c>"`` (linear decay to 0 over ``learn``) or a callable of SB3's
        ``progress_remaining``. 0 (the default) leaves training exactly SB3's. Off-policy (TD3, DDPG,
        SAC, TQC, CrossQ), the labelled transitions are the demonstrations that
        :func:`sb3_graph.behaviour_clone` left in the replay buffer; on-policy (PPO, A2C), every
        rollout state is labelled by ``bc_expert``. TD3+BC's ``lambda``-normalised form
        ``-lambda Q + BC`` with ``lambda = alpha / mean|Q|`` is this with ``c = mean|Q| / alpha``
        (the paper's ``alpha = 2.5``). The term's gradient is added to the actor's just before its
        optimizer steps (after PPO's and A2C's gradient clipping, which it does not pass through),
        at the cost of one more actor forward and backward pass on the batch.
    :param bc_expert: on-policy only: ``expert(obs) -> (n_envs, max_nodes)`` actions that label the
        rollout states while ``bc_coef`` is above 0 (not saved with the model)
    """

    graph_buffer_class: type | None = None
    buffer_class_attribute = "replay_buffer_class"
    # Defaults for models saved before these options existed.
    bc_coef: float | str | Callable[[float], float] = 0.0
    bc_expert: Callable | None = None

    def __init__(self, *args: Any, bc_coef: Any = 0.0, bc_expert: Callable | None = None, **kwargs: Any) -> None:
        self.bc_coef = parse_bc_coef(bc_coef)
        self.bc_expert = bc_expert
        super().__init__(*args, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "bc_expert"]  # type: ignore[misc]

    def bc_coefficient(self) -> float:
        """The imitation term's weight now (see ``bc_coef``), at SB3's ``_current_progress_remaining``."""
        return bc_coef_value(self.bc_coef, getattr(self, "_current_progress_remaining", 1.0))

    @property
    def _on_policy(self) -> bool:
        return self.buffer_class_attribute == "rollout_buffer_class"

    def actor_optimizer(self) -> Any:
        """The optimizer of the actor's parameters: the actor's own (off-policy) or the policy's (on-policy)."""
        actor = getattr(self, "actor", None)
        return self.policy.optimizer if actor is None else actor.optimizer  # type: ignore[attr-defined]

    def _setup_model(self) -> None:
        check_vec_normalize(self._vec_normalize_env, self.observation_space)  # type: ignore[attr-defined]
        attribute = self.buffer_class_attribute
        if getattr(self, attribute, None) is None and isinstance(self.observation_space, GraphSpace):  # type: ignore[attr-defined]
            setattr(self, attribute, self.graph_buffer_class)
            if attribute == "replay_buffer_class" and self.n_steps > 1:  # type: ignore[attr-defined]
                # n-step returns: the graph buffer computes them as SB3's NStepReplayBuffer does.
                self.replay_buffer_kwargs = {  # type: ignore[attr-defined]
                    **self.replay_buffer_kwargs,  # type: ignore[attr-defined]
                    "n_steps": self.n_steps,  # type: ignore[attr-defined]
                    "gamma": self.gamma,  # type: ignore[attr-defined]
                }
        if attribute != "replay_buffer_class" or self.n_steps == 1:  # type: ignore[attr-defined]
            super()._setup_model()  # type: ignore[misc]
            return
        # SB3 warns that n_steps is ignored whenever a buffer class is set; here the buffer's own
        # n_steps is the algorithm's, so the warning would be wrong. Otherwise SB3's warning stands.
        n_steps, takes_it = self.n_steps, self.replay_buffer_kwargs.get("n_steps") == self.n_steps  # type: ignore[attr-defined]
        if takes_it:
            self.n_steps = 1
        try:
            super()._setup_model()  # type: ignore[misc]
        finally:
            self.n_steps = n_steps

    def train(self, *args: Any, **kwargs: Any) -> None:
        """SB3's ``train``; a graph critic (TD3, DDPG, SAC, TQC) computes no weight gradients in the
        policy loss, which SB3 discards (see :class:`~sb3_graph.common.networks.GraphCritic`); with
        ``bc_coef`` above 0, the imitation term joins the actor's loss."""
        coef = self.bc_coefficient()
        with self._imitation_term(coef) if coef > 0 else contextlib.nullcontext():
            critic = getattr(getattr(self, "policy", None), "critic", None)
            if not isinstance(critic, GraphCritic):
                super().train(*args, **kwargs)  # type: ignore[misc]
                return
            critic.policy_loss_without_weight_gradients = True
            try:
                super().train(*args, **kwargs)  # type: ignore[misc]
            finally:
                critic.policy_loss_without_weight_gradients = False

    @contextlib.contextmanager
    def _imitation_term(self, coef: float) -> Iterator[None]:
        """Within the block, each step of the actor's optimizer first adds the gradient of
        ``coef * demonstration_loss`` on the batch that SB3 sampled last (recorded at the buffer)."""
        buffer = self.rollout_buffer if self._on_policy else self.replay_buffer  # type: ignore[attr-defined]
        method = "_get_samples" if self._on_policy else "sample"
        original = getattr(buffer, method)
        last: list[Any] = [None]
        losses: list[float] = []

        def recording(*args: Any, **kwargs: Any) -> Any:
            last[0] = original(*args, **kwargs)
            return last[0]

        def add_imitation_gradient(optimizer: Any, args: Any, kwargs: Any) -> None:
            loss = None if last[0] is None else demonstration_loss(self.policy, last[0])  # type: ignore[attr-defined]
            if loss is not None:
                (coef * loss).backward()
                losses.append(loss.item())

        setattr(buffer, method, recording)
        handle = self.actor_optimizer().register_step_pre_hook(add_imitation_gradient)
        try:
            yield
        finally:
            handle.remove()
            del buffer.__dict__[method]
        self.logger.record("train/bc_coef", coef)  # type: ignore[attr-defined]
        if losses:
            self.logger.record("train/bc_loss", float(np.mean(losses)))  # type: ignore[attr-defined]

    def collect_rollouts(self, env: VecEnv, callback: BaseCallback, *args: Any, **kwargs: Any) -> Any:
        """SB3's ``collect_rollouts``; on-policy with ``bc_coef`` above 0, ``bc_expert`` labels every
        rollout state (:class:`~sb3_graph.common.demonstrations.ExpertLabeller`)."""
        if not self._on_policy or self.bc_coefficient() <= 0:
            return super().collect_rollouts(env, callback, *args, **kwargs)  # type: ignore[misc]
        if self.bc_expert is None:
            raise ValueError(
                f"{type(self).__name__}: bc_coef > 0 needs an expert to label the rollouts: pass bc_expert= "
                "(sb3_graph.behaviour_clone sets it)"
            )
        labeller = ExpertLabeller(self.bc_expert, self.rollout_buffer)  # type: ignore[attr-defined]
        labeller.init_callback(self)  # type: ignore[arg-type]
        both = CallbackList([callback, labeller])
        both.model = self  # type: ignore[assignment] # the children are initialised already
        return super().collect_rollouts(env, both, *args, **kwargs)  # type: ignore[misc]

    def set_env(self, env: Any, force_reset: bool = True) -> None:
        super().set_env(env, force_reset)  # type: ignore[misc]
        check_vec_normalize(self._vec_normalize_env, self.observation_space)  # type: ignore[attr-defined]

    def _store_transition(self, replay_buffer: Any, buffer_action: np.ndarray, *args: Any, **kwargs: Any) -> None:
        """SB3's ``_store_transition`` with each environment's ``info["executed_action"]`` (when it
        reports one) in place of the proposed action (off-policy algorithms only)."""
        infos = kwargs.get("infos", args[-1] if args else ())
        executed = [k for k, info in enumerate(infos) if EXECUTED_ACTION in info]
        if executed:
            buffer_action = np.array(buffer_action, copy=True)
            for k in executed:  # one per environment of the VecEnv
                action = np.asarray(infos[k][EXECUTED_ACTION], dtype=buffer_action.dtype)
                action = action.reshape(buffer_action[k].shape)
                buffer_action[k] = self.policy.scale_action(action)  # type: ignore[attr-defined]
        super()._store_transition(replay_buffer, buffer_action, *args, **kwargs)  # type: ignore[misc]


class VertexEntropyMixin:
    """Entropy target per real vertex for SAC, TQC and CrossQ with a per-vertex Gaussian policy.

    The graph actors' log-probability of a graph's action is the *sum* over its real vertices, so
    its entropy grows with the vertex count. SB3's ``target_entropy="auto"`` is
    ``-dim(A) = -max_nodes`` for every graph, which asks a small graph for much less entropy per
    vertex than a large one. With ``target_entropy="auto"`` these aliases instead use
    ``-1`` per real vertex: the target of graph ``b`` is ``-n_b``.

    The entropy coefficient's loss is linear in the target,
    ``-(log_alpha * (log_prob_b + target_b)).mean()``, so a per-graph target ``-n_b`` gives the same
    gradient as the scalar target ``-mean_b(n_b)`` of the sampled batch. The actor records that mean
    in ``action_log_prob`` (``last_mean_vertices``) when it runs with gradients enabled, which in
    SB3's and sb3-contrib's ``train`` is its call on the batch's observations (the call on the next
    observations runs under ``no_grad``). :attr:`target_entropy` returns
    ``vertex_target_entropy * last_mean_vertices`` on *every* read, without side effects: SAC's
    ``train`` reads it twice per gradient step (an ``assert`` and the loss), TQC and CrossQ once,
    and each read gets the batch's per-vertex target. Before the first gradient step it is SB3's
    stored value. SB3's ``train`` runs unchanged.

    A number given as ``target_entropy`` keeps SB3's meaning (one target for every graph).
    Stock ``stable_baselines3.SAC(GraphSACPolicy, env)`` uses ``-max_nodes``.
    """

    vertex_target_entropy: float | None = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        arguments = inspect.signature(super().__init__).bind_partial(*args, **kwargs).arguments
        target = arguments.get("target_entropy", "auto")
        self.vertex_target_entropy = -1.0 if isinstance(target, str) and target == "auto" else None
        super().__init__(*args, **kwargs)  # type: ignore[call-arg]

    @property
    def target_entropy(self) -> Any:
        stored = self.__dict__.get("_target_entropy", "auto")
        if self.vertex_target_entropy is not None and isinstance(stored, (float, np.floating)):
            count = getattr(self.__dict__.get("actor"), "last_mean_vertices", None)
            if count is not None:
                return float(self.vertex_target_entropy * count)
        return stored

    @target_entropy.setter
    def target_entropy(self, value: Any) -> None:
        self.__dict__["_target_entropy"] = value
