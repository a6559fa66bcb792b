"""What the intersection domain plugs into sb3-graph, declared as entry points in ``pyproject.toml``
(groups ``sb3_graph.commands``, ``sb3_graph.tuning``, ``sb3_graph.experts``, ``sb3_graph.planner_configs`` and
``sb3_graph.gym_packages``; see :mod:`sb3_graph.plugins`). Plain strings only: reading this module imports no
command.
"""

from __future__ import annotations

#: ``sb3-graph <command>`` -> (module with ``add_arguments``/``run``, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "evaluate": ("envs.commands.evaluate", "compare planners on the same scenarios and write a report"),
    "sweep": ("envs.commands.sweep", "compare planners across traffic demand levels, with their capacity"),
    "aggregate": ("envs.commands.aggregate", "IQM and 95 % intervals of evaluate reports over seeds and scenarios"),
    "ind": ("envs.commands.ind", "replay inD recordings through the planners"),
    "record": ("envs.commands.record", "watch one episode: planners on a scenario as a GIF, MP4 or HTML animation"),
    "serve": ("envs.commands.serve", "run a planner as an edge server: scenes in, one acceleration per vehicle out"),
    "reward-check": ("envs.commands.reward_check", "rank correlation of each reward's returns with flow and delay"),
}

#: ``sb3-graph tune``: env id prefix -> (metric evaluator, reduced env kwargs of the trials)
TUNING: dict[str, tuple[str, str]] = {
    "CoopIntersection": ("envs.evaluation.tuning:evaluate_model", "envs.evaluation.tuning:tuning_env_kwargs"),
}

#: ``sb3-graph train --pretrain-from PLANNER``: env id prefix -> (expert factory, what PLANNER may be)
EXPERTS: dict[str, tuple[str, str]] = {
    "CoopIntersection": (
        "envs.planners.expert:make_expert",
        "a planner word of evaluate (aim, fifo, pr, fullthrottle, signal, file.py:Class, a policy file)",
    ),
}

#: ``sb3-graph export`` of a run's model: env id prefix -> (planner config of the run's env config, what it records)
PLANNER_CONFIGS: dict[str, tuple[str, str]] = {
    "CoopIntersection": (
        "envs.planners.gnn:planner_config_from_env",
        "the action's type, scale and glide version, the observation's features, a residual base",
    ),
}
