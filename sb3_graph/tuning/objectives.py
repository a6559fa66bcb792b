"""The objectives, measured on task metrics (never on the training reward: the weights change it).

- ``flow``: maximize the flow rate (veh/s) subject to ``collision_rate <= max_collision_rate``.
- ``flow-delay``: maximize ``flow_rate - weight * delay_mean`` (veh/s minus ``weight`` per second
  of mean delay; default weight :data:`DEFAULT_WEIGHTS`), under the same constraint.
- ``flow-stop``: maximize ``flow_rate - weight * stop_ratio`` (the share of vehicles that stopped),
  under the same constraint.
- ``pareto``: flow rate up, mean delay down, stop ratio down with NSGA-II, under the same
  constraint; the result is the (feasible) Pareto front. Multi-objective studies cannot prune, so
  each trial is evaluated once, at its end.

The constraint is recorded with :meth:`optuna.Trial.set_constraint`, so the TPE and NSGA-II
samplers model feasibility and :attr:`optuna.Study.best_trial` (``best_trials``) holds *feasible*
trials. The single-objective studies report each intermediate evaluation's value, so a pruner
(median, successive halving or Hyperband, see :mod:`sb3_graph.tuning.pruners`) stops poor trials
early.

An evaluator returns a mapping of metric names to numbers; the names used here are
:data:`FLOW`, :data:`COLLISION`, :data:`STOP` and :data:`DELAY`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import optuna

FLOW, COLLISION, STOP, DELAY = "flow_rate", "collision_rate", "stop_ratio", "delay_mean"
OBJECTIVES = ("flow", "flow-delay", "flow-stop", "pareto")
#: Default ``weight`` of the combined objectives: 0.01 veh/s per second of mean delay (10 s of delay
#: cost as much as 0.1 veh/s of flow), 0.2 veh/s per unit of stop ratio (half the vehicles stopping
#: costs 0.1 veh/s).
DEFAULT_WEIGHTS = {"flow-delay": 0.01, "flow-stop": 0.2}
_PENALIZED = {"flow-delay": DELAY, "flow-stop": STOP}
DEFAULT_MAX_COLLISION_RATE = 0.02
DEFAULT_POPULATION = 10


@dataclass(frozen=True)
class Objective:
    """What a study optimizes.

    :param name: one of :data:`OBJECTIVES`
    :param metrics: the metrics read, in order: one per objective value, or the terms of
        ``coefficients``
    :param directions: ``"maximize"``/``"minimize"`` per objective value
    :param max_collision_rate: the constraint on the collision rate (every objective has it)
    :param coefficients: ``None``, or one factor per metric: the single value is
        ``sum(coefficient * metric)`` (``flow-delay``, ``flow-stop``)
    """

    name: str
    metrics: tuple[str, ...]
    directions: tuple[str, ...]
    max_collision_rate: float = DEFAULT_MAX_COLLISION_RATE
    coefficients: tuple[float, ...] | None = None

    @property
    def prunable(self) -> bool:
        """Single-objective studies report intermediate values; Optuna cannot prune multi-objective ones."""
        return len(self.directions) == 1

    @property
    def labels(self) -> tuple[str, ...]:
        """One name per objective value (the study's ``metrics`` attribute, the report's columns)."""
        if self.coefficients is None:
            return self.metrics
        terms = [name if c == 1 else f"{c:g} * {name}" for c, name in zip(self.coefficients, self.metrics)]
        return (" + ".join(terms).replace("+ -", "- "),)

    def required(self) -> tuple[str, ...]:
        """Metrics the evaluator must return (finite) for this objective."""
        return tuple(dict.fromkeys((*self.metrics, COLLISION)))

    def values(self, metrics: Mapping[str, float]) -> float | tuple[float, ...]:
        """The objective value(s) of a trial from its metrics.

        :param metrics: the evaluator's output
        :return: a float (single objective) or a tuple (one per metric)
        :raises KeyError: a required metric is missing
        """
        values = tuple(float(metrics[name]) for name in self.metrics)
        if self.coefficients is not None:
            return float(sum(c * v for c, v in zip(self.coefficients, values)))
        return values[0] if len(values) == 1 else values

    def constraint(self, metrics: Mapping[str, float]) -> float:
        """``collision_rate - max_collision_rate`` (feasible when <= 0)."""
        return float(metrics[COLLISION]) - self.max_collision_rate

    def sampler(
        self, seed: int | None = None, population_size: int = DEFAULT_POPULATION
    ) -> optuna.samplers.BaseSampler:
        """TPE for a single objective (constraint-aware, constant liar for parallel workers), NSGA-II for ``pareto``.

        :param seed: sampler seed (``None``: fresh entropy; give each worker its own)
        :param population_size: NSGA-II population (trials per generation)
        """
        if self.prunable:
            return optuna.samplers.TPESampler(seed=seed, constant_liar=True)
        return optuna.samplers.NSGAIISampler(population_size=population_size, seed=seed)

    def pruner(
        self,
        kind: str = "median",
        timesteps: int = 1,
        evaluations: int = 3,
        min_resource: int | None = None,
        reduction_factor: int = 3,
        n_startup_trials: int = 4,
    ) -> optuna.pruners.BasePruner:
        """The pruner of this objective: ``kind`` (see :mod:`sb3_graph.tuning.pruners`), none for ``pareto``.

        :param kind: ``median``, ``successive-halving``, ``hyperband`` or ``none``
        :param timesteps: training steps of a full trial
        :param evaluations: evaluations of a full trial
        :param min_resource: SHA/Hyperband: the first rung [steps] (default from ``evaluations``)
        :param reduction_factor: SHA/Hyperband: factor between two rungs
        :param n_startup_trials: median: finished trials before any pruning
        """
        from sb3_graph.tuning.pruners import make_pruner

        if not self.prunable:
            return optuna.pruners.NopPruner()
        return make_pruner(kind, timesteps, evaluations, min_resource, reduction_factor, n_startup_trials)


def make_objective(
    name: str, max_collision_rate: float = DEFAULT_MAX_COLLISION_RATE, weight: float | None = None
) -> Objective:
    """Build an objective by name.

    :param name: one of :data:`OBJECTIVES`
    :param max_collision_rate: the constraint, in ``[0, 1]``
    :param weight: ``flow-delay``/``flow-stop``: the factor of the penalized metric, >= 0 (default
        :data:`DEFAULT_WEIGHTS`); refused for the other objectives
    :raises ValueError: an unknown name, an impossible rate or weight
    """
    if not (isinstance(max_collision_rate, (int, float)) and 0.0 <= max_collision_rate <= 1.0):
        raise ValueError(f"max_collision_rate must be in [0, 1], got {max_collision_rate!r}")
    if name not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {name!r}")
    rate = float(max_collision_rate)
    if name in _PENALIZED:
        weight = DEFAULT_WEIGHTS[name] if weight is None else weight
        if (
            isinstance(weight, bool)
            or not isinstance(weight, (int, float))
            or not (math.isfinite(weight) and weight >= 0)
        ):
            raise ValueError(f"the weight of objective {name!r} must be a finite number >= 0, got {weight!r}")
        return Objective(name, (FLOW, _PENALIZED[name]), ("maximize",), rate, (1.0, -float(weight)))
    if weight is not None:
        raise ValueError(f"objective {name!r} takes no weight (only {' and '.join(_PENALIZED)} do)")
    if name == "flow":
        return Objective("flow", (FLOW,), ("maximize",), rate)
    return Objective("pareto", (FLOW, DELAY, STOP), ("maximize", "minimize", "minimize"), rate)


def check_metrics(metrics: Mapping[str, float], objective: Objective) -> str | None:
    """Why the metrics cannot be scored (a missing or non-finite required metric), or ``None``."""
    missing = [name for name in objective.required() if name not in metrics]
    if missing:
        return f"the evaluator returned no {missing} (it returned {sorted(metrics)})"
    bad = {name: metrics[name] for name in objective.required() if not math.isfinite(float(metrics[name]))}
    if bad:
        return f"non-finite metrics {bad}"
    return None
