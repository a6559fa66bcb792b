"""What a floor asks from the floors above it, by name: the planners that the environment trains
with, and the client of a planner server.

The environment's ``shield``, ``residual_base`` and ``"action"`` (``"priority"``, ``"advice"``) keys run a
planner inside :meth:`envs.simulation.env.CoopIntersectionEnv.step`. Planners live above the simulation
(:mod:`envs.planners` imports it), so the environment does not build them: it asks this registry for
a maker by name. :mod:`envs.planners` registers its makers when imported; ``envs/__init__.py`` names
it as the provider, imported on the first request, so that a bare environment finds them too.

Makers (name -> what it is called with -> what it returns):

- ``"shield"``: ``(simulation_frequency, max_speed, governor_deceleration)`` -> the training shield
  (``check(scene, proposal)`` -> accelerations, ``last_overridden``),
- ``"residual_base"``: ``(name)`` -> the base planner of a residual policy (``reset(seed)``, ``act(scene)``),
- ``"human"``: ``()`` -> the human driver model of mixed traffic (``act(scene)`` -> accelerations of
  every row; the environment applies those of the human-driven rows),
- ``"priority"``: ``(glide)`` -> the arrival-time scheduler of the ``"priority"`` and ``"advice"`` action
  types, with the parameter set named by the action's ``glide`` (``reset(seed)``, ``schedule(scene, kind,
  offsets)`` -> checked accelerations).

Planner words ``http://HOST:PORT`` (:mod:`envs.planners.loading`) name a planner server, whose client
lives above the planners (:mod:`envs.serve.client` registers these; ``envs/__init__.py`` names it):

- ``"remote_planner"``: ``(address, shielded=False)`` -> the planner that plans through the server,
- ``"remote_planner_name"``: ``(address)`` -> its report name, asked from the server.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

HOOKS = ("shield", "residual_base", "priority", "human", "remote_planner", "remote_planner_name")
_MAKERS: dict[str, Callable[..., Any]] = {}
_PROVIDERS: list[str] = []


def register(name: str, maker: Callable[..., Any]) -> None:
    """Register the maker of one hook (a provider calls this when imported).

    :param name: one of :data:`HOOKS`
    :param maker: see the module docstring
    """
    if name not in HOOKS:
        raise ValueError(f"hook {name!r} is not one of {', '.join(HOOKS)}")
    _MAKERS[name] = maker


def add_provider(module: str) -> None:
    """Name a module that registers makers when imported; it is imported on the first request.

    :param module: dotted module name
    """
    if module not in _PROVIDERS:
        _PROVIDERS.append(module)


def maker(name: str) -> Callable[..., Any]:
    """The maker of hook ``name``, importing the providers first if none registered it yet.

    :param name: one of :data:`HOOKS`
    :raises LookupError: no provider registers it
    """
    if name not in _MAKERS:
        for module in _PROVIDERS:
            importlib.import_module(module)
    try:
        return _MAKERS[name]
    except KeyError:
        raise LookupError(
            f"nothing registered for {name!r}: import envs.planners and envs.serve.client first"
        ) from None
