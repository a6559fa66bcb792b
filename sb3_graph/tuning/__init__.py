"""Optuna tuning of reward weights and algorithm settings on task metrics (``sb3-graph tune``, ``tune-report``).

Environment-agnostic: the task metrics come from an evaluator plug-in (``module:function``) and
the reduced environment from a preset plug-in; a domain provides both through its
``sb3_graph.tuning`` entry point (:mod:`sb3_graph.plugins`).
Modules: :mod:`~sb3_graph.tuning.storage` (URL -> Optuna storage),
:mod:`~sb3_graph.tuning.search_space`, :mod:`~sb3_graph.tuning.objectives`,
:mod:`~sb3_graph.tuning.runner` (one trial), :mod:`~sb3_graph.tuning.report`,
:mod:`~sb3_graph.tuning.pretrain` (cloning once per study); the two commands live in ``sb3_graph.commands.tune`` and
``sb3_graph.commands.tune_report``. See ``docs/tuning.md``.
"""
