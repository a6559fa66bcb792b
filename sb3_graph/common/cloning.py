"""Behaviour cloning of an expert into any algorithm of the registry, before (or between) RL.

:func:`behaviour_clone` drives the model's own VecEnv with an expert (optionally mixing in the policy,
DAgger), labels every visited state with the expert's action, and trains the actor on the labels with
the masked imitation loss of :mod:`sb3_graph.common.demonstrations`. Off-policy models keep the demonstrations
in their replay buffer (:class:`~sb3_graph.GraphReplayBuffer` with expert actions), where the
``bc_coef`` regularizer finds them during RL, and warm up their critics on them.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.logger import Logger

from sb3_graph.common.algorithm import EXECUTED_ACTION
from sb3_graph.common.buffers import GraphReplayBuffer
from sb3_graph.common.demonstrations import Expert, checked_expert_actions, demonstration_loss, expert_targets


def behaviour_clone(
    model: Any,
    expert: Expert,
    *,
    transitions: int,
    gradient_steps: int,
    batch_size: int = 256,
    beta: float | Callable[[int], float] = 1.0,
    rounds: int = 1,
    critic_steps: int | None = None,
    learning_rate: float | None = None,
    log_interval: int = 100,
    demonstrations: Demonstrations | None = None,
    record: bool = False,
    collector: Callable[[int, float, int], Demonstrations] | None = None,
) -> dict[str, Any]:
    """Clone an expert into ``model``'s actor (and, off-policy, warm up its critics on the demonstrations).

    In each of ``rounds`` rounds: step the model's VecEnv ``transitions / rounds`` times (rounded up to
    whole VecEnv steps), each sub-environment acting with the expert with probability ``beta`` and with
    the policy's deterministic action otherwise (DAgger; ``beta=1``: plain behaviour cloning), label each
    visited state with the expert's action, then take ``gradient_steps / rounds`` gradient steps of the
    actor on batches of labelled transitions (all rounds' so far).

    The loss (:func:`sb3_graph.common.demonstrations.demonstration_loss`) is the squared error of the policy's
    deterministic action against the expert's over the real vertices only: a masked MSE of the actor's
    output for TD3 and DDPG; for the stochastic actors the error of the Gaussian *mean* (``tanh(mean)``
    for SAC, TQC and CrossQ, the mean for PPO and A2C), not the negative log-likelihood: an expert's
    action on the bounds (full throttle, full braking) has an infinite ``atanh``, and the entropy is left
    to RL.

    Off-policy models (TD3, DDPG, SAC, TQC, CrossQ) store the demonstrations in their replay buffer, with
    the expert's action per transition (:meth:`GraphReplayBuffer.enable_expert_actions`): the
    ``bc_coef`` regularizer reads them during RL. After cloning, a TD3 or DDPG actor target is set to the
    cloned actor, then the critics are warmed up by ``critic_steps`` of SB3's own ``train`` with the
    actor's optimizer step disabled (the actor frozen: the critics learn the value of the cloned policy
    from the demonstrations, with SB3's targets, target networks and entropy coefficient). On-policy
    models (PPO, A2C) learn from a temporary buffer and get ``bc_expert = expert`` (when not set), which
    labels their rollouts for ``bc_coef``; their value function is not warmed up.

    :param model: an algorithm of :mod:`sb3_graph.registry` built on a ``GraphSpace`` environment
    :param expert: ``expert(obs) -> (n_envs, max_nodes)`` actions in the action space's units, asked
        exactly once per state (before the environments step)
    :param transitions: environment steps to collect, over all sub-environments
    :param gradient_steps: gradient steps of the actor
    :param batch_size: transitions per gradient step
    :param beta: probability of acting with the expert, or ``beta(round) -> probability``
        (DAgger's schedule, e.g. ``lambda k: 0.5 ** k``)
    :param rounds: collect-then-train rounds
    :param critic_steps: critic warm-up gradient steps (off-policy; default ``gradient_steps // 4``)
    :param learning_rate: the actor's learning rate while cloning (default: the model's current one)
    :param log_interval: gradient steps between two dumps of the model's logger (if it has one)
    :param demonstrations: transitions recorded by an earlier call (``record=True``) on the same
        environments (same ``n_envs`` and spaces): they are replayed into the dataset instead of
        collecting (``transitions`` and ``beta`` are then unused, ``rounds`` must be 1, the expert is
        never asked; an on-policy model still gets it as ``bc_expert``)
    :param record: also return the collected transitions as ``result["demonstrations"]``
        (a :class:`Demonstrations`, e.g. to clone into other models without collecting again)
    :param collector: collects each round elsewhere instead of stepping the model's VecEnv:
        ``collector(round, beta, steps)`` returns that round's :class:`Demonstrations` of ``steps`` VecEnv
        steps on as many sub-environments as the model's (e.g. :class:`~sb3_graph.common.labelling.ShardedCollector`,
        which labels each sub-environment's share on an executor and resumes from its cache); not with
        ``demonstrations`` or ``record``
    :return: ``actor_loss`` and ``critic_loss`` (one value per gradient step), ``transitions``
        collected, ``expert_share`` (the share of sub-environment steps acted by the expert),
        ``collect_s``, ``train_s`` and ``critic_s`` (wall time of collecting, of the actor's steps and of
        the critics' warm-up), and with ``record`` the ``demonstrations``
    :raises ValueError: a bad argument, naming it, or an expert answer of the wrong shape
    """
    _check_arguments(model, transitions, gradient_steps, batch_size, rounds, critic_steps)
    env = model.get_env()
    if collector is not None and (demonstrations is not None or record):
        raise ValueError("behaviour_clone: a collector keeps its own rounds (no demonstrations, no record)")
    if demonstrations is not None:
        _check_demonstrations(demonstrations, env, rounds)
        transitions = demonstrations.transitions
    on_policy = getattr(model, "replay_buffer", None) is None
    dataset = _dataset(model, transitions, env.num_envs, on_policy)
    recorder = Demonstrations() if record and demonstrations is None else demonstrations
    optimizer = model.actor_optimizer()
    if learning_rate is not None:
        for group in optimizer.param_groups:
            group["lr"] = float(learning_rate)
    logger = _logger(model)
    result: dict[str, Any] = {
        "actor_loss": [], "critic_loss": [], "transitions": 0, "collect_s": 0.0, "train_s": 0.0, "critic_s": 0.0
    }
    expert_steps, obs = 0, (env.reset() if demonstrations is None and collector is None else None)
    per_round = [_share(transitions, rounds, k) for k in range(rounds)]
    steps_per_round = [_share(gradient_steps, rounds, k) for k in range(rounds)]
    for k in range(rounds):
        probability = float(beta(k) if callable(beta) else beta)
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"behaviour_clone: beta must lie in [0, 1], got {probability} in round {k}")
        start = time.perf_counter()
        if collector is not None:
            collected = collector(k, probability, math.ceil(per_round[k] / env.num_envs))
            _check_demonstrations(collected, env, 1)
            collected.replay(dataset, model.policy)
            expert_steps += collected.expert_steps
            result["transitions"] += collected.transitions
        elif demonstrations is None:
            steps = math.ceil(per_round[k] / env.num_envs)
            obs, acted = _collect(model, expert, dataset, obs, steps, probability, recorder)
            expert_steps += acted
            result["transitions"] += steps * env.num_envs
        else:
            demonstrations.replay(dataset, model.policy)
            expert_steps += demonstrations.expert_steps
            result["transitions"] += demonstrations.transitions
        result["collect_s"] += time.perf_counter() - start
        start = time.perf_counter()
        losses = _fit_actor(model, dataset, optimizer, steps_per_round[k], batch_size, logger, log_interval)
        result["actor_loss"] += losses
        result["train_s"] += time.perf_counter() - start
    result["expert_share"] = expert_steps / max(result["transitions"], 1)
    actor_target = getattr(model, "actor_target", None)
    if actor_target is not None:
        actor_target.load_state_dict(model.actor.state_dict())
    start = time.perf_counter()
    if on_policy:
        if model.bc_expert is None:
            model.bc_expert = expert
    else:
        steps = gradient_steps // 4 if critic_steps is None else critic_steps
        result["critic_loss"] = _warm_up_critics(model, optimizer, steps, batch_size, logger, log_interval)
    result["critic_s"] = time.perf_counter() - start
    if record:
        result["demonstrations"] = recorder
    logger.record("pretrain/transitions", result["transitions"])
    logger.record("pretrain/expert_share", result["expert_share"])
    logger.dump(len(result["actor_loss"]) + len(result["critic_loss"]))
    model._last_obs = None  # learn() starts from a reset
    return result


def _check_arguments(
    model: Any, transitions: int, gradient_steps: int, batch_size: int, rounds: int, critic_steps: int | None
) -> None:
    for name, value, low in (
        ("transitions", transitions, 1),
        ("gradient_steps", gradient_steps, 0),
        ("batch_size", batch_size, 1),
        ("rounds", rounds, 1),
        ("critic_steps", 0 if critic_steps is None else critic_steps, 0),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"behaviour_clone: {name} must be an integer >= {low}, got {value!r}")
    if not hasattr(model, "actor_optimizer"):
        raise ValueError(f"behaviour_clone: model must be an algorithm of sb3_graph, got {type(model).__name__}")
    if model.get_env() is None:
        raise ValueError("behaviour_clone: the model has no environment (model.set_env(env) first)")
    if transitions < rounds:
        raise ValueError(f"behaviour_clone: transitions ({transitions}) must be at least rounds ({rounds})")


def _check_demonstrations(demonstrations: Demonstrations, env: Any, rounds: int) -> None:
    if not isinstance(demonstrations, Demonstrations) or demonstrations.steps == 0:
        raise ValueError("behaviour_clone: demonstrations must be a non-empty Demonstrations (record=True)")
    if rounds != 1:
        raise ValueError(f"behaviour_clone: replayed demonstrations take rounds=1 (DAgger collects), got {rounds}")
    n_envs, max_nodes = demonstrations.actions.shape[1:]
    if n_envs != env.num_envs or max_nodes != int(np.prod(env.action_space.shape)):
        raise ValueError(
            f"behaviour_clone: demonstrations of {n_envs} environments x {max_nodes} vertices do not fit this "
            f"model's {env.num_envs} x {int(np.prod(env.action_space.shape))}"
        )


def _share(total: int, parts: int, k: int) -> int:
    """Part ``k`` of ``total`` split into ``parts`` near-equal integers."""
    return total // parts + (1 if k < total % parts else 0)


def _dataset(model: Any, transitions: int, n_envs: int, on_policy: bool) -> GraphReplayBuffer:
    if on_policy:
        return GraphReplayBuffer(
            max(transitions, n_envs),
            model.observation_space,
            model.action_space,
            device=model.device,
            n_envs=n_envs,
            store_expert_actions=True,
        )
    buffer = model.replay_buffer
    if not isinstance(buffer, GraphReplayBuffer):
        raise ValueError(
            f"behaviour_clone: needs the graph replay buffer (GraphReplayBuffer), got {type(buffer).__name__}"
        )
    buffer.enable_expert_actions()
    return buffer


def _logger(model: Any) -> Logger:
    """The model's logger, or a silent one that ``learn`` replaces (a model that never learned has none)."""
    try:
        return model.logger
    except AttributeError:
        model._logger = Logger(folder=None, output_formats=[])
        return model._logger


def _collect(
    model: Any,
    expert: Expert,
    buffer: GraphReplayBuffer,
    obs: dict,
    steps: int,
    probability: float,
    recorder: Demonstrations | None = None,
) -> tuple[dict, int]:
    """Step the VecEnv ``steps`` times, store each transition with its expert label; return the last
    observation and the number of sub-environment steps acted by the expert."""
    env, policy = model.get_env(), model.policy
    rng = np.random.default_rng(np.random.randint(2**31))  # noqa: NPY002 (follows the model's seed)
    acted = 0
    for _ in range(steps):
        new_obs, stored, labels, rewards, dones, infos, use_expert = expert_step(env, policy, expert, obs, probability,
                                                                                 rng)  # fmt: skip
        acted += int(use_expert.sum())
        rewards = _original_rewards(model, rewards)
        buffer.add(
            obs,
            _next_observations(new_obs, dones, infos),
            expert_targets(policy, stored),
            rewards,
            dones,
            infos,
            expert_action=expert_targets(policy, labels),
        )
        if recorder is not None:
            recorder.append(obs, new_obs, stored, labels, rewards, dones, infos, use_expert)
        obs = new_obs
    return obs, acted


def expert_step(
    env: Any, policy: Any, expert: Expert, obs: dict, probability: float, rng: np.random.Generator
) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict], np.ndarray]:
    """One VecEnv step of a cloning round: each sub-environment acts with the expert with ``probability``, else
    with ``policy``'s deterministic action (DAgger); every state gets the expert's label.

    :return: ``(new_obs, executed actions, labels, rewards, dones, infos, by_expert)``, actions in the action
        space's units (``executed``: what the environment reports it did, where it says so)
    """
    n_envs, max_nodes = env.num_envs, int(np.prod(env.action_space.shape))
    labels = checked_expert_actions(expert(obs), n_envs, max_nodes, obs["node_mask"])
    use_expert = rng.random(n_envs) < probability
    action = labels
    if not use_expert.all():
        with torch.no_grad():
            own, _ = policy.predict(obs, deterministic=True)
        action = np.where(use_expert[:, None], np.clip(labels, env.action_space.low, env.action_space.high), own)
    new_obs, rewards, dones, infos = env.step(action)
    stored = np.array(action, dtype=np.float32, copy=True)
    for i, info in enumerate(infos):  # one per environment, as SB3's _store_transition
        if EXECUTED_ACTION in info:
            stored[i] = np.asarray(info[EXECUTED_ACTION], dtype=np.float32).reshape(max_nodes)
    return new_obs, stored, labels, rewards, dones, infos, use_expert


class Demonstrations:
    """Transitions collected by :func:`behaviour_clone` (``record=True``), to replay into other models.

    Kept as VecEnv steps: the observations ``obs[t]`` (``steps + 1`` of them: step ``t`` goes from
    ``obs[t]`` to ``obs[t + 1]``, except where an episode ended, whose terminal observation is kept
    apart), the executed and the expert's actions in the action space's units (so that any algorithm's
    policy can take them), the original rewards, the dones and the time-limit truncations.
    :meth:`save` and :meth:`load` write and read one ``.npz`` file (arrays only, nothing unpickled).
    """

    ARRAYS = ("actions", "labels", "rewards", "dones", "truncated", "by_expert", "terminal_index")

    def __init__(self) -> None:
        self._obs: list[dict[str, np.ndarray]] = []
        self._rows: dict[str, list[np.ndarray]] = {name: [] for name in self.ARRAYS if name != "terminal_index"}
        self._terminal: list[tuple[int, int, dict[str, np.ndarray]]] = []
        self._frozen: dict[str, np.ndarray] | None = None

    def append(
        self,
        obs: dict[str, np.ndarray],
        new_obs: dict[str, np.ndarray],
        actions: np.ndarray,
        labels: np.ndarray,
        rewards: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
        by_expert: np.ndarray,
    ) -> None:
        """Record one VecEnv step (``obs`` must be the ``new_obs`` of the previous one, if any)."""
        if self._frozen is not None:
            raise ValueError("Demonstrations: loaded demonstrations are read-only")
        if not self._obs:
            self._obs.append({key: np.array(value, copy=True) for key, value in obs.items()})
        self._obs.append({key: np.array(value, copy=True) for key, value in new_obs.items()})
        step = len(self._obs) - 2
        for name, value in (("actions", actions), ("labels", labels), ("rewards", rewards), ("dones", dones),
                            ("by_expert", by_expert)):  # fmt: skip
            self._rows[name].append(np.array(value, dtype=np.float32 if name != "by_expert" else bool, copy=True))
        self._rows["truncated"].append(np.array([bool(info.get("TimeLimit.truncated", False)) for info in infos]))
        for i, info in enumerate(infos):
            terminal = info.get("terminal_observation")
            if dones[i] and terminal is not None:
                self._terminal.append((step, i, {key: np.asarray(terminal[key]) for key in new_obs}))

    def arrays(self) -> dict[str, np.ndarray]:
        """Everything as named arrays (``obs/KEY``, ``terminal/KEY`` and :attr:`ARRAYS`)."""
        if self._frozen is not None:
            return self._frozen
        if not self._obs:
            raise ValueError("Demonstrations: nothing recorded")
        out = {f"obs/{key}": np.stack([o[key] for o in self._obs]) for key in self._obs[0]}
        out.update({name: np.stack(rows) for name, rows in self._rows.items()})
        out["terminal_index"] = np.array([(t, i) for t, i, _ in self._terminal], dtype=np.int64).reshape(-1, 2)
        for key in self._obs[0]:
            shape = self._obs[0][key].shape[1:]
            rows = [obs[key] for _, _, obs in self._terminal]
            out[f"terminal/{key}"] = np.stack(rows) if rows else np.zeros((0, *shape), self._obs[0][key].dtype)
        return out

    @property
    def steps(self) -> int:
        """VecEnv steps held."""
        return int(self.arrays()["actions"].shape[0]) if (self._obs or self._frozen is not None) else 0

    @property
    def actions(self) -> np.ndarray:
        """``(steps, n_envs, max_nodes)`` executed actions."""
        return self.arrays()["actions"]

    @property
    def transitions(self) -> int:
        """Sub-environment steps held."""
        return int(np.prod(self.actions.shape[:2]))

    @property
    def expert_steps(self) -> int:
        """Sub-environment steps that the expert acted."""
        return int(self.arrays()["by_expert"].sum())

    def replay(self, buffer: GraphReplayBuffer, policy: Any) -> None:
        """Add every transition to ``buffer`` with its expert label, in ``policy``'s buffer units."""
        data = self.arrays()
        keys = [name[len("obs/"):] for name in data if name.startswith("obs/")]
        terminal = {(int(t), int(i)): k for k, (t, i) in enumerate(data["terminal_index"])}
        for t in range(self.steps):  # one buffer.add per VecEnv step, as when collecting
            obs = {key: data[f"obs/{key}"][t] for key in keys}
            next_obs = {key: np.array(data[f"obs/{key}"][t + 1], copy=True) for key in keys}
            for i in np.flatnonzero(data["dones"][t]):
                if (t, int(i)) in terminal:
                    for key in keys:
                        next_obs[key][i] = data[f"terminal/{key}"][terminal[t, int(i)]]
            infos = [{"TimeLimit.truncated": bool(flag)} for flag in data["truncated"][t]]
            buffer.add(
                obs,
                next_obs,
                expert_targets(policy, data["actions"][t]),
                data["rewards"][t],
                data["dones"][t],
                infos,
                expert_action=expert_targets(policy, data["labels"][t]),
            )

    @classmethod
    def stack(cls, parts: list[Demonstrations]) -> Demonstrations:
        """The sub-environments of ``parts`` side by side (part ``p``'s environment ``i`` after those of the parts
        before it): what collecting them in one VecEnv in lockstep would have recorded.

        :raises ValueError: parts of different lengths or spaces
        """
        if not parts:
            raise ValueError("Demonstrations.stack: no parts")
        data = [part.arrays() for part in parts]
        if len({d["actions"].shape[0] for d in data}) != 1 or len({tuple(sorted(d)) for d in data}) != 1:
            raise ValueError("Demonstrations.stack: the parts differ in steps or arrays")
        out = {}
        for name in data[0]:
            if name == "terminal_index":
                offsets = np.cumsum([0] + [d["actions"].shape[1] for d in data[:-1]])
                out[name] = np.concatenate([d[name] + [0, offset] for d, offset in zip(data, offsets)])
            elif name.startswith("terminal/"):
                out[name] = np.concatenate([d[name] for d in data])
            else:  # (steps[+1], n_envs, ...)
                out[name] = np.concatenate([d[name] for d in data], axis=1)
        # terminal observations in (step, env) order, as one VecEnv's steps record them
        order = np.lexsort((out["terminal_index"][:, 1], out["terminal_index"][:, 0]))
        out["terminal_index"] = out["terminal_index"][order].reshape(-1, 2).astype(np.int64)
        for name in [n for n in out if n.startswith("terminal/")]:
            out[name] = out[name][order]
        return cls.from_arrays(out)

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Demonstrations:
        """Read-only demonstrations of named arrays, as :meth:`arrays` gives them (a shard sent back by a worker)."""
        new = cls()
        new._frozen = arrays
        return new

    def save(self, file: Any) -> None:
        """Write the arrays to ``file`` (a path or a binary file object) as a compressed ``.npz``."""
        np.savez_compressed(file, **self.arrays())

    @classmethod
    def load(cls, file: Any) -> Demonstrations:
        """Read demonstrations written by :meth:`save` (no pickle).

        :raises ValueError: not such a file
        """
        try:
            with np.load(file, allow_pickle=False) as npz:
                data = {name: npz[name] for name in npz.files}
        except (OSError, ValueError, KeyError) as error:
            raise ValueError(f"Demonstrations.load: not a demonstrations file: {error}") from None
        missing = [name for name in cls.ARRAYS if name not in data]
        if missing or not any(name.startswith("obs/") for name in data):
            raise ValueError(f"Demonstrations.load: not a demonstrations file (missing {missing or 'obs/'})")
        return cls.from_arrays(data)


def _next_observations(new_obs: dict, dones: np.ndarray, infos: list[dict]) -> dict:
    """The next observations to store: the terminal observation where an episode ended (SB3's rule)."""
    next_obs = copy.deepcopy(new_obs)
    for i, done in enumerate(dones):
        terminal = infos[i].get("terminal_observation")
        if done and terminal is not None:
            for key in next_obs:
                next_obs[key][i] = terminal[key]
    return next_obs


def _original_rewards(model: Any, rewards: np.ndarray) -> np.ndarray:
    normalizer = getattr(model, "_vec_normalize_env", None)
    return rewards if normalizer is None else normalizer.get_original_reward()


def _fit_actor(
    model: Any, buffer: GraphReplayBuffer, optimizer: Any, steps: int, batch_size: int, logger: Logger, interval: int
) -> list[float]:
    """``steps`` gradient steps of the imitation loss on labelled transitions; the losses."""
    model.policy.set_training_mode(True)
    losses = []
    for _ in range(steps):
        loss = demonstration_loss(model.policy, buffer.sample_expert(batch_size))
        if loss is None:  # only empty graphs were sampled
            losses.append(0.0)
            continue
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        logger.record_mean("pretrain/actor_loss", losses[-1])
        if len(losses) % interval == 0:
            logger.dump(len(losses))
    model.policy.set_training_mode(False)
    return losses


def _warm_up_critics(
    model: Any, actor_optimizer: Any, steps: int, batch_size: int, logger: Logger, interval: int
) -> list[float]:
    """``steps`` single-step calls of SB3's ``train`` with the actor's optimizer step disabled; the
    critic loss of each."""
    losses = []
    actor_optimizer.step = lambda *args, **kwargs: None  # the actor is frozen; its gradients are dropped
    try:
        for _ in range(steps):
            model.train(gradient_steps=1, batch_size=batch_size)
            loss = float(logger.name_to_value.get("train/critic_loss", np.nan))
            losses.append(loss)
            logger.record_mean("pretrain/critic_loss", loss)
            if len(losses) % interval == 0:
                logger.dump(len(losses))
    finally:
        del actor_optimizer.step
        actor_optimizer.zero_grad()
    return losses
