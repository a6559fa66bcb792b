"""How the world moves and what the learner sees: the intersection, its traffic and the environment.

- :mod:`~envs.simulation.layouts`: the intersections (routes, conflict zones, speed limits),
- :mod:`~envs.simulation.engine`: the vectorized vehicle simulation (:class:`Simulation`, :func:`integrate`),
- :mod:`~envs.simulation.traffic`: the training spawner and the evaluation scenario files,
- :mod:`~envs.simulation.scene`: what a planner sees (:class:`~envs.simulation.scene.Scene`),
- :mod:`~envs.simulation.graph`: the scene as the learner's graph observation,
- :mod:`~envs.simulation.commitment`: who can no longer stop before the conflict zones (the observation and the shield),
- :mod:`~envs.simulation.rewards`: the reward terms and presets,
- :mod:`~envs.simulation.config`: validation of the environment's configuration,
- :mod:`~envs.simulation.env`: the gymnasium environments (``CoopIntersection*-v0``),
- :mod:`~envs.simulation.step_record`: what one step did, typed,
- :mod:`~envs.simulation.free_flow`: free-flow travel times (the reference of the delays),
- :mod:`~envs.simulation.rendering`: episodes drawn as GIF, MP4 or HTML,
- :mod:`~envs.simulation.hooks`: the planners the environment trains with, registered from above.

This package re-exports the engine's names (``from envs.simulation import Simulation``), loaded on
first use so that ``import envs`` stays cheap; the other modules load only when imported (the
environment pulls in torch, the rendering matplotlib).
"""

from __future__ import annotations

from typing import Any

__all__ = ["SPLIT_CLEARANCE", "Simulation", "StepEvents", "integrate", "overlapping_pairs"]


def __getattr__(name: str) -> Any:
    """The engine's names, imported on first use (PEP 562)."""
    if name in __all__:
        from envs.simulation import engine  # highway-env: 2 s, not paid by ``import envs``

        return getattr(engine, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
