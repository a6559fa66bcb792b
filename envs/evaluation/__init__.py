"""How planners are compared: like-for-like runs on scenario files, their metrics and reports.

- :mod:`~envs.evaluation.harness`: jobs (one planner on one scenario file), episodes, :func:`evaluate`,
- :mod:`~sb3_graph.common.executors`: where the jobs run (local processes, Dask, Ray),
- :mod:`~envs.evaluation.metrics`: a run's vehicle log and its metrics row, the summaries,
- :mod:`~envs.evaluation.comparison`: paired differences between planners with intervals,
- :mod:`~envs.evaluation.report`: ``evaluate``'s report (``report.md``, the figures, the CSV files),
- :mod:`~envs.evaluation.sweep`: planners across demand levels, with their capacity,
- :mod:`~envs.evaluation.tuning`: the objective of ``sb3-graph tune`` (a trained model on validation scenarios).
- :mod:`~envs.evaluation.recording`: one episode run with a frame per step, for ``sb3-graph record``.

This package re-exports the harness's names (``from envs.evaluation import evaluate, run_episode``), loaded on
first use; the other modules load only when imported (the report and the sweep pull in matplotlib).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# The harness's names load on first use (PEP 562 ``__getattr__``): a command's parser imports
# ``sb3_graph.common.executors`` for its choices, and ``--help`` must not pay for torch and highway-env.
_HARNESS_NAMES = (
    "EVALUATION_CONFIG",
    "SCENARIO_SUFFIX",
    "Job",
    "check_scenarios",
    "env_config",
    "evaluate",
    "evaluation_env_kwargs",
    "find_scenarios",
    "generate_scenarios",
    "is_baseline",
    "layout_of",
    "planned_accelerations",
    "preset_returns",
    "run_episode",
    "run_job",
    "run_seed",
    "run_shared_job",
)

if TYPE_CHECKING:
    from envs.evaluation.harness import (  # noqa: F401
        EVALUATION_CONFIG,
        SCENARIO_SUFFIX,
        Job,
        check_scenarios,
        env_config,
        evaluate,
        evaluation_env_kwargs,
        find_scenarios,
        generate_scenarios,
        is_baseline,
        layout_of,
        planned_accelerations,
        preset_returns,
        run_episode,
        run_job,
        run_seed,
        run_shared_job,
    )

__all__ = list(_HARNESS_NAMES)


def __getattr__(name: str) -> Any:
    if name in _HARNESS_NAMES:
        return getattr(importlib.import_module("envs.evaluation.harness"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
