"""The two objectives, measured on task metrics (never on the training reward: the weights change it).

- ``flow``: maximize the flow rate (veh/s) subject to ``collision_rate <= max_collision_rate``.
  The constraint is recorded with :meth:`optuna.Trial.set_constraint`, so the TPE sampler models
  feasibility and :attr:`optuna.Study.best_trial` is the best *feasible* trial. Intermediate
  evaluations report the flow rate, so a pruner (median, successive halving or Hyperband, see
  :mod:`sb3_graph.tuning.pruners`) stops poor trials early.
- ``pareto``: flow rate up, collision rate down, stop ratio down with NSGA-II; the result is the
  Pareto front. Multi-objective studies cannot prune, so each trial is evaluated once, at its end.

An evaluator returns a mapping of metric names to numbers; the names used here are
:data:`FLOW`, :data:`COLLISION` and :data:`STOP`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import optuna

FLOW, COLLISION, STOP = "flow_rate", "collision_rate", "stop_ratio"
OBJECTIVES = ("flow", "pareto")
DEFAULT_MAX_COLLISION_RATE = 0.02
DEFAULT_POPULATION = 10


@dataclass(frozen=True)
class Objective:
    """What a study optimizes.

    :param name: ``"flow"`` or ``"pareto"``
    :param metrics: the metric of each objective value, in order
    :param directions: ``"maximize"``/``"minimize"`` per value
    :param max_collision_rate: the ``flow`` objective's constraint on the collision rate
    """

    name: str
    metrics: tuple[str, ...]
    directions: tuple[str, ...]
    max_collision_rate: float = DEFAULT_MAX_COLLISION_RATE

    @property
    def prunable(self) -> bool:
        """Single-objective studies report intermediate values; Optuna cannot prune multi-objective ones."""
        return len(self.metrics) == 1

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
        return values[0] if len(values) == 1 else values

    def constraint(self, metrics: Mapping[str, float]) -> float | None:
        """``collision_rate - max_collision_rate`` for ``flow`` (feasible when <= 0), ``None`` for ``pareto``."""
        if self.name != "flow":
            return None
        return float(metrics[COLLISION]) - self.max_collision_rate

    def sampler(
        self, seed: int | None = None, population_size: int = DEFAULT_POPULATION
    ) -> optuna.samplers.BaseSampler:
        """TPE for ``flow`` (constraint-aware, constant liar for parallel workers), NSGA-II for ``pareto``.

        :param seed: sampler seed (``None``: fresh entropy; give each worker its own)
        :param population_size: NSGA-II population (trials per generation)
        """
        if self.name == "flow":
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


def make_objective(name: str, max_collision_rate: float = DEFAULT_MAX_COLLISION_RATE) -> Objective:
    """Build an objective by name.

    :param name: one of :data:`OBJECTIVES`
    :param max_collision_rate: constraint of ``flow``, in ``[0, 1]``
    :raises ValueError: an unknown name or an impossible rate
    """
    if not (isinstance(max_collision_rate, (int, float)) and 0.0 <= max_collision_rate <= 1.0):
        raise ValueError(f"max_collision_rate must be in [0, 1], got {max_collision_rate!r}")
    if name == "flow":
        return Objective("flow", (FLOW,), ("maximize",), float(max_collision_rate))
    if name == "pareto":
        return Objective(
            "pareto", (FLOW, COLLISION, STOP), ("maximize", "minimize", "minimize"), float(max_collision_rate)
        )
    raise ValueError(f"objective must be one of {OBJECTIVES}, got {name!r}")


def check_metrics(metrics: Mapping[str, float], objective: Objective) -> str | None:
    """Why the metrics cannot be scored (a missing or non-finite required metric), or ``None``."""
    missing = [name for name in objective.required() if name not in metrics]
    if missing:
        return f"the evaluator returned no {missing} (it returned {sorted(metrics)})"
    bad = {name: metrics[name] for name in objective.required() if not math.isfinite(float(metrics[name]))}
    if bad:
        return f"non-finite metrics {bad}"
    return None
