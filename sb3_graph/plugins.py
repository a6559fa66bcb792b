"""Domains plug into sb3-graph through package entry points; ``sb3_graph`` names none of them.

A package that provides graph environments declares, in its ``pyproject.toml``::

    [project.entry-points."sb3_graph.commands"]
    mydomain = "mydomain.plugin:COMMANDS"        # {"name": ("module", "one-line help")}, as sb3_graph.cli.COMMANDS

    [project.entry-points."sb3_graph.tuning"]
    mydomain = "mydomain.plugin:TUNING"          # {"EnvIdPrefix": ("module:evaluator", "module:preset" or "none")}

    [project.entry-points."sb3_graph.gym_packages"]
    mydomain = "mydomain"                        # importing it registers its gymnasium environments

    [project.entry-points."sb3_graph.experts"]
    mydomain = "mydomain.plugin:EXPERTS"         # {"EnvIdPrefix": ("module:make_expert", "what a spec may be")}

    [project.entry-points."sb3_graph.planner_configs"]
    mydomain = "mydomain.plugin:PLANNER_CONFIGS" # {"EnvIdPrefix": ("module:planner_config", "what it records")}

- **commands**: each becomes ``sb3-graph <name>``; its module provides ``add_arguments(parser)`` and
  ``run(args) -> int`` and raises :class:`sb3_graph.commands.UserError` for a user's mistake. A
  command of the package itself keeps its name over a domain's.
- **tuning**: ``sb3-graph tune --env <id>`` with an id that starts with the prefix uses that
  evaluator (``evaluate(model, env_id, env_kwargs, episodes, seed) -> metrics``) and env preset
  unless ``--evaluator``/``--env-preset`` are given.
- **experts**: ``sb3-graph train --pretrain-from SPEC`` (and the ``pretrain_from`` key of an
  experiment) with an env id that starts with the prefix clones ``make_expert(SPEC, vec_env)``, a
  callable ``expert(obs) -> (n_envs, max_nodes)`` actions (see :func:`sb3_graph.behaviour_clone`).
  The toy task's expert (``GraphMaxNeighbour``: ``exact``) is the package's own.
- **planner_configs**: ``sb3-graph export`` of a model in a run folder of ``sb3-graph train`` (its
  ``run.json`` and ``config.yml``), without ``--planner-config``, stores ``planner_config(env_config)``
  (the run's ``env_kwargs["config"]``) as the file's planner configuration: what the environment did
  around the policy in training, which the domain's planner must do again.
- **gym_packages**: imported by ``sb3-graph train`` (and ``tune`` for a domain's env id) when
  ``--gym-packages`` is not given.

The mappings are plain strings, so that listing the commands imports no command module. Entry
points are read from the installed package metadata (``pip install -e .`` writes them); a plugin
that cannot be loaded is left out with a one-line warning on stderr.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from importlib import metadata
from typing import Any

COMMANDS_GROUP = "sb3_graph.commands"
TUNING_GROUP = "sb3_graph.tuning"
GYM_PACKAGES_GROUP = "sb3_graph.gym_packages"
EXPERTS_GROUP = "sb3_graph.experts"
PLANNER_CONFIGS_GROUP = "sb3_graph.planner_configs"
#: The package's own experts (env id prefix -> (factory, what a spec may be)), before the domains'.
BUILTIN_EXPERTS: dict[str, tuple[str, str]] = {
    "GraphMaxNeighbour": ("sb3_graph.toy_envs:make_expert", "exact (the task's exact answer)"),
}
#: Folders searched for installed distributions (``None``: ``sys.path``, as ``importlib.metadata``).
SEARCH_PATH: list[str] | None = None


def entry_points(group: str) -> list[metadata.EntryPoint]:
    """The entry points of ``group``, one per name (the first found on the search path wins)."""
    seen: dict[str, metadata.EntryPoint] = {}
    distributions = set()
    for distribution in metadata.distributions(**({} if SEARCH_PATH is None else {"path": list(SEARCH_PATH)})):
        name = (distribution.metadata["Name"] or "").lower().replace("-", "_")
        if name in distributions:  # an older copy further down the path, as importlib.metadata skips it
            continue
        distributions.add(name)
        for point in distribution.entry_points:
            if point.group == group:
                seen.setdefault(point.name, point)
    return list(seen.values())


def _warn(point: metadata.EntryPoint, problem: str) -> None:
    print(f"sb3-graph: plugin {point.name!r} ({point.group} = {point.value!r}) left out: {problem}", file=sys.stderr)


def _pairs(group: str) -> dict[str, tuple[str, str]]:
    """Every plugin's ``name -> (str, str)`` mapping of ``group``, merged (first plugin wins a clash)."""
    merged: dict[str, tuple[str, str]] = {}
    for point in entry_points(group):
        try:
            value: Any = point.load()
        except Exception as error:  # noqa: BLE001 - a broken plugin must not break the other commands
            _warn(point, f"{type(error).__name__}: {error}")
            continue
        if not isinstance(value, Mapping) or not all(
            isinstance(key, str) and isinstance(item, (tuple, list)) and len(item) == 2 and all(
                isinstance(part, str) for part in item
            )
            for key, item in value.items()
        ):
            _warn(point, "expected a mapping of names to (string, string) pairs")
            continue
        for key, item in value.items():
            merged.setdefault(key, (item[0], item[1]))
    return merged


def domain_commands() -> dict[str, tuple[str, str]]:
    """``command -> (module, one-line help)`` of every installed domain."""
    return _pairs(COMMANDS_GROUP)


def tuning_defaults() -> dict[str, tuple[str, str]]:
    """``env id prefix -> (evaluator, env preset)`` of every installed domain."""
    return _pairs(TUNING_GROUP)


def gym_packages() -> list[str]:
    """The modules whose import registers the installed domains' environments (not imported here)."""
    return [point.value for point in entry_points(GYM_PACKAGES_GROUP)]


def expert_factories() -> dict[str, tuple[str, str]]:
    """``env id prefix -> (expert factory, what a spec may be)`` of the package and every installed domain."""
    return {**_pairs(EXPERTS_GROUP), **BUILTIN_EXPERTS}


def expert_factory(env_id: str) -> tuple[str, str] | None:
    """The expert factory whose prefix is the longest that starts ``env_id``, or ``None``."""
    return _longest_prefix(expert_factories(), env_id)


def planner_config_factory(env_id: str) -> tuple[str, str] | None:
    """``(module:function, what it records)`` of the domain whose prefix is the longest that starts ``env_id``:
    the function turns a run's environment config into a policy file's planner configuration; ``None`` if no
    domain has one."""
    return _longest_prefix(_pairs(PLANNER_CONFIGS_GROUP), env_id)


def _longest_prefix(mapping: dict[str, tuple[str, str]], env_id: str) -> tuple[str, str] | None:
    matches = [prefix for prefix in mapping if env_id.startswith(prefix)]
    return mapping[max(matches, key=len)] if matches else None
