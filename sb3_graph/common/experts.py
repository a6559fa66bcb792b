"""The expert that a ``pretrain_from`` spec names for an environment, and the default budget of a cloning.

Both ``sb3-graph train`` (:mod:`sb3_graph.commands.train`) and a tuning study's cloning
(:mod:`sb3_graph.tuning.pretrain`) clone an expert into a model; this module is what they share. It imports no
network code, so that a command's ``--help`` can show the defaults.
"""

from __future__ import annotations

from typing import Any

from sb3_graph.plugins import expert_factories, expert_factory
from sb3_graph.registry import import_object

#: environment steps of demonstrations that a cloning collects unless the entry says (``pretrain_transitions``)
PRETRAIN_TRANSITIONS = 10_000
#: gradient steps of a cloning unless the entry says (``pretrain_steps``)
PRETRAIN_STEPS = 2_000


class ExpertError(ValueError):
    """No expert is known for the environment, or its factory refuses the spec (a user's mistake: one line)."""


def make_expert(spec: str, env_id: str, train_env: Any) -> Any:
    """The expert ``spec`` for ``env_id``'s environments, from the factory that the package or a domain
    declares for it (:func:`sb3_graph.plugins.expert_factory`).

    :param spec: the ``pretrain_from`` value (e.g. ``glide+shield``, or ``exact`` for the toy task)
    :param env_id: the environment id
    :param train_env: the VecEnv the expert labels
    :return: a callable ``expert(obs) -> (n_envs, max_nodes)`` actions
    :raises ExpertError: no factory for ``env_id``, or the factory refuses ``spec``
    """
    found = expert_factory(env_id)
    if found is None:
        raise ExpertError(
            f"pretrain_from: no expert is known for env {env_id!r} (experts exist for env ids starting with "
            f"{sorted(expert_factories())})"
        )
    try:
        return import_object(found[0])(spec, train_env)
    except ValueError as error:
        raise ExpertError(f"pretrain_from: {error} (for {env_id!r}: {found[1]})") from None
