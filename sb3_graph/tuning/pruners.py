"""Multi-fidelity pruning: which pruner stops a trial, and at which training steps a trial is evaluated.

A trial reports a *task metric* (the objective's value, e.g. the validation flow rate) at its
intermediate evaluations with ``trial.report(value, step)``, ``step`` being the environment steps
trained so far; the pruner compares it with the other trials at the same step and stops the poor
ones, so most trials end early and the survivors get the whole budget (``--timesteps``).

- ``median``: :class:`~optuna.pruners.MedianPruner`, after ``n_startup_trials`` finished trials;
  evaluations are spread evenly (``--evaluations`` per trial, the last at the end).
- ``successive-halving``: :class:`~optuna.pruners.SuccessiveHalvingPruner` (asynchronous SHA). Rung
  ``k`` is at ``min_resource * reduction_factor**k`` steps; a trial goes on past a rung only if its
  value is in the top ``1 / reduction_factor`` of the trials that reached the rung.
- ``hyperband``: :class:`~optuna.pruners.HyperbandPruner`, several SHA brackets with different
  early-stopping rates (trials are assigned to brackets by their number), from ``min_resource`` to
  the full budget.
- ``none``: :class:`~optuna.pruners.NopPruner`; evaluations still run (the learning curve is kept).

For SHA and Hyperband the evaluations fall on the rungs (:func:`evaluation_steps`), a geometric
schedule: evaluating between rungs would cost validation episodes and decide nothing.
"""

from __future__ import annotations

import optuna

PRUNERS = ("median", "successive-halving", "hyperband", "none")
RUNG_PRUNERS = ("successive-halving", "hyperband")
DEFAULT_REDUCTION_FACTOR = 3
DEFAULT_STARTUP_TRIALS = 4


def check_pruner(kind: str) -> str:
    """The pruner name, or a ``ValueError`` naming the allowed ones."""
    if kind not in PRUNERS:
        raise ValueError(f"pruner must be one of {PRUNERS}, got {kind!r}")
    return kind


def default_min_resource(timesteps: int, evaluations: int, reduction_factor: int = DEFAULT_REDUCTION_FACTOR) -> int:
    """The first rung such that a trial that survives every rung is evaluated ``evaluations`` times.

    :param timesteps: training steps of a full trial
    :param evaluations: evaluations of a full trial, the last at its end
    :param reduction_factor: factor between two rungs
    :return: ``ceil(timesteps / reduction_factor ** (evaluations - 1))``, at least 1 (rounded up, so
        that the last rung below the budget is not a few steps short of the final evaluation)
    """
    return max(1, -(-int(timesteps) // int(reduction_factor) ** max(int(evaluations) - 1, 0)))


def evaluation_steps(
    kind: str,
    timesteps: int,
    evaluations: int,
    min_resource: int | None = None,
    reduction_factor: int = DEFAULT_REDUCTION_FACTOR,
) -> tuple[int, ...]:
    """Training steps of a trial's intermediate evaluations (the final one, at ``timesteps``, is not included).

    :param kind: one of :data:`PRUNERS`
    :param timesteps: training steps of a full trial
    :param evaluations: ``median``/``none``: evaluations per trial, evenly spaced, the last at the end
    :param min_resource: SHA/Hyperband: the first rung [steps] (default :func:`default_min_resource`)
    :param reduction_factor: SHA/Hyperband: factor between two rungs, at least 2
    :return: increasing steps, each below ``timesteps``
    """
    check_pruner(kind)
    if kind not in RUNG_PRUNERS:
        return tuple(sorted({timesteps * k // evaluations for k in range(1, evaluations)} - {0}))
    if reduction_factor < 2:
        raise ValueError(f"reduction factor must be at least 2, got {reduction_factor}")
    step = min_resource if min_resource is not None else default_min_resource(timesteps, evaluations, reduction_factor)
    if not 1 <= step < timesteps:
        raise ValueError(f"min resource must be in [1, {timesteps}) steps (below the trial's budget), got {step}")
    steps = []
    while step < timesteps:
        steps.append(int(step))
        step *= reduction_factor
    return tuple(steps)


def make_pruner(
    kind: str,
    timesteps: int,
    evaluations: int = 3,
    min_resource: int | None = None,
    reduction_factor: int = DEFAULT_REDUCTION_FACTOR,
    n_startup_trials: int = DEFAULT_STARTUP_TRIALS,
) -> optuna.pruners.BasePruner:
    """The Optuna pruner named ``kind`` (see the module docstring), its resource counted in training steps.

    :param kind: one of :data:`PRUNERS`
    :param timesteps: training steps of a full trial (Hyperband's maximum resource)
    :param evaluations: evaluations of a full trial (gives the default ``min_resource``)
    :param min_resource: SHA/Hyperband: the first rung [steps]
    :param reduction_factor: SHA/Hyperband: factor between two rungs
    :param n_startup_trials: median: finished trials before any pruning
    """
    check_pruner(kind)
    if kind == "none":
        return optuna.pruners.NopPruner()
    if kind == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=n_startup_trials, n_warmup_steps=0)
    first = evaluation_steps(kind, timesteps, evaluations, min_resource, reduction_factor)[0]
    if kind == "successive-halving":
        return optuna.pruners.SuccessiveHalvingPruner(min_resource=first, reduction_factor=reduction_factor)
    return optuna.pruners.HyperbandPruner(
        min_resource=first, max_resource=int(timesteps), reduction_factor=reduction_factor
    )
