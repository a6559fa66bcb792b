"""Behaviour cloning of an expert into any algorithm of the registry, before (or between) RL.

:func:`behaviour_clone` drives the model's own VecEnv with an expert (optionally mixing in the policy,
DAgger), labels every visited state with the expert's action, and trains the actor on the labels with
the masked imitation loss of :mod:`sb3_graph.demonstrations`. Off-policy models keep the demonstrations
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

from sb3_graph.algorithm import EXECUTED_ACTION
from sb3_graph.buffers import GraphReplayBuffer
from sb3_graph.demonstrations import Expert, checked_expert_actions, demonstration_loss, expert_targets


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
) -> dict[str, Any]:
    """Clone an expert into ``model``'s actor (and, off-policy, warm up its critics on the demonstrations).

    In each of ``rounds`` rounds: step the model's VecEnv ``transitions / rounds`` times (rounded up to
    whole VecEnv steps), each sub-environment acting with the expert with probability ``beta`` and with
    the policy's deterministic action otherwise (DAgger; ``beta=1``: plain behaviour cloning), label each
    visited state with the expert's action, then take ``gradient_steps / rounds`` gradient steps of the
    actor on batches of labelled transitions (all rounds' so far).

    The loss (:func:`sb3_graph.demonstrations.demonstration_loss`) is the squared error of the policy's
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
    :return: ``actor_loss`` and ``critic_loss`` (one value per gradient step), ``transitions``
        collected, ``expert_share`` (the share of sub-environment steps acted by the expert),
        ``collect_s``, ``train_s`` and ``critic_s`` (wall time of collecting, of the actor's steps and of
        the critics' warm-up)
    :raises ValueError: a bad argument, naming it, or an expert answer of the wrong shape
    """
    _check_arguments(model, transitions, gradient_steps, batch_size, rounds, critic_steps)
    env = model.get_env()
    on_policy = getattr(model, "replay_buffer", None) is None
    dataset = _dataset(model, transitions, env.num_envs, on_policy)
    optimizer = model.actor_optimizer()
    if learning_rate is not None:
        for group in optimizer.param_groups:
            group["lr"] = float(learning_rate)
    logger = _logger(model)
    result: dict[str, Any] = {
        "actor_loss": [], "critic_loss": [], "transitions": 0, "collect_s": 0.0, "train_s": 0.0, "critic_s": 0.0
    }
    expert_steps, obs = 0, env.reset()
    per_round = [_share(transitions, rounds, k) for k in range(rounds)]
    steps_per_round = [_share(gradient_steps, rounds, k) for k in range(rounds)]
    for k in range(rounds):
        probability = float(beta(k) if callable(beta) else beta)
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"behaviour_clone: beta must lie in [0, 1], got {probability} in round {k}")
        start = time.perf_counter()
        obs, acted = _collect(model, expert, dataset, obs, math.ceil(per_round[k] / env.num_envs), probability)
        expert_steps += acted
        result["transitions"] += math.ceil(per_round[k] / env.num_envs) * env.num_envs
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
    model: Any, expert: Expert, buffer: GraphReplayBuffer, obs: dict, steps: int, probability: float
) -> tuple[dict, int]:
    """Step the VecEnv ``steps`` times, store each transition with its expert label; return the last
    observation and the number of sub-environment steps acted by the expert."""
    env, policy = model.get_env(), model.policy
    n_envs, max_nodes = env.num_envs, buffer.max_nodes
    rng = np.random.default_rng(np.random.randint(2**31))  # noqa: NPY002 (follows the model's seed)
    acted = 0
    for _ in range(steps):
        labels = checked_expert_actions(expert(obs), n_envs, max_nodes, obs["node_mask"])
        use_expert = rng.random(n_envs) < probability
        action = labels
        if not use_expert.all():
            with torch.no_grad():
                own, _ = policy.predict(obs, deterministic=True)
            action = np.where(use_expert[:, None], np.clip(labels, env.action_space.low, env.action_space.high), own)
        acted += int(use_expert.sum())
        new_obs, rewards, dones, infos = env.step(action)
        stored = np.array(action, dtype=np.float32, copy=True)
        for i, info in enumerate(infos):  # one per environment, as SB3's _store_transition
            if EXECUTED_ACTION in info:
                stored[i] = np.asarray(info[EXECUTED_ACTION], dtype=np.float32).reshape(max_nodes)
        buffer.add(
            obs,
            _next_observations(new_obs, dones, infos),
            expert_targets(policy, stored),
            _original_rewards(model, rewards),
            dones,
            infos,
            expert_action=expert_targets(policy, labels),
        )
        obs = new_obs
    return obs, acted


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
