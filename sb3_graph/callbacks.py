"""Training callbacks that any graph environment can use (SB3 ``BaseCallback`` subclasses).

They are referenced from rl-zoo3 style YAML by dotted name, e.g.::

    callback:
      - sb3_graph.callbacks.LinearScheduleCallback:
          method: set_spawn_probability
          start: 0.01
          end: 0.05
          end_fraction: 0.5
      - sb3_graph.callbacks.InfoLoggerCallback:
          keys: [reward_terms]
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback

#: ``info`` key of an environment whose vertices come and go: for each vertex of the new observation,
#: its slot in the previous one (``-1`` for a new vertex), see :class:`VertexNoiseCallback`
VERTEX_ORIGIN = "vertex_origin"


class LinearScheduleCallback(BaseCallback):
    """Raise (or lower) an environment parameter linearly with the training progress.

    At every ``update_every`` steps the value is recomputed from ``model.num_timesteps`` and
    passed to every training environment as ``env.<method>(value)`` through
    ``VecEnv.env_method``; after ``end_fraction`` of the run it stays at ``end`` (the paper
    raises the spawn probability until it saturates at 5 % per step). The value is logged as
    ``curriculum/<method>``.

    :param method: name of the environment method that takes the new value
    :param start: value at step 0
    :param end: value from ``end_fraction`` of the run on
    :param end_fraction: share of the total timesteps after which ``end`` is reached, in (0, 1]
    :param total_timesteps: the schedule's length; ``None`` takes the ``learn`` call's total
    :param update_every: steps between two updates
    :param verbose: verbosity level
    """

    def __init__(
        self,
        method: str,
        start: float,
        end: float,
        end_fraction: float = 0.5,
        total_timesteps: int | None = None,
        update_every: int = 1000,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if not isinstance(method, str) or not method:
            raise ValueError(f"LinearScheduleCallback: method must be a method name, got {method!r}")
        if not 0.0 < end_fraction <= 1.0:
            raise ValueError(f"LinearScheduleCallback: end_fraction must be in (0, 1], got {end_fraction}")
        if update_every < 1:
            raise ValueError(f"LinearScheduleCallback: update_every must be >= 1, got {update_every}")
        self.method = method
        self.start = float(start)
        self.end = float(end)
        self.end_fraction = float(end_fraction)
        self.total_timesteps = total_timesteps
        self.update_every = int(update_every)
        self.value: float | None = None
        self._last_update = -1

    def value_at(self, step: int) -> float:
        """The scheduled value after ``step`` environment steps."""
        # model._total_timesteps is the absolute total of the current learn() call, resumes included
        total = self.total_timesteps or getattr(self.model, "_total_timesteps", 0) or 1
        progress = min(1.0, step / (self.end_fraction * total))
        return self.start + progress * (self.end - self.start)

    def _apply(self) -> None:
        self.value = self.value_at(self.num_timesteps)
        self.training_env.env_method(self.method, self.value)
        self.logger.record(f"curriculum/{self.method}", self.value)
        self._last_update = self.num_timesteps

    def _on_training_start(self) -> None:
        self._apply()

    def _on_step(self) -> bool:
        if self.num_timesteps - self._last_update >= self.update_every:
            self._apply()
        return True


class InfoLoggerCallback(BaseCallback):
    """Log the means of numeric entries that environments report in ``info``.

    For each name in ``keys``, ``info[name]`` may be a number, a dictionary of numbers (e.g. the
    reward terms) or a list of events (e.g. the ids of vehicles that crossed the intersection in
    the step, logged as ``<name>_count``); their means per step between two logger dumps are
    recorded as ``info/<name>/<entry>`` (TensorBoard, CSV, stdout: wherever the logger writes).
    A 0-d array counts as its value; entries without a mean (strings, ``None``, other objects) are
    skipped.

    :param keys: names of ``info`` entries to log
    :param verbose: verbosity level
    """

    def __init__(self, keys: Sequence[str] = ("reward_terms",), verbose: int = 0) -> None:
        super().__init__(verbose)
        self.keys = [keys] if isinstance(keys, str) else list(keys)

    def _record(self, name: str, value: Any) -> None:
        if isinstance(value, dict):
            for entry, sub in value.items():
                self._record(f"{name}/{entry}", sub)
        elif isinstance(value, np.ndarray) and value.ndim == 0:
            self._record(name, value.item())  # a 0-d array is a number (or a string), not an event list
        elif isinstance(value, (list, tuple, np.ndarray)):
            # an event list (e.g. ids of vehicles that crossed this step): log how many
            self.logger.record_mean(f"info/{name}_count", float(len(value)))
        elif isinstance(value, (numbers.Real, np.bool_)) and np.isfinite(float(value)):
            # record_mean averages every value until the logger's next dump
            self.logger.record_mean(f"info/{name}", float(value))
        # anything else (a string, None, an object) has no mean: skipped

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            for key in self.keys:
                if key in info:
                    self._record(key, info[key])
        return True


class ActorWarmupCallback(BaseCallback):
    """Start from a zero action and hold the actor still while the critics learn its value.

    For a residual policy (the action corrects a base planner, zero reproduces it) the first
    policy should be the base planner, and the first actor updates should follow a critic that
    has seen the base planner's data, not a random one. At the start of training this callback
    sets the actor's output layer to zero (``zero_output``; the actor's ``head``, and the target
    actor's, so ``tanh(0) = 0`` on every vertex) and freezes the actor's parameters; after
    ``steps`` environment steps it unfreezes them. The critics train all along (TD3's actor loss
    still runs, but moves no frozen parameter).

    :param steps: environment steps (``num_timesteps``) before the actor learns
    :param zero_output: set the actor's output layer to zero at the start
    :param verbose: verbosity level
    """

    def __init__(self, steps: int, zero_output: bool = True, verbose: int = 0) -> None:
        super().__init__(verbose)
        if not isinstance(steps, numbers.Integral) or isinstance(steps, bool) or steps < 0:
            raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
        self.steps = int(steps)
        self.zero_output = bool(zero_output)
        self.frozen = False

    def _actors(self) -> list[Any]:
        policy = self.model.policy
        actors = [getattr(policy, name, None) for name in ("actor", "actor_target")]
        actors = [a for a in actors if a is not None]
        if not actors or not all(hasattr(a, "head") for a in actors):
            raise ValueError("ActorWarmupCallback needs a policy whose actor has a `head` layer (the graph policies)")
        return actors

    def _set_frozen(self, frozen: bool) -> None:
        for parameter in self.model.policy.actor.parameters():
            parameter.requires_grad_(not frozen)
        self.frozen = frozen

    def _on_training_start(self) -> None:
        import torch as th

        actors = self._actors()
        if self.zero_output and self.model.num_timesteps == 0:
            with th.no_grad():
                for actor in actors:
                    for parameter in actor.head.parameters():
                        parameter.zero_()
        if self.model.num_timesteps < self.steps:
            self._set_frozen(True)

    def _on_step(self) -> bool:
        if self.frozen and self.model.num_timesteps >= self.steps:
            self._set_frozen(False)
        return True


class VertexNoiseCallback(BaseCallback):
    """Keep each vertex's exploration noise with its vertex when vertices leave or join.

    Time-correlated action noise (SB3's ``OrnsteinUhlenbeckActionNoise``) keeps one state per
    action slot, and a graph's slot ``i`` is vertex ``i`` of the observation. When a vertex leaves,
    the vertices after it move up one slot: without this callback each of them inherits the state
    of its predecessor, and a vertex that joins inherits a state built up for another one, so the
    noise of a vertex is correlated in time only while the graph keeps its vertices. An
    environment that reports :data:`VERTEX_ORIGIN` in ``info`` (for each vertex of the new
    observation its previous slot, ``-1`` for a new vertex) lets this callback move every state
    to its vertex's new slot after each step and start new vertices at the process's initial
    state (zero unless ``initial_noise`` was given); slots without a vertex are reset the same way.
    Noise without a state (``NormalActionNoise``) and steps without the key are left alone.

    :param verbose: verbosity level
    """

    def _on_step(self) -> bool:
        noise = self.model.action_noise
        if noise is None:
            return True
        processes = getattr(noise, "noises", [noise])  # VectorizedActionNoise: one per environment
        for info, process in zip(self.locals.get("infos", []), processes):
            origin = info.get(VERTEX_ORIGIN)
            if origin is None or not hasattr(process, "noise_prev"):
                continue
            origin = np.asarray(origin, dtype=np.int64).reshape(-1)
            state = np.asarray(process.noise_prev)
            if origin.size > state.shape[0] or (origin >= state.shape[0]).any():
                raise ValueError(
                    f"info[{VERTEX_ORIGIN!r}] names {origin.size} vertices or a slot past {state.shape[0] - 1}, "
                    f"but the action noise has {state.shape[0]} slots"
                )
            initial = getattr(process, "initial_noise", None)
            moved = np.zeros_like(state) if initial is None else np.array(initial, dtype=state.dtype, copy=True)
            known = origin >= 0
            moved[: origin.size][known] = state[origin[known]]
            process.noise_prev = moved
        return True


class FixedEpisodesEvalCallback(EvalCallback):
    """SB3's :class:`~stable_baselines3.common.callbacks.EvalCallback`, on the same validation episodes every time.

    SB3's callback resets its evaluation env without a seed, so its n-th validation draws the episodes that follow
    those of the one before: in a domain whose episodes differ much in difficulty (traffic demand, say), the
    validation curve then follows the episodes, and ``best_model.zip`` is picked by their draw. This one reseeds
    the evaluation env with ``seed`` before each validation, so that validations compare policies.

    :param eval_env: the evaluation environment (as SB3's)
    :param seed: seed of the first evaluation env at each validation (a VecEnv adds its index per env)
    :param kwargs: SB3's ``EvalCallback`` arguments
    """

    def __init__(self, eval_env: Any, seed: int, **kwargs: Any) -> None:
        super().__init__(eval_env, **kwargs)
        self.seed = int(seed)

    def _on_step(self) -> bool:
        if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
            self.eval_env.seed(self.seed)  # applied at the reset that starts the validation
        return super()._on_step()
